"""The `vibration` kind: a table of shaker/tumble tests, its nominal model and its effects.

**Nominal model** (the idealised transfer function the paper's shaker method assumes,
docs/models.md §3): a linear transfer function, bias and scale factor only,

    a_out = a0 + (1 + δ) a_in                                                        [g],

fitted freely to the rows (there is no prior: `NominalDevice` describes the servo loop and
does not enter this kind). With a single input level a_in the scale factor cannot be told
from the bias; δ is then held at 0 and the bias absorbs both (a note says so).

**Effects** (each adds coefficients of the static transfer function, docs/models.md §3 eq. (1),
and is exactly the nominal model when they are zero):

- `k2`, `k3`, `k4`, `k5`: the nonlinearity k_n a3ⁿ, whose time average under vibration
  rectifies (k2 b²/2, 1.5 k3 a b², …);
- `asymmetry`: the scale-factor asymmetry ½ A1 |a3|, which rectifies when the vibration
  crosses zero;
- `cross_coupling`: m31 a3 a1 + m32 a3 a2, which rectifies as ½ m3i b3 bi for in-phase
  sinusoids on the input and a cross axis. Only a table with cross-axis vibration columns
  (`vib_amp_oa`, `vib_amp_pa`, see `accel_jax._data.OPTIONAL_COLUMNS`) can show it: without
  them (or with them all zero) the effect is left out of the candidates and a note says so.

The mean output of every row is the exact expectation of `accel_jax._vibration`
(`design_matrix`: quadrature over the sine phase and the Gaussian random part, exact for the
polynomial terms and for |a3| with a sinusoid). The model is linear in the coefficients, so
that Jacobian is the whole model: a_out = a_in + J θ (θ in ppm). Every candidate and every
cross-validation fold is solved by optimistix least squares (Gauss–Newton, SVD solve)
on that design, all of a
table's fits in one vmapped call (`fit_coefficients` fits one table per call and compiles
per table size; the tests check the two agree).

**Held out**: cross-validation over rows: leave-one-out for tables of up to `MAX_FOLDS`
rows, else `MAX_FOLDS` folds with a fixed scrambled assignment (a test table is usually
ordered by condition; interleaving by row number would hold out whole conditions, e.g. every
cross-axis row at once). Each row is predicted by the fit that did not see it. The evidence
(2 ln B, BIC scale, noise variance profiled out) is from the fit to all rows.

Float64 throughout (ppm-level differences of O(1 g) numbers).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx

from .._data import DataError, NominalDevice, VibrationData
from .._static import PPM
from .._vibration import design_matrix
from . import openworld
from .base import (
    CandidateFit,
    DiagnosisResult,
    effect_library,
    held_out_gap,
    ljung_box,
    rank_candidates,
    require_float64,
)
from .vibration_effects import COEFFICIENTS, AbstractVibrationEffect

MAX_FOLDS = 60
"""Cross-validation folds: one per row (leave-one-out) up to this many rows."""

_FOLD_SEED = 20260601  # fixed: the fold assignment of larger tables is deterministic

N_PHASE = 256
"""Phase quadrature points of the exact expectation (exact for the polynomial terms)."""

IDENTIFIABLE = 1e-6
"""A coefficient whose design column keeps less than this fraction of its norm after
projection on the nominal columns cannot be seen in the table (e.g. k3 with no vibration
and a_in = ±1 g only, where a³ = a)."""


FIT_TOLERANCE = 1e-10
"""rtol = atol of the least-squares fits (ppm-scaled coefficients and residuals)."""


# Fits
# --------------------------------------------------------------------------------------


def _effects() -> list[AbstractVibrationEffect]:
    return [cls() for cls in effect_library("vibration").values()]


def _fit_table(design, target, masks, weights):
    """Least squares of every candidate (rows of `masks`: 1 where a coefficient is free)
    on every row subset (rows of `weights`: 1 where a row is fitted), vmapped. Coefficients
    that are not free are pinned at 0 by extra residuals; a_out − a_in = J θ (ppm)."""

    def fit_one(mask, weight):
        def residuals(theta, _):
            data = weight * (design @ (mask * theta) - target)
            return jnp.concatenate([data, (1 - mask) * theta])

        # Gauss–Newton with an SVD solve: the problem is linear, so the first step lands on
        # the least-squares solution and the second confirms it; the SVD keeps a fold whose
        # training rows cannot determine a coefficient finite (minimum-norm solution).
        solver = optx.GaussNewton(rtol=FIT_TOLERANCE, atol=FIT_TOLERANCE, linear_solver=lx.SVD())
        solution = optx.least_squares(
            residuals, solver, jnp.zeros(design.shape[1]), max_steps=16, throw=False
        )
        theta = mask * solution.value
        return theta, solution.result == optx.RESULTS.successful

    per_fold = jax.vmap(fit_one, in_axes=(None, 0))
    return jax.vmap(per_fold, in_axes=(0, None))(masks, weights)


_fit_tables = eqx.filter_jit(jax.vmap(_fit_table))


def _unexplained(columns: np.ndarray, basis: np.ndarray) -> np.ndarray:
    """Per column of `columns`, |residual after projection on `basis`| / |column|."""
    if basis.shape[1] == 0:
        return np.ones(columns.shape[1])
    coef, *_ = np.linalg.lstsq(basis, columns, rcond=None)
    residual = columns - basis @ coef
    norms = np.linalg.norm(columns, axis=0)
    return np.where(norms > 0, np.linalg.norm(residual, axis=0) / np.maximum(norms, 1e-300), 0.0)


def _prepare(data: VibrationData, effects) -> dict:
    """Host side: the design matrix, the free coefficients of each candidate, the folds."""
    table = data.table()
    try:
        design = np.asarray(design_matrix(table, COEFFICIENTS, n_phase=N_PHASE)) / PPM
    except ValueError as error:
        raise DataError(f"vibration table: {error}") from None
    n = design.shape[0]
    target = (np.asarray(data.a_out) - np.asarray(data.a_in)) / PPM
    index = {c: j for j, c in enumerate(COEFFICIENTS)}
    notes = []
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
    return {
        "design": design,
        "target": target,
        "masks": np.stack(masks),
        "weights": weights,
        "candidates": candidates,
        "free": free,
        "nominal_columns": nominal,
        "fold_of_row": fold_of_row,
        "unavailable": unavailable,
        "notes": notes,
    }


# --------------------------------------------------------------------------------------
# Host side: evidence, localisation, result
# --------------------------------------------------------------------------------------


def _rss_floor(target: np.ndarray) -> float:
    # Rounding floor of the residual sum of squares (ppm²): keeps ln(RSS) finite on exact data.
    return target.size * (1e-9 * max(float(np.max(np.abs(target))), 1.0)) ** 2


def _group(keys: np.ndarray, residual: np.ndarray, label: str, unit: str) -> list[dict]:
    out = []
    for value in np.unique(keys):
        rows = keys == value
        out.append(
            {
                label: float(value),
                "rows": int(np.sum(rows)),
                f"mean_residual_{unit}": float(np.mean(residual[rows])),
                f"rms_residual_{unit}": float(np.sqrt(np.mean(residual[rows] ** 2))),
            }
        )
    return out


def _localise(data: VibrationData, residual: np.ndarray, sigma: float, prep: dict) -> dict:
    """Where the nominal refit's residual lies: per row, by input level, by vibration level
    (mean square of the input-axis vibration, b²/2 + σ²), by cross-axis vibration and by
    frequency; and its whiteness across rows (in table order and sorted by condition)."""
    a_in = np.asarray(data.a_in)
    power = np.asarray(data.vib_amp) ** 2 / 2 + np.asarray(data.vib_rms) ** 2
    freq = np.asarray(data.vib_freq)
    n = residual.size
    standardised = residual / sigma if sigma > 0 else np.zeros_like(residual)
    rows = [
        {
            "row": i,
            "a_in_g": float(a_in[i]),
            "vib_amp_g": float(data.vib_amp[i]),
            "vib_rms_g": float(data.vib_rms[i]),
            "vib_freq_Hz": float(freq[i]),
            "residual_g": float(residual[i]),
            "standardised": float(standardised[i]),
        }
        for i in range(n)
    ]
    where = {
        "conditions": rows,
        "by_input_level": _group(np.round(a_in, 9), residual, "a_in_g", "g"),
        "by_vibration_level": _group(np.round(power, 9), residual, "vibration_mean_square_g2", "g"),
    }
    for column, axis in (("vib_amp_oa", "OA"), ("vib_amp_pa", "PA")):
        values = getattr(data, column)
        if values is not None:
            where[f"by_cross_axis_{axis}"] = _group(
                np.round(np.asarray(values), 9), residual, f"{column}_g", "g"
            )
    vibrating = np.asarray(data.vib_amp) > 0
    if np.unique(freq[vibrating]).size > 1:
        # Frequency should not matter to a static transfer function (δ(ω) is linear and
        # averages out): a residual that follows it points at dynamics outside the model.
        terciles = np.quantile(freq[vibrating], [1 / 3, 2 / 3])
        band = np.digitize(freq, terciles)
        where["by_vibration_frequency"] = [
            {
                "band": int(b),
                "frequency_range_Hz": [
                    float(freq[vibrating & (band == b)].min()),
                    float(freq[vibrating & (band == b)].max()),
                ],
                "rows": int(np.sum(vibrating & (band == b))),
                "rms_residual_g": float(np.sqrt(np.mean(residual[vibrating & (band == b)] ** 2))),
            }
            for b in range(3)
            if np.any(vibrating & (band == b))
        ]
    order = np.lexsort((power, a_in))
    lags = max(1, min(10, n // 4))
    where["whiteness"] = ljung_box(residual, lags=lags)
    where["whiteness_sorted_by_condition"] = ljung_box(residual[order], lags=lags)
    where["largest_standardised_residual"] = {
        "row": int(np.argmax(np.abs(standardised))),
        "value": float(standardised[np.argmax(np.abs(standardised))]),
    }
    where["noise_sigma_g"] = sigma
    where["not_identifiable"] = dict(prep["unavailable"])
    return where


def _postprocess(data: VibrationData, prep: dict, effects, thetas, converged) -> DiagnosisResult:
    design, target = prep["design"], prep["target"]
    n = target.size
    fold_of_row = prep["fold_of_row"]
    by_effect = {e.name: e for e in effects}
    floor_rss = _rss_floor(target)
    fits, full_predictions, cv_errors = [], {}, {}
    standard_errors = {}
    nominal_se = None
    for c, name in enumerate(prep["candidates"]):
        theta_full = thetas[c, 0]
        prediction = design @ theta_full
        rss = max(float(np.sum((prediction - target) ** 2)), floor_rss)
        free = np.flatnonzero(prep["masks"][c])
        p = free.size
        fold_predictions = design @ thetas[c, 1:].T  # (n, folds)
        cv = (fold_predictions[np.arange(n), fold_of_row] - target) * PPM  # g
        sigma2 = rss / max(n - p, 1)
        covariance = sigma2 * np.linalg.pinv(design[:, free].T @ design[:, free])
        se_all = np.full(len(COEFFICIENTS), np.nan)
        se_all[free] = np.sqrt(np.clip(np.diag(covariance), 0, None))
        params = {}
        k = 0
        if name != "nominal":
            effect = by_effect[name]
            columns = [COEFFICIENTS.index(c_) for c_ in effect.coefficients]
            standard_errors[name] = se_all[columns]
            params = effect.physical(theta_full[columns], {"standard_errors": standard_errors})
            k = len(prep["free"][name])
        full_predictions[name] = prediction
        cv_errors[name] = cv
        fits.append(
            CandidateFit(
                effect=name,
                n_effect_params=k,
                log_likelihood=float(-0.5 * n * np.log(rss / n)),
                n_train=n,
                held_out_ms=float(np.mean(cv**2)),
                held_out_errors=cv,
                train_ms=sigma2 * PPM**2,
                params=params,
                converged=bool(np.all(converged[c])),
            )
        )
        if name == "nominal":
            nominal_se = se_all
    assert nominal_se is not None  # "nominal" is always the first candidate (`_prepare`)
    _, ranking, _ = rank_candidates(fits[0], fits[1:])
    floor = min(f.train_ms for f in fits)
    by_name = {f.effect: f for f in fits}
    # Open world: with repeated test conditions the table carries its own noise floor (pure
    # error), and a model that leaves a significant lack of fit does not explain it.
    # Without repeats the floor is the fit's own residual and no such test exists.
    replicates = _pure_error(data, target)
    lack = {}
    for fit in fits:
        free = len(prep["free"].get(fit.effect, ())) if fit.effect != "nominal" else None
        p = len(prep["nominal_columns"]) + (free or 0)
        rss = fit.train_ms * max(n - p, 1) / PPM**2
        lack[fit.effect] = _lack_of_fit(rss, p, replicates)
    for entry in ranking:
        entry.update(
            {
                "stochastic": False,
                "explains": lack[entry["effect"]]["explains"],
                "plausible": entry["converged"],
            }
        )
    nominal_status = {"explains": lack["nominal"]["explains"], "white": True, "plausible": True}
    for entry in ranking:
        g = held_out_gap(
            fits[0].held_out_errors, by_name[entry["effect"]].held_out_errors, floor, block=1
        )
        entry["explained_fraction"] = openworld.explained_fraction(g["before"], g["after"])
    decision = openworld.decide(nominal_status, ranking)
    verdict, tied = decision["verdict"], decision["tied"]
    for entry in ranking:
        g = held_out_gap(
            fits[0].held_out_errors, by_name[entry["effect"]].held_out_errors, floor, block=1
        )
        entry["gap_shrink"] = g["shrink"]
    chosen = decision["chosen"] or decision["best_partial"] or "nominal"
    after = by_name[chosen].held_out_errors
    gap = held_out_gap(fits[0].held_out_errors, after, floor, block=1)
    gap["unit"] = "g"
    gap["model_after"] = chosen
    folds = len(prep["weights"]) - 1
    gap["held_out"] = (
        "leave-one-out cross-validation over rows"
        if folds == n
        else f"{folds}-fold cross-validation over rows (fixed scrambled assignment)"
    )

    # The refit: bias and scale factor of the nominal transfer function, fitted freely.
    theta_nominal = thetas[0, 0]
    residual_ideal = np.asarray(data.a_out) - np.asarray(data.a_in)
    residual_nominal = (full_predictions["nominal"] - target) * -PPM  # measured − model [g]
    rms_before = float(np.sqrt(np.mean(residual_ideal**2)))
    rms_after = float(np.sqrt(np.mean(residual_nominal**2)))
    sigma = float(np.sqrt(floor))
    ib, isf = COEFFICIENTS.index("bias"), COEFFICIENTS.index("scale_factor_error")
    bias_g = float(theta_nominal[ib] * PPM)
    delta = float(theta_nominal[isf] * PPM)
    refit = {
        "parameters": {},
        "nominal_fit": {
            "bias_g": bias_g,
            "bias_se_g": float(nominal_se[ib] * PPM),
            "scale_factor_error": delta,
            "scale_factor_error_se": (
                float(nominal_se[isf] * PPM) if isf in prep["nominal_columns"] else None
            ),
        },
        "model": "a_out = a0 + (1 + δ) a_in (no prior; the servo device file does not enter)",
        "rms_before_refit_g": rms_before,
        "rms_after_refit_g": rms_after,
        "gap_closed_by_refit": 1 - rms_after / rms_before if rms_before > 0 else 0.0,
        "converged": bool(np.all(converged[0])),
    }
    refit["parameter_error"] = bool(
        verdict == "none" and rms_before > 3 * sigma and rms_after < 1.5 * sigma
    )
    scale_text = (
        f"δ = {delta / PPM:.4g} ± {nominal_se[isf]:.2g} ppm"
        if isf in prep["nominal_columns"]
        else "δ held at 0 (one input level)"
    )
    refit["description"] = (
        f"a0 = {bias_g * 1e3:.4g} ± {nominal_se[ib] * PPM * 1e3:.2g} mg, {scale_text}; "
        f"RMS residual to a_out = a_in {rms_before:.3g} g → {rms_after:.3g} g after the refit"
    )
    where = _localise(data, residual_nominal, sigma, prep)
    best = full_predictions[chosen]
    traces = {
        "row": np.arange(n),
        "a_in": np.asarray(data.a_in),
        "vibration_mean_square": np.asarray(data.vib_amp) ** 2 / 2 + np.asarray(data.vib_rms) ** 2,
        "measured": np.asarray(data.a_out),
        "nominal": np.asarray(data.a_in) + full_predictions["nominal"] * PPM,
        "best": np.asarray(data.a_in) + best * PPM,
        "best_name": chosen,
        "residual_before": residual_nominal,
        "residual_after": (target - best) * PPM if verdict != "none" else residual_nominal,
        "held_out_before": fits[0].held_out_errors,
        "held_out_after": after,
    }
    notes = list(prep["notes"])
    if replicates["dof"] < 3:
        notes.append(
            "no repeated test conditions: the noise floor is the fit's own residual, so a "
            "misfit outside the effect library would not show (repeat some rows to test it)"
        )
    where["lack_of_fit"] = lack
    entry = {e["effect"]: e for e in ranking}
    fraction = entry[chosen]["explained_fraction"] if chosen in entry else 0.0
    remaining_gap = {
        "g": gap["after"],
        "noise_floor_g": sigma,
        "over_floor": gap["after"] / sigma if sigma > 0 else float("inf"),
        "model": chosen,
    }
    return DiagnosisResult(
        kind="vibration",
        verdict=verdict,
        tied=tied,
        ranking=ranking,
        gap=gap,
        where=where,
        refit=refit,
        traces=traces,
        notes=notes,
        explained_fraction=fraction,
        remaining_gap=remaining_gap,
        reason=_reason(decision, entry, lack, gap, sigma),
    )


LACK_OF_FIT_LEVEL = 1e-3
"""A model leaves a significant lack of fit (F-test against the pure error of repeated
test conditions) below this p-value."""


def _pure_error(data: VibrationData, target: np.ndarray) -> dict:
    """Pure-error sum of squares and its degrees of freedom from rows with the same test
    condition (a_in, amplitudes, random level; the frequency does not enter the model)."""
    columns = [data.a_in, data.vib_amp, data.vib_rms]
    columns += [c for c in (data.vib_amp_oa, data.vib_amp_pa) if c is not None]
    keys = np.round(np.stack([np.asarray(c) for c in columns], 1), 12)
    _, group = np.unique(keys, axis=0, return_inverse=True)
    group = np.asarray(group).ravel()
    ss, dof = 0.0, 0
    for g in np.unique(group):
        values = target[group == g] / PPM
        if values.size > 1:
            ss += float(np.sum((values - values.mean()) ** 2))
            dof += values.size - 1
    return {"ss": ss, "dof": dof, "groups": int(np.unique(group).size)}


def _lack_of_fit(rss: float, n_params: int, pure: dict) -> dict:
    from jax.scipy.special import betainc

    dof_lof = pure["groups"] - n_params
    if pure["dof"] < 3 or dof_lof < 1 or pure["ss"] <= 0:
        return {"testable": False, "explains": True}
    ss_lof = max(rss - pure["ss"], 0.0)
    f = (ss_lof / dof_lof) / (pure["ss"] / pure["dof"])
    x = dof_lof * f / (dof_lof * f + pure["dof"])
    p_value = float(1 - betainc(dof_lof / 2, pure["dof"] / 2, x))
    return {
        "testable": True,
        "F": f,
        "dof": [dof_lof, pure["dof"]],
        "p_value": p_value,
        "explains": bool(p_value >= LACK_OF_FIT_LEVEL),
    }


def _reason(decision, entry, lack, gap, sigma) -> str:
    verdict = decision["verdict"]
    if verdict == "none":
        return "no effect is significant (2 ln B < 10 or no cross-validated improvement)."
    if verdict == "cannot_tell":
        a, b = decision["tied"]
        return (
            f"{a} and {b} both fit and their evidence differs by "
            f"{abs(entry[a]['evidence'] - entry[b]['evidence']):.1f} (< 6 on the 2 ln B scale): "
            "their rectified terms are nearly collinear over this test plan."
        )
    if verdict != "unexplained":
        return (
            f"{verdict} is significant (2 ln B = {entry[verdict]['evidence']:.1f}) and shrinks "
            f"the cross-validated gap from {gap['before']:.3g} g to {gap['after']:.3g} g."
        )
    best = decision["best_partial"]
    text = "the repeated test conditions show a lack of fit that no library effect removes"
    if best:
        text += (
            f" (best: {best}, F-test p = {lack[best]['p_value']:.2g}; it explains "
            f"{entry[best]['explained_fraction']:.0%} of the cross-validated excess)"
        )
    return text + "."


def diagnose_vibration(
    datasets: list[VibrationData], nominal: NominalDevice | None = None
) -> list[DiagnosisResult]:
    """Diagnose vibration tables (docs/models.md §5, `vibration` kind).

    For each table: the exact-expectation design matrix (`accel_jax._vibration`), then the
    nominal model and each available effect fitted to all rows and to every
    cross-validation fold (one vmapped optimistix call for every table with the same
    number of rows), the ranking by evidence (`rank_candidates`), the held-out gap on the
    cross-validated rows, and the localisation of the nominal residual across conditions.

    **Arguments:**

    - `datasets`: validated `VibrationData` tables (e.g. from `read_csv`).
    - `nominal`: ignored (the servo device has no parameter in this kind's nominal model);
        accepted for the common `diagnose` interface.

    **Returns:** one `DiagnosisResult` per table, in order. Float64 (needs x64 enabled;
    a `ValueError` otherwise).
    """
    require_float64("vibration errors are ppm-level differences of O(1 g) outputs")
    del nominal
    effects = _effects()
    preps = [_prepare(data, effects) for data in datasets]
    results: dict[int, DiagnosisResult] = {}  # by table, every one in one group
    groups: dict[tuple, list[int]] = {}
    for i, prep in enumerate(preps):
        key = (prep["design"].shape[0], tuple(prep["candidates"]))
        groups.setdefault(key, []).append(i)
    for indices in groups.values():
        stack = lambda name, indices=indices: jnp.asarray(  # noqa: E731
            np.stack([preps[i][name] for i in indices])
        )
        thetas, converged = _fit_tables(
            stack("design"), stack("target"), stack("masks"), stack("weights")
        )
        thetas, converged = np.asarray(thetas), np.asarray(converged)
        for j, i in enumerate(indices):
            results[i] = _postprocess(datasets[i], preps[i], effects, thetas[j], converged[j])
    return [results[i] for i in range(len(datasets))]
