"""The vibration diagnosis's view of a table (`prepare`, a `VibrationTable`): the
exact-expectation design matrix, the coefficients each candidate frees (those the table can
see: `IDENTIFIABLE`), and the cross-validation folds over rows (`MAX_FOLDS`)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..._data import DataError, VibrationData
from ..._static import PPM
from ..._vibration import design_matrix
from .effects import COEFFICIENTS, AbstractVibrationEffect
from .state import VibrationTable

MAX_FOLDS = 60
"""Cross-validation folds: one per row (leave-one-out) up to this many rows."""

_FOLD_SEED = 20260601  # fixed: the fold assignment of larger tables is deterministic

N_PHASE = 256
"""Phase quadrature points of the exact expectation (exact for the polynomial terms)."""

IDENTIFIABLE = 1e-6
"""A coefficient whose design column keeps less than this fraction of its norm after
projection on the nominal columns cannot be seen in the table (e.g. k3 with no vibration
and a_in = ±1 g only, where a³ = a)."""


def padded_rows(n: int) -> int:
    """The row count a table's fits are compiled for: a power of two, at least 16 (the
    padding rows have weight 0 in every fit), so that tables of several sizes share one
    program."""
    return max(16, 1 << max(n - 1, 0).bit_length())


def _unexplained(columns: np.ndarray, basis: np.ndarray) -> np.ndarray:
    """Per column of `columns`, |residual after projection on `basis`| / |column|."""
    if basis.shape[1] == 0:
        return np.ones(columns.shape[1])
    coef, *_ = np.linalg.lstsq(basis, columns, rcond=None)
    residual = columns - basis @ coef
    norms = np.linalg.norm(columns, axis=0)
    return np.where(norms > 0, np.linalg.norm(residual, axis=0) / np.maximum(norms, 1e-300), 0.0)


def prepare(data: VibrationData, effects: Sequence[AbstractVibrationEffect]) -> VibrationTable:
    """Host side: the design matrix, the free coefficients of each candidate, the folds (a
    `DataError` where the table has no design matrix)."""
    out = np.asarray(data.a_out)
    if np.ptp(out) == 0 and np.ptp(np.asarray(data.a_in)) > 0:
        # As a step record's constant u_out: a dead output would read as a scale factor of
        # zero (δ = −1e6 ppm), "closed by the refit" (a user's trial read `none`).
        raise DataError(
            f"vibration table: a_out is {out[0]:.6g} g in every row while a_in varies; no "
            "response to diagnose (a disconnected or saturated channel?)."
        )
    table = data.table()
    try:
        design = np.asarray(design_matrix(table, COEFFICIENTS, n_phase=N_PHASE)) / PPM
    except ValueError as error:
        raise DataError(f"vibration table: {error}") from None
    n = design.shape[0]
    target = (np.asarray(data.a_out) - np.asarray(data.a_in)) / PPM
    index = {c: j for j, c in enumerate(COEFFICIENTS)}
    notes = []
    columns = [np.asarray(v, np.float64) for v in table.values()]
    rows = np.stack(columns, axis=1)
    copies = rows.shape[0] - np.unique(rows, axis=0).shape[0]
    if copies:
        # Repeated conditions are repeats, but a row equal to another in every column,
        # a_out to the last digit, is more likely pasted twice: counted as a measurement
        # it shrinks the standard errors. Said, not removed.
        notes.append(
            f"{copies} row(s) equal another row in every column, a_out included: repeated "
            "measurements agree to the last digit only by chance; a row pasted twice counts "
            "as two measurements and shrinks the standard errors."
        )
    nominal = [index["bias"]]
    if _unexplained(design[:, [index["scale_factor_error"]]], design[:, nominal])[0] > IDENTIFIABLE:
        nominal.append(index["scale_factor_error"])
    else:
        notes.append(
            "one input level only: the scale factor cannot be told from the bias (δ held at 0, "
            "the bias absorbs a0 + δ·a_in)."
        )
    masks = []
    free = {}
    unavailable = {}
    for effect in effects:
        reason = effect.unavailable(data)
        columns = []
        if reason is None:
            basis = list(nominal)
            for coefficient in effect.coefficients:
                j = index[coefficient]
                if _unexplained(design[:, [j]], design[:, basis])[0] > IDENTIFIABLE:
                    columns.append(j)
                    basis.append(j)
            if not columns:
                reason = (
                    f"{effect.name} left out: with this table its term "
                    f"({', '.join(effect.coefficients)}) is a combination of the bias and "
                    "scale-factor terms (extend the plan: more input levels or vibration)."
                )
        if reason is not None:
            unavailable[effect.name] = reason
            notes.append(reason)
            continue
        free[effect.name] = columns
    candidates = ["nominal"] + list(free)
    for name in candidates:
        mask = np.zeros(len(COEFFICIENTS))
        mask[nominal] = 1
        mask[free.get(name, [])] = 1
        masks.append(mask)
    folds = min(MAX_FOLDS, n)
    if folds == n:
        fold_of_row = np.arange(n)
    else:
        fold_of_row = np.random.default_rng(_FOLD_SEED).permutation(n) % folds
    weights = np.ones((1 + folds, n))
    for k in range(folds):
        weights[1 + k, fold_of_row == k] = 0.0
    return VibrationTable(
        design=design,
        target=target,
        masks=np.stack(masks),
        weights=weights,
        candidates=tuple(candidates),
        free=free,
        nominal_columns=tuple(nominal),
        fold_of_row=fold_of_row,
        unavailable=unavailable,
        notes=tuple(notes),
    )
