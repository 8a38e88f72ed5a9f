"""The vibration diagnosis's verdict on one table (`evaluate`): every candidate's evidence
and ranking, the lack-of-fit test against the pure error of repeated test conditions
(`pure_error`, `lack_of_fit`: the open-world test), the cross-validated gap, the refit of
the nominal bias and scale factor, and the reason in words."""

from __future__ import annotations

import numpy as np

from ..._data import VibrationData
from ..._static import PPM
from .. import openworld
from ..base import (
    CandidateFit,
    DiagnosisResult,
    held_out_gap,
    rank_candidates,
)
from .effects import COEFFICIENTS
from .localise import localise
from .state import VibrationTable


def _rss_floor(target: np.ndarray) -> float:
    # Rounding floor of the residual sum of squares (ppm²): keeps ln(RSS) finite on exact data.
    return target.size * (1e-9 * max(float(np.max(np.abs(target))), 1.0)) ** 2


def evaluate(
    data: VibrationData, table: VibrationTable, effects, thetas, converged
) -> DiagnosisResult:
    """The diagnosis of one table from its fits (`thetas`, `converged`: every candidate's
    coefficients and convergence on all rows, then on each cross-validation fold): evidence
    and ranking, the lack-of-fit test against repeated conditions, the open-world verdict,
    the cross-validated gap, the refit of bias and scale factor and the localisation."""
    design, target = table.design, table.target
    n = target.size
    fold_of_row = table.fold_of_row
    by_effect = {e.name: e for e in effects}
    floor_rss = _rss_floor(target)
    fits, full_predictions, cv_errors = [], {}, {}
    standard_errors = {}
    nominal_se = None
    for c, name in enumerate(table.candidates):
        theta_full = thetas[c, 0]
        prediction = design @ theta_full
        rss = max(float(np.sum((prediction - target) ** 2)), floor_rss)
        free = np.flatnonzero(table.masks[c])
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
            k = len(table.free[name])
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
    assert nominal_se is not None  # "nominal" is always the first candidate (`prepare`)
    _, ranking, _ = rank_candidates(fits[0], fits[1:])
    floor = min(f.train_ms for f in fits)
    by_name = {f.effect: f for f in fits}
    # Open world: with repeated test conditions the table carries its own noise floor (pure
    # error), and a model that leaves a significant lack of fit does not explain it.
    # Without repeats the floor is the fit's own residual and no such test exists.
    replicates = pure_error(data, target)
    lack = {}
    for fit in fits:
        free = len(table.free.get(fit.effect, ())) if fit.effect != "nominal" else None
        p = len(table.nominal_columns) + (free or 0)
        rss = fit.train_ms * max(n - p, 1) / PPM**2
        lack[fit.effect] = lack_of_fit(rss, p, replicates)
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
    verdict, tied = decision.verdict, list(decision.tied)
    for entry in ranking:
        g = held_out_gap(
            fits[0].held_out_errors, by_name[entry["effect"]].held_out_errors, floor, block=1
        )
        entry["gap_shrink"] = g["shrink"]
    chosen = decision.chosen or decision.best_partial or "nominal"
    after = by_name[chosen].held_out_errors
    gap = held_out_gap(fits[0].held_out_errors, after, floor, block=1)
    gap["unit"] = "g"
    gap["model_after"] = chosen
    folds = table.folds
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
                float(nominal_se[isf] * PPM) if isf in table.nominal_columns else None
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
        if isf in table.nominal_columns
        else "δ held at 0 (one input level)"
    )
    refit["description"] = (
        f"a0 = {bias_g * 1e3:.4g} ± {nominal_se[ib] * PPM * 1e3:.2g} mg, {scale_text}; "
        f"RMS residual to a_out = a_in {rms_before:.3g} g → {rms_after:.3g} g after the refit"
    )
    where = localise(data, residual_nominal, sigma, table)
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
    notes = list(table.notes)
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


def pure_error(data: VibrationData, target: np.ndarray) -> dict:
    """Pure-error sum of squares [ppm², as `target`, (a_out − a_in) in ppm of 1 g] and its
    degrees of freedom from rows with the same test condition (a_in, amplitudes, random
    level; the frequency does not enter the model)."""
    columns = [data.a_in, data.vib_amp, data.vib_rms]
    columns += [c for c in (data.vib_amp_oa, data.vib_amp_pa) if c is not None]
    keys = np.round(np.stack([np.asarray(c) for c in columns], 1), 12)
    _, group = np.unique(keys, axis=0, return_inverse=True)
    group = np.asarray(group).ravel()
    ss, dof = 0.0, 0
    for g in np.unique(group):
        values = target[group == g]  # ppm of 1 g, as the fits' RSS
        if values.size > 1:
            ss += float(np.sum((values - values.mean()) ** 2))
            dof += values.size - 1
    return {"ss": ss, "dof": dof, "groups": int(np.unique(group).size)}


def lack_of_fit(rss: float, n_params: int, pure: dict) -> dict:
    """The F-test of a fit's lack of fit (`rss` with `n_params` coefficients) against the
    pure error `pure` (`pure_error`); untestable without 3 degrees of freedom of it."""
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
    verdict = decision.verdict
    if verdict == "none":
        return "no effect is significant (2 ln B < 10 or no cross-validated improvement)."
    if verdict == "cannot_tell":
        a, b = decision.tied
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
    best = decision.best_partial
    text = "the repeated test conditions show a lack of fit that no library effect removes"
    if best:
        text += (
            f" (best: {best}, F-test p = {lack[best]['p_value']:.2g}; it explains "
            f"{entry[best]['explained_fraction']:.0%} of the cross-validated excess)"
        )
    return text + "."
