"""The noise diagnosis's verdict on one record (`evaluate`): every candidate's evidence and
ranking (with the nested pairs `NESTED`), the open-world test of each (held-out one-step
errors white at the variance it predicts, no periodic line carried into them), the
held-out gap, the refit of the nominal model, the fitted model's parameters with
intervals, and the reason in words."""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from ..._data import NoiseData
from .. import openworld
from ..base import (
    NESTED_LEVEL,
    CandidateFit,
    DiagnosisResult,
    _resolve_nested,
    held_out_gap,
    rank_candidates,
)
from .fit import model_intervals
from .localise import localise
from .state import NoiseRecord

NESTED = {"exp_cosine": "gauss_markov", "gauss_markov": "random_walk"}
"""An exponential-cosine noise at β = 0 is a Gauss–Markov noise; a Gauss–Markov noise with
τ_c → ∞ (σ² ∝ τ_c) is a random walk."""


def evaluate(data: NoiseData, rec: NoiseRecord, effects, outputs) -> DiagnosisResult:
    """The diagnosis of one record from its fits (`outputs` of `fit._fit_record`: z,
    innovations, their predicted variances, log-likelihoods, convergence and steps of every
    candidate): evidence and ranking, the open-world verdict, the held-out gap, the refit
    and the localisation of the white-noise residual."""
    zs, nus, ss, log_liks, converged, steps = (np.asarray(o) for o in outputs)
    split, scale, dt = rec.split, rec.scale, rec.dt
    n = nus.shape[1]
    names = ["nominal"] + [e.name for e in effects]
    context = {"scale": scale, "dt": dt, "duration": rec.duration}
    fits = []
    # Log-likelihoods in the record's unit: the normalisation by s₀ shifts every model by
    # the same −(n_terms) ln s₀.
    unit_shift = -(split - 1) * math.log(scale)
    for i, name in enumerate(names):
        innovation = nus[i] * scale
        params = {}
        if i:
            params = effects[i - 1].physical(zs[i, 1 : 1 + effects[i - 1].n_params], context)
        params["white_sigma_g"] = math.exp(float(zs[i, 0])) * scale
        fits.append(
            CandidateFit(
                effect=name,
                n_effect_params=0 if i == 0 else effects[i - 1].n_params,
                log_likelihood=float(log_liks[i]) + unit_shift,
                n_train=split,
                held_out_ms=float(np.mean(innovation[split:] ** 2)),
                held_out_errors=innovation[split:],
                train_ms=float(np.mean(innovation[1:split] ** 2)),
                params=params,
                converged=bool(converged[i]),
            )
        )
    _, ranking, _ = rank_candidates(fits[0], fits[1:], nested=NESTED)
    by_name = {f.effect: f for f in fits}
    # Open world: a model explains the record when its held-out one-step errors, each
    # scaled by the variance the model predicts for it, are white with unit variance (to
    # 3 standard errors), and no periodic line of its training errors continues into the
    # held-out ones. The line test runs on each model's own standardised one-step errors,
    # whose null is white: on the raw record a slow Gauss–Markov wander alone would pass
    # for a low-frequency line (a τ = 50 s record at 1 Hz did: a 0.0011 Hz "line" that
    # predicted over 20 % of the held-out part).
    n_test = n - split
    assessed = {}
    for i, name in enumerate(names):
        predicted = ss[i, split:] * scale**2
        scaled = by_name[name].held_out_errors / np.sqrt(predicted)
        test = openworld.whiteness(scaled)
        ratio = float(np.mean(scaled**2))
        # The predicted variance comes from the fit to the training part: both parts'
        # sampling errors count (2/n each for a variance), not the held-out part's alone.
        spread = math.sqrt(2 / max(n_test, 1) + 2 / max(split, 1))
        consistent = abs(ratio - 1) <= 3 * spread
        standardised = nus[i] / np.sqrt(np.maximum(ss[i], np.finfo(float).tiny))
        line = openworld.predictability(
            standardised[1:],
            split - 1,
            dt,
            np.zeros(0, int),
            np.zeros(0),
            1,
            tests=("periodic",),
            line_z=openworld.LINE_Z,
        )
        assessed[name] = {
            "floor": float(np.mean(predicted)),
            "whiteness": test,
            "variance_ratio": ratio,
            "predictable": line,
            "explains": bool(test.white and consistent and not line.deterministic),
        }
    for entry in ranking:
        own = assessed[entry["effect"]]
        before = openworld.excess(fits[0].held_out_ms, own["floor"])
        after = openworld.excess(by_name[entry["effect"]].held_out_ms, own["floor"])
        entry.update(
            {
                "stochastic": True,
                "explains": own["explains"],
                # A fit that stopped short of its maximum only understates its evidence
                # (a lower bound), as in the step kind: it stays credible. (Whether the
                # exp-cosine fit of a near-undamped line reaches its tolerance within the
                # step limit depended on the batch it ran in.)
                "plausible": bool(np.isfinite(entry["evidence"])),
                "one_step_whiteness": own["whiteness"].to_dict(),
                "variance_ratio": own["variance_ratio"],
                "deterministic_misfit": own["predictable"].deterministic,
                "explained_fraction": openworld.explained_fraction(before, after),
            }
        )
    nominal_status = {
        "explains": assessed["nominal"]["explains"],
        "white": assessed["nominal"]["whiteness"].white,
        "plausible": bool(converged[0]),
    }
    decision = openworld.decide(
        nominal_status,
        ranking,
        resolve_tie=lambda a, b: _resolve_nested(a, b, fits[1:], NESTED, NESTED_LEVEL),
    )
    verdict, tied = decision.verdict, list(decision.tied)
    shown = decision.chosen or decision.best_partial
    chosen = shown or "nominal"
    # The noise floor is the shown model's own predicted innovation variance on the
    # held-out part (the filter's S_k): what remains above it is what the model did not
    # expect. (A floor estimated on the training part would add the sampling mismatch of
    # two segments' variances, as large as the excess being measured.)
    floor = assessed[chosen]["floor"]
    for entry in ranking:
        g = held_out_gap(fits[0].held_out_errors, by_name[entry["effect"]].held_out_errors, floor)
        entry["gap_shrink"] = g["shrink"]
        entry["fit_steps"] = int(steps[names.index(entry["effect"])])
    after = by_name[chosen].held_out_errors
    gap = held_out_gap(fits[0].held_out_errors, after, floor)
    gap["unit"] = "g"
    gap["model_after"] = chosen
    gap["held_out"] = f"the last {n - split} of {n} samples (one-step prediction errors)"
    gap["metric"] = (
        "held-out RMS one-step prediction error in excess of the chosen model's predicted "
        "innovation variance"
    )
    fraction = next((e["explained_fraction"] for e in ranking if e["effect"] == shown), 0.0)
    remaining = gap["after"]
    remaining_gap = {
        "g": remaining,
        "noise_floor_g": math.sqrt(floor),
        "over_floor": remaining / math.sqrt(floor) if floor > 0 else float("inf"),
        "model": chosen,
        "whiteness_p_value": assessed[chosen]["whiteness"].p_value,
    }
    line = assessed[chosen]["predictable"]
    if line.deterministic:
        # A line is a gap the RMS hardly shows: its amplitude, in g, beside the RMS gap.
        remaining_gap["periodic_line"] = {
            "frequency_Hz": line.frequency_Hz,
            "rms_g": line.periodic_rms * math.sqrt(floor),
            "z": line.periodic_z,
        }
    predictable = assessed[chosen]["predictable"]
    reason = _reason(decision, assessed, ranking, predictable, remaining, floor, chosen)

    white_sigma = fits[0].params["white_sigma_g"]
    x = np.asarray(data.a_out)
    residual = x - rec.level
    refit = {
        "parameters": {},
        "nominal_fit": {"white_sigma_g": white_sigma, "level_g": rec.level},
        "model": "a_out = level + σ_w w (white noise about a constant level; no prior)",
        "parameter_error": False,
        "converged": bool(converged[0]),
        "description": (
            f"the nominal model (white noise alone) has σ_w = {white_sigma:.4g} g about the "
            f"level {rec.level:.7g} g (fitted on the training part)"
        ),
    }
    chosen_index = names.index(chosen)
    # The numbers a Kalman filter needs: the shown model's parameters with intervals.
    model = model_intervals(
        zs[chosen_index],
        rec.normalised,
        split,
        jnp.asarray(chosen_index),
        effects[chosen_index - 1] if chosen_index else None,
        context,
    )
    model["model"] = "white" if chosen_index == 0 else f"white+{chosen}"
    refit["model_parameters"] = model
    where = localise(residual, nus[0], white_sigma, rec)
    traces = {
        "t": np.asarray(data.t),
        "measured": x,
        "level": rec.level,
        "innovations_before": nus[0] * scale,
        "innovations_after": nus[chosen_index] * scale,
        "best_name": chosen,
        "split": split,
    }
    where["predictability"] = predictable.to_dict()
    return DiagnosisResult(
        kind="noise",
        verdict=verdict,
        tied=tied,
        ranking=ranking,
        gap=gap,
        where=where,
        refit=refit,
        traces=traces,
        notes=list(getattr(data, "notes", ())),
        explained_fraction=fraction,
        remaining_gap=remaining_gap,
        reason=reason,
    )


def _reason(decision, assessed, ranking, predictable, remaining, floor, chosen) -> str:
    verdict = decision.verdict
    sigma = math.sqrt(floor)
    entry = {e["effect"]: e for e in ranking}
    if verdict == "none":
        return (
            "the held-out record is white noise about its level (Ljung–Box p = "
            f"{assessed['nominal']['whiteness'].p_value:.2g}) and no effect is significant."
        )
    if verdict == "cannot_tell":
        a, b = decision.tied
        return (
            f"{a} and {b} both whiten the held-out record and their evidence differs by "
            f"{abs(entry[a]['evidence'] - entry[b]['evidence']):.1f} (< 6 on the 2 ln B scale)."
        )
    if verdict != "unexplained":
        return (
            f"with {verdict} the held-out one-step prediction errors are white (Ljung–Box p = "
            f"{assessed[verdict]['whiteness'].p_value:.2g}) at the variance it predicts; "
            f"evidence 2 ln B = {entry[verdict]['evidence']:.1f} over white noise."
        )
    parts = []
    if predictable.deterministic:
        parts.append(
            f"a periodic line at {predictable.frequency_Hz:.4g} Hz continues from the "
            f"training part into the held-out one-step errors of {chosen} (projection "
            f"{predictable.periodic_z:.1f} standard errors, {predictable.periodic:.1%} "
            "of their mean square): deterministic, not one of the library's noises"
        )
    elif abs(predictable.periodic_z) >= openworld.LINE_Z and predictable.frequency_Hz:
        # A line of the training part whose continuation is anti-correlated (or far off)
        # with the held-out part: a real spectral line whose phase or frequency wanders.
        parts.append(
            f"a spectral line at {predictable.frequency_Hz:.4g} Hz in the training part "
            f"does not carry its phase into the held-out part (projection "
            f"{predictable.periodic_z:.1f} standard errors): a wandering line"
        )
    if decision.best_partial:
        best = decision.best_partial
        own = assessed[best]
        if not own["whiteness"].white:
            p_value = own["whiteness"].p_value
            short = f"its one-step errors are not white (Ljung–Box p = {p_value:.2g})"
        elif own["predictable"].deterministic:
            short = "it leaves the line"
        else:
            short = (
                f"its one-step errors are {math.sqrt(own['variance_ratio']):.3g}× the size it "
                "predicts"
            )
        parts.append(
            f"the best library effect, {best}, explains {entry[best]['explained_fraction']:.0%} "
            f"of the excess, but {short}; {remaining:.3g} g above its {sigma:.3g} g floor "
            "remains"
        )
    elif not any(e["significant"] for e in ranking):
        nominal = assessed["nominal"]
        p_value = nominal["whiteness"].p_value
        if nominal["predictable"].deterministic:
            why = "the line is not one of the library's noises"
        elif nominal["whiteness"].white:
            why = (
                f"the held-out record is white (Ljung–Box p = {p_value:.2g}) but its variance "
                f"is {nominal['variance_ratio']:.3g}× the training part's"
            )
        else:
            why = (
                "the record is not white noise (Ljung–Box p = "
                f"{nominal['whiteness'].p_value:.2g})"
            )
        parts.append(why + " and no library effect is significant")
    else:
        parts.append(
            "no library noise leaves white one-step prediction errors (best: "
            f"{chosen}, Ljung–Box p = {assessed[chosen]['whiteness'].p_value:.2g})"
        )
    return "; ".join(parts) + "."
