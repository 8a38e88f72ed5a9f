"""Coefficient fitting from a table of vibration tests: the exact-expectation prediction of
each row (`predict_table`), the design matrix of the coefficients (`design_matrix`), which
coefficients a test plan can separate (`identifiability`) and the Levenberg-Marquardt fit
(`fit_coefficients`), on tables padded to a power-of-two row count so that one compiled
model and solver serve many plan sizes.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._static import StaticTransferFunction
from .environment import VibrationEnvironment
from .expectation import mean_indicated_acceleration
from .table import validate_vibration_table

FIT_PARAMETERS = ("bias", "scale_factor_error", "asymmetry", "k2", "k3", "k4", "k5")
"""The coefficients `fit_coefficients` estimates by default (m31, m32 are added when the
table has cross-axis vibration)."""


def _row_environment(row: dict) -> VibrationEnvironment:
    zero = jnp.zeros_like(row["vib_amp"])
    amp = jnp.stack([row.get("vib_amp_oa", zero), row.get("vib_amp_pa", zero), row["vib_amp"]])
    rms = jnp.stack([zero, zero, row["vib_rms"]])
    return VibrationEnvironment(sine_amplitude=amp, random_std=rms)


def predict_table(tf: StaticTransferFunction, table: dict, *, n_phase: int = 256) -> Array:
    """Mean indicated acceleration [g] for each row of a test table (exact expectation;
    the frequency column does not enter: δ(ω) is linear and averages out)."""
    rows, n = _padded_rows(table)
    return _predict_rows(tf, rows, n_phase)[:n]


@eqx.filter_jit
def _predict_rows(tf, rows, n_phase):
    def one(row):
        return mean_indicated_acceleration(tf, _row_environment(row), row["a_in"], n_phase=n_phase)

    return jax.vmap(one)(rows)


def _fit_names(table: dict, parameters) -> tuple[str, ...]:
    if parameters is not None:
        unknown = set(parameters) - set(StaticTransferFunction.__dataclass_fields__)
        if unknown:
            raise ValueError(f"fit_coefficients: unknown parameter(s) {sorted(unknown)}.")
        return tuple(parameters)
    names = FIT_PARAMETERS
    if "vib_amp_oa" in table and np.any(np.asarray(table["vib_amp_oa"]) > 0):
        names += ("m31",)
    if "vib_amp_pa" in table and np.any(np.asarray(table["vib_amp_pa"]) > 0):
        names += ("m32",)
    return names


def _tf_from(names, theta, base):
    return eqx.tree_at(
        lambda t: tuple(getattr(t, n) for n in names),
        base,
        tuple(theta[i] * PPM_SCALE for i in range(len(names))),
    )


PPM_SCALE = 1e-6
"""The fit works in ppm-scaled parameters (θ = coefficient / 1e-6) for conditioning."""


def design_matrix(table: dict, parameters=None, *, n_phase: int = 256) -> Array:
    """∂a_out/∂coefficient for every row and fitted coefficient (rows × parameters), in g
    per ppm. The model is linear in the coefficients, so this Jacobian is the whole model."""
    cols = validate_vibration_table(table)
    names = _fit_names(cols, parameters)
    theta0 = jnp.zeros(len(names))
    rows, n = _padded_rows(cols)
    return _design(names, n_phase)(theta0, rows, StaticTransferFunction())[:n]


def _rows(cols: dict) -> dict:
    return {c: jnp.asarray(v) for c, v in cols.items() if c != "a_out"}


_MIN_ROWS = 16


def _padded_rows(cols: dict) -> tuple[dict, int]:
    # Tables are padded to a power-of-two number of rows (at least 16) by repeating the last
    # row, so that tables of different lengths share one compiled model and solver (a study
    # compares many test plans); callers drop (or mask) the padding.
    rows = _rows(cols)
    n = int(jnp.shape(rows["a_in"])[0])
    size = max(_MIN_ROWS, 1 << max(n - 1, 0).bit_length())
    if size > n:
        rows = {c: jnp.concatenate([v, jnp.repeat(v[-1:], size - n)]) for c, v in rows.items()}
    return rows, n


@functools.lru_cache(maxsize=32)
def _residual_fn(names: tuple[str, ...], n_phase: int):
    # One function object per (coefficients, quadrature): optimistix's and jit's caches
    # then reuse the compiled solver for every table of the same shape.
    def residual(theta, args):
        rows, y, mask, base = args  # padded rows (`_padded_rows`); mask = 0 on the padding
        prediction = _predict_rows(_tf_from(names, theta, base), rows, n_phase)
        return mask * (prediction - y) / 1e-6

    return residual


@functools.lru_cache(maxsize=32)
def _design(names: tuple[str, ...], n_phase: int):
    @eqx.filter_jit
    def design(theta, rows, base):
        return jax.jacfwd(lambda th: _predict_rows(_tf_from(names, th, base), rows, n_phase))(theta)

    return design


class Identifiability(eqx.Module):
    """Which coefficients a test plan can separate.

    **Fields:**

    - `names`: the coefficients (static).
    - `unexplained_fraction`: per coefficient, |residual of its design column projected on
      the other columns| / |column| — 0 when the column is a combination of the others
      (not identifiable: e.g. k3 vs the scale factor at ±1 g alone), 1 when orthogonal.
    - `identifiable`: unexplained_fraction > 1e-6.
    - `standard_error_ppm`: per coefficient, the standard error [ppm units] for an output
      noise of `noise` g per row; inf for every coefficient when any one is not
      identifiable (fit fewer coefficients, or extend the plan).
    - `singular_values`: of the design matrix (g per ppm).
    """

    names: tuple[str, ...] = eqx.field(static=True)
    unexplained_fraction: Array
    identifiable: Array
    standard_error_ppm: Array
    singular_values: Array


def identifiability(
    table: dict, parameters=None, *, noise: float = 1e-6, n_phase: int = 256
) -> Identifiability:
    """Identifiability of the coefficients from a test plan (the `a_out` column is not
    used; pass zeros for a plan not yet run). `noise` [g] is the standard deviation of
    each row's mean output. Precision: float64 advised."""
    if not noise > 0:
        raise ValueError(f"identifiability: noise must be positive, got {noise!r} g.")
    cols = validate_vibration_table(table)
    names = _fit_names(cols, parameters)
    J = np.asarray(design_matrix(cols, names, n_phase=n_phase), dtype=np.float64)
    p = J.shape[1]
    frac = np.empty(p)
    for j in range(p):
        others = np.delete(J, j, axis=1)
        coef, *_ = np.linalg.lstsq(others, J[:, j], rcond=None)
        frac[j] = np.linalg.norm(J[:, j] - others @ coef) / max(np.linalg.norm(J[:, j]), 1e-300)
    ident = frac > 1e-6
    se = np.full(p, np.inf)
    if np.all(ident) and J.shape[0] >= p:
        se = noise * np.sqrt(np.diag(np.linalg.inv(J.T @ J)))
    return Identifiability(
        names=names,
        unexplained_fraction=jnp.asarray(frac),
        identifiable=jnp.asarray(ident),
        standard_error_ppm=jnp.asarray(se),
        singular_values=jnp.asarray(np.linalg.svd(J, compute_uv=False)),
    )


class CoefficientFit(eqx.Module):
    """Least-squares estimate of the transfer-function coefficients from a test table.

    **Fields:**

    - `transfer_function`: the fitted `StaticTransferFunction` (others at their initial value).
    - `names`: the fitted coefficients (static).
    - `estimate_ppm`, `standard_error_ppm`: per fitted coefficient [ppm units; bias in ppm
      of g, i.e. µg].
    - `correlation`: their correlation matrix [1].
    - `residual_rms`: RMS of the residuals [g].
    - `result`: the optimistix result code.
    """

    transfer_function: StaticTransferFunction
    names: tuple[str, ...] = eqx.field(static=True)
    estimate_ppm: Array
    standard_error_ppm: Array
    correlation: Array
    residual_rms: Array
    result: object


def fit_coefficients(
    table: dict,
    parameters=None,
    *,
    initial: StaticTransferFunction | None = None,
    noise: float | None = None,
    n_phase: int = 256,
    throw: bool = True,
) -> CoefficientFit:
    """Fit a0, the scale-factor error δ, A1, k2..k5 (and m31, m32 if the table has
    cross-axis vibration) to a table of tests by optimistix Levenberg-Marquardt least
    squares on the exact expectation of the output.

    **Arguments:**

    - `table`: the test table (`read_vibration_table` or a dict of columns) [g, Hz].
    - `parameters`: the coefficient names to fit (default: `FIT_PARAMETERS` + m3i).
    - `initial`: starting / fixed values of the other coefficients (default zeros).
    - `noise`: known standard deviation of a_out [g]; default: estimated from the
      residuals (RSS/(n − p)).
    - `throw`: raise if the solver fails (batch sweeps pass False and read `result`).

    A host-level function (it validates the table with NumPy): call it outside `jit`; the
    solver inside is compiled and cached per (coefficients, table size).

    **Returns:** a `CoefficientFit`. Standard errors from σ² (JᵀJ)⁻¹; a plan in which a
    coefficient is not identifiable (see `identifiability`) gives infinite/NaN errors —
    check it first. float64 advised.
    """
    import optimistix as optx

    cols = validate_vibration_table(table)
    names = _fit_names(cols, parameters)
    n, p = cols["a_in"].shape[0], len(names)
    if n < p:
        raise ValueError(
            f"fit_coefficients: {n} test rows cannot determine {p} coefficients {names}."
        )
    base = StaticTransferFunction() if initial is None else initial
    theta0 = jnp.asarray([float(getattr(base, nm)) / PPM_SCALE for nm in names])
    rows, _ = _padded_rows(cols)
    size = int(jnp.shape(rows["a_in"])[0])
    y = jnp.zeros(size).at[:n].set(jnp.asarray(cols["a_out"]))
    mask = (jnp.arange(size) < n).astype(y.dtype)
    args = (rows, y, mask, base)
    residual = _residual_fn(names, n_phase)
    solver = optx.LevenbergMarquardt(rtol=1e-12, atol=1e-12)
    sol = optx.least_squares(residual, solver, theta0, args, max_steps=256, throw=throw)
    theta = sol.value
    r = residual(theta, args)[:n] * 1e-6
    J = _design(names, n_phase)(theta, rows, base)[:n]  # g per ppm (the model is linear)
    sigma2 = noise**2 if noise is not None else jnp.sum(r**2) / max(n - p, 1)
    cov = sigma2 * jnp.linalg.inv(J.T @ J)
    se = jnp.sqrt(jnp.diag(cov))
    return CoefficientFit(
        transfer_function=_tf_from(names, theta, base),
        names=names,
        estimate_ppm=theta,
        standard_error_ppm=se,
        correlation=cov / jnp.outer(se, se),
        residual_rms=jnp.sqrt(jnp.mean(r**2)),
        result=sol.result,
    )


def greedy_test_plan(
    design: np.ndarray, target_standard_error: np.ndarray, *, max_rows: int = 30
) -> tuple[list[int], list[dict]]:
    """A test plan for `fit_coefficients`: rows of a candidate grid chosen one at a time,
    each maximising log det(JᵀJ) of the rows so far (greedy D-optimal design), until every
    coefficient's standard error √diag((JᵀJ)⁻¹) is at or below its target.

    **Arguments:**

    - `design`: J, the candidate rows' design matrix (`design_matrix` of the grid), shape
        (rows, coefficients), in the units of the fit (e.g. ppm per unit noise σ).
    - `target_standard_error`: the largest acceptable standard error per coefficient, in
        units of the noise σ (shape (coefficients,)).
    - `max_rows`: the most rows chosen.

    **Returns:** (the chosen row indices in order — a row may repeat, i.e. a repeated
    test — and the history: after each row that makes J full rank, the largest standard
    error over its target). Host-side NumPy; a tiny ridge (1e-12) keeps log det finite
    while fewer rows than coefficients are chosen.
    """
    design = np.asarray(design, dtype=float)
    target = np.asarray(target_standard_error, dtype=float)
    if design.ndim != 2 or target.shape != (design.shape[1],):
        raise ValueError(
            f"greedy_test_plan: design must be (rows, coefficients) and the targets one per "
            f"coefficient; got {design.shape} and {target.shape}."
        )
    if not (np.all(np.isfinite(design)) and np.all(np.isfinite(target)) and np.all(target > 0)):
        raise ValueError(
            "greedy_test_plan: the design must be finite and the targets finite and positive."
        )
    n_coefficients = design.shape[1]
    if np.linalg.matrix_rank(design) < n_coefficients:
        raise ValueError(
            f"greedy_test_plan: the candidate rows cannot identify all {n_coefficients} "
            f"coefficients (design rank {np.linalg.matrix_rank(design)}); add rows that move "
            "the missing ones (e.g. other input levels or vibration amplitudes)."
        )
    chosen: list[int] = []
    history = []
    for _ in range(max_rows):
        best, best_value = None, -np.inf
        for i in range(design.shape[0]):
            rows = design[chosen + [i]]
            value = np.linalg.slogdet(rows.T @ rows + 1e-12 * np.eye(n_coefficients))[1]
            if value > best_value:
                best, best_value = i, value
        if best is None:  # every candidate's log-determinant NaN or −∞
            raise ValueError("greedy_test_plan: no candidate row gives a finite log-determinant.")
        chosen.append(best)
        rows = design[chosen]
        if len(chosen) >= n_coefficients and np.linalg.matrix_rank(rows) == n_coefficients:
            standard_error = np.sqrt(np.diag(np.linalg.inv(rows.T @ rows)))
            history.append(
                {
                    "rows": len(chosen),
                    "max_se_over_target": float(np.max(standard_error / target)),
                }
            )
            if np.all(standard_error <= target):
                break
    return chosen, history
