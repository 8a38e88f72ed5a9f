"""The step diagnosis's verdict (host side): each candidate's held-out gap, credibility and
evidence, the open-world decision (`openworld.decide`), the reason in words, the refit
and where the residual lies.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from .._data import NominalDevice, StepData
from .._servo import scale_factor
from . import openworld
from .base import SIGNIFICANCE, DiagnosisResult, held_out_gap, ljung_box
from .step_fit import (
    _I_DV,
    _I_DW,
    _I_GAIN,
    _I_MOMENT,
    _I_SLOT,
    GAIN_SIGMA,
    REFIT_FIELDS,
    refitted_device,
)
from .step_nuisance import (  # noqa: F401  (re-exported: the verdict's nuisance test)
    NUISANCE_ALPHA,
    change_shifts,
    nuisance_test,
    strained_sentence,
)
from .step_record import segments, time_text

TRANSIENT_FRACTION = 0.25
"""The first quarter of each constant-input segment counts as transient, the rest as steady."""

NOISE_VARIANCE_FACTOR = 4.0
"""A noise model explains the free-run errors when their mean square is within this factor
of the variance it predicts (RMS within 2×)."""

LOCK_WINDOW = 10.0
"""Window after each change for the input-locked predictor, in loop time constants T."""


def _fit_entry(
    prep,
    effects_all,
    candidate,
    w,
    prediction,
    innovations,
    log_v,
    converged,
    prior_prediction,
    u_out,
):
    train = ~prep["held"]
    n_train = int(np.sum(train))
    z = np.asarray(w[:4])
    z_gain = float(w[_I_GAIN])
    rss = float(np.sum(innovations[train] ** 2))
    rss = max(rss, 1e-300)
    log_like = (
        -0.5 * n_train * math.log(rss / n_train)
        - 0.5 * float(log_v)
        - 0.5 * float(np.sum(z**2))
        - 0.5 * z_gain**2
    )
    effect = effects_all[candidate - 1] if candidate else None
    context = dict(prep["host"])
    context["innovation_variance"] = rss / n_train
    gain = prep["polarity"] * math.exp(GAIN_SIGMA * z_gain)
    context["test_gain"] = gain * prep["k_test"]
    params = {}
    if effect is not None:
        params = effect.physical(w[_I_SLOT : _I_SLOT + effect.n_params], context)
    error = u_out - prediction
    return {
        "effect": "nominal" if effect is None else effect.name,
        "object": effect,
        "stochastic": bool(effect is not None and effect.stochastic),
        "k": 0 if effect is None else effect.n_params,
        "w": w,
        "z": z,
        "z_gain": z_gain,
        "gain": gain,
        "log_likelihood": log_like,
        "innovation_variance": rss / n_train,
        "prediction": prediction,
        "prior_prediction": prior_prediction,
        "error": error,
        "innovations": innovations,
        "converged": bool(converged),
        "params": params,
    }


def fit_entries(prep, effects_all, candidates, outputs, u_out):
    w, prediction, innovations, log_v, converged, steps, prior, decrement, objective, trained = (
        np.asarray(o) for o in outputs
    )
    n = prep["n"]  # the record's blocks, without the padding
    prediction, innovations, prior, u_out = (
        prediction[:, :n],
        innovations[:, :n],
        prior[:, :n],
        u_out[:n],
    )
    entries = []
    for c, candidate in enumerate(candidates):
        entry = _fit_entry(
            prep,
            effects_all,
            int(candidate),
            w[c],
            prediction[c],
            innovations[c],
            log_v[c],
            converged[c],
            prior[c],
            u_out,
        )
        entry["steps"] = int(steps[c])
        entry["decrement"] = float(decrement[c])
        entry["objective"] = float(objective[c])
        entry["w_trained"] = trained[c]
        entries.append(entry)
    return entries


NESTED_TOLERANCE = 1e-6
"""An effect's maximised penalised log-likelihood may fall below the nominal's by this share
of the nominal's objective (and at least `NESTED_ABSOLUTE`) before its fit counts as failed:
the nominal model is the effect at z = 0, so a fit that ends lower stopped in the wrong
basin (round-off and the solver's tolerance aside)."""

NESTED_ABSOLUTE = 1e-3
"""The least shortfall [in ln L units] that counts as a failed nested fit."""


def nested_shortfall(fit, nominal_fit) -> float:
    """How far `fit`'s maximised penalised log-likelihood (−½ the solver's objective: the
    training residuals, the priors of the refit, the nuisances and the effect) ends below
    the nominal fit's (≤ 0: not below). The reported ln L, which leaves out the change
    times' and the effect's own priors, may differ from it by those terms."""
    return 0.5 * (float(fit["objective"]) - float(nominal_fit["objective"]))


def nested_failed(fit, nominal_fit) -> bool:
    """Whether a nested fit ended below the nominal's penalised likelihood beyond
    round-off (`NESTED_TOLERANCE`)."""
    scale = 0.5 * abs(float(nominal_fit["objective"]))
    return nested_shortfall(fit, nominal_fit) > max(NESTED_TOLERANCE * scale, NESTED_ABSOLUTE)


def nested_losers(fits) -> list[str]:
    """The candidates of one record (`fits[0]` the nominal) whose fit lost to the nominal."""
    return [f["effect"] for f in fits[1:] if nested_failed(f, fits[0])]


def _assess(fit, prep, nominal_fit=None):
    """Held-out and training gaps of one fit against the noise floor (its own noise model
    for a stochastic effect), credibility, and whether it explains the record."""
    held, sigma = prep["held"], prep["sigma"]
    e = fit["error"]
    floor_var = sigma**2
    if fit["stochastic"]:
        white, correlated = (
            fit["params"]["sigma_white_V"] ** 2,
            fit["params"]["sigma_correlated_V"] ** 2,
        )
        floor_var = white + correlated
    ms_train = float(np.mean(e[~held] ** 2))
    ms_held = float(np.mean(e[held] ** 2)) if np.any(held) else 0.0
    fit["ms_train"], fit["ms_held"] = ms_train, ms_held
    fit["ms_held_one_step"] = float(np.mean(fit["innovations"][held] ** 2))
    fit["model_noise_variance"] = floor_var
    fit["gap_train"] = openworld.excess(ms_train, floor_var)
    fit["gap_held"] = openworld.excess(ms_held, floor_var)
    limit = openworld.FLOOR_FACTOR * sigma
    explains = fit["gap_train"] <= limit and fit["gap_held"] <= limit
    if fit["stochastic"]:
        # A noise explains the record when its one-step errors are white and the free-run
        # errors are of the size it predicts: their mean square within a factor
        # `NOISE_VARIANCE_FACTOR` of σ_w² + σ_s² on both parts (a loose check — a fit of
        # the deterministic part takes some low-frequency noise with it on the training
        # part; the predictability test is what refuses deterministic misfits).
        fit["one_step_whiteness"] = openworld.whiteness(fit["innovations"][held])
        ratios = [float(np.mean(part**2)) / max(floor_var, 1e-300) for part in (e[~held], e[held])]
        fit["free_run_over_noise_variance"] = ratios
        consistent = all(1 / NOISE_VARIANCE_FACTOR <= r <= NOISE_VARIANCE_FACTOR for r in ratios)
        fit["variance_consistent"] = bool(consistent)
        explains = fit["one_step_whiteness"]["white"] and consistent
    fit["explains"] = bool(explains)
    out = [
        REFIT_FIELDS[i]
        for i in range(4)
        if prep["prior_sigma"][i] > 0 and abs(fit["z"][i]) > openworld.PRIOR_LIMIT
    ]
    if abs(fit["z_gain"]) > openworld.PRIOR_LIMIT:
        out.append("test_winding_gain")
    fit["out_of_prior"] = out
    # A candidate fit that stopped short of its minimum only understates its likelihood (its
    # evidence is a lower bound): it stays credible. The nominal refit must converge for
    # `none` (evaluate), and its shortfall is taken off every effect's evidence.
    fit["plausible"] = bool(not out)
    return fit


def _describe_where(residual, prep, data, sigma) -> str:
    """Where a residual lies, in words: the segments whose RMS is largest."""
    u = np.asarray(data.u_test)
    t = np.asarray(data.t)
    edges = segments(u)
    parts = []
    for start, stop in zip(edges[:-1], edges[1:], strict=True):
        cut = start + max(1, int(TRANSIENT_FRACTION * (stop - start)))
        for label, a, b in (("transient", start, cut), ("steady", cut, stop)):
            if b > a:
                parts.append((float(np.sqrt(np.mean(residual[a:b] ** 2))), label, start, b - a))
    if not parts:
        return ""
    total = float(np.sqrt(np.mean(residual**2)))
    worst = sorted(parts, reverse=True)[:3]
    transient = sum(p[0] ** 2 * p[3] for p in parts if p[1] == "transient")
    steady = sum(p[0] ** 2 * p[3] for p in parts if p[1] == "steady")
    kind = "in the transients after the changes" if transient > steady else "in the steady states"
    at = ", ".join(
        f"{time_text(t[p[2]] - t[0])} (U_test {u[p[2]]:+.3g} V)" for p in worst if p[0] > 2 * sigma
    )
    where = f"largest {kind}"
    if at:
        where += f": segments starting at {at}"
    return where + f" (RMS {total:.3g} V over the record)"


def evidence_slack(fit, prep, n_train: int) -> float:
    """How much 2 ln L a fit that stopped short of its minimum could still gain.

    The Newton decrement D is the decrease of the cost ½Σ(a/σ)² (σ the noise floor the fit
    scales by) that a full Gauss–Newton step predicts. The log-likelihood profiles the
    noise variance, ln L = −(n/2) ln(RSS/n), so the same decrease is worth
    2Δln L = −n ln(1 − 2Dσ²/RSS): about 2D when the fit is at the floor (RSS ≈ nσ²), and
    2D·σ²/(RSS/n) — far less — when it misses by a wide margin (a linear loop refitted to a
    record that hits its stops predicted D ≈ 5e3, worth 2Δln L ≈ 0.03). Infinite when the
    step would remove the whole residual: then nothing can be significant against it."""
    sigma = float(prep["sigma"])
    rss = max(float(fit["innovation_variance"]) * n_train, 1e-300)
    share = 2 * float(fit["decrement"]) * sigma**2 / rss
    if share >= 1:
        return math.inf
    return -n_train * math.log1p(-share)


def evaluate(data, nominal: NominalDevice, prep, fits) -> DiagnosisResult:
    held, sigma = prep["held"], prep["sigma"]
    for fit in fits:
        _assess(fit, prep)
    nominal_fit, candidates = fits[0], fits[1:]
    n_train = int(np.sum(~held))
    nominal_fit["whiteness"] = openworld.whiteness(nominal_fit["error"][held])
    nominal_fit["explains"] = bool(
        nominal_fit["gap_train"] <= openworld.FLOOR_FACTOR * sigma
        and nominal_fit["gap_held"] <= openworld.FLOOR_FACTOR * sigma
    )
    # A deterministic effect also explains the record when what it leaves is a small part
    # of the gap it closed (a model-form difference, e.g. another contact law at a stop):
    # named, with the remaining gap reported (`openworld.MODEL_FORM`).
    for fit in candidates:
        if fit["stochastic"] or fit["explains"]:
            continue
        fit["explains_model_form"] = bool(
            fit["gap_train"] <= openworld.MODEL_FORM * nominal_fit["gap_train"]
            and fit["gap_held"] <= openworld.MODEL_FORM * nominal_fit["gap_held"]
        )
        fit["explains"] = fit["explains_model_form"]
    window = max(int(LOCK_WINDOW * prep["period"] / prep["dt"]), 4)
    predictable = openworld.predictability(
        nominal_fit["error"], held, prep["dt"], prep["change_block"], prep["change_step"], window
    )
    # The nominal fit may stop short of its minimum: an effect's evidence is then overstated
    # by up to what the rest of the way would add to the nominal's log-likelihood.
    slack = 0.0 if nominal_fit["converged"] else evidence_slack(nominal_fit, prep, n_train)
    nominal_fit["plausible"] = bool(nominal_fit["converged"] and not nominal_fit["out_of_prior"])
    entries = []
    for fit in candidates:
        evidence = 2 * (
            fit["log_likelihood"]
            - 0.5 * fit["k"] * math.log(n_train)
            - nominal_fit["log_likelihood"]
        )
        if fit["stochastic"]:
            improves = fit["ms_held_one_step"] < nominal_fit["ms_held"]
        else:
            improves = fit["ms_held"] < nominal_fit["ms_held"]
        if not np.isfinite(evidence):
            evidence = -np.inf
        fraction = openworld.explained_fraction(nominal_fit["gap_held"], fit["gap_held"])
        # A nested fit that ended below the nominal's likelihood is a solver failure (it
        # was restarted from the nominal optimum first): flagged, never an effect.
        failed = nested_failed(fit, nominal_fit)
        entry = {
            "effect": fit["effect"],
            "evidence": float(evidence),
            "fit_failed": failed,
            "objective_below_nominal": max(nested_shortfall(fit, nominal_fit), 0.0),
            "significant": bool(evidence - slack >= SIGNIFICANCE and improves and not failed),
            "stochastic": fit["stochastic"],
            "explains": fit["explains"],
            "explains_up_to_model_form": fit.get("explains_model_form", False),
            "plausible": fit["plausible"] and not failed,
            "explained_fraction": 0.0 if failed else fraction,
            "gap_after_V": fit["gap_held"],
            "gap_shrink": (
                1 - fit["gap_held"] / nominal_fit["gap_held"]
                if nominal_fit["gap_held"] > 0
                else 0.0
            ),
            "held_out_mean_square": fit["ms_held"],
            "held_out_one_step_mean_square": fit["ms_held_one_step"],
            "params": fit["params"],
            "converged": fit["converged"],
            "fit_steps": fit["steps"],
            "out_of_prior": fit["out_of_prior"],
        }
        if fit["stochastic"]:
            entry["deterministic_misfit"] = bool(predictable.get("deterministic", False))
            entry["one_step_whiteness"] = fit["one_step_whiteness"]
            entry["variance_consistent"] = fit["variance_consistent"]
            if entry["deterministic_misfit"]:
                # A noise that absorbs a predictable misfit explains none of it.
                entry["explained_fraction"] = 0.0
        entries.append(entry)
    nominal_status = {
        "explains": nominal_fit["explains"],
        "white": nominal_fit["whiteness"]["white"],
        "plausible": nominal_fit["plausible"],
    }
    decision = openworld.decide(nominal_status, entries, domain=prep["domain_problems"])
    # The nuisances judged together: a record whose nominal refit needs strained nuisances
    # is not `none` (an effect they absorbed would go unseen).
    nuisances = nuisance_test(nominal_fit, prep)
    if decision["verdict"] == "none" and nuisances["strained"]:
        decision = {**decision, "verdict": "unexplained", "path": "nuisances"}
    entries.sort(key=lambda r: (not r["fit_failed"], r["significant"], r["evidence"]), reverse=True)
    verdict = decision["verdict"]
    by_name = {f["effect"]: f for f in fits}
    shown = decision["chosen"] or decision["best_partial"]
    after_fit = by_name[shown] if shown else nominal_fit
    floor_after = after_fit["model_noise_variance"] if after_fit["stochastic"] else None
    gap = held_out_gap(
        nominal_fit["error"][held], after_fit["error"][held], sigma**2, floor_after=floor_after
    )
    gap.update(
        {
            "unit": "V",
            "model_after": shown or "nominal",
            "metric": "held-out free-run simulation error (RMS) in excess of the noise floor",
            "one_step_before_rms_V": math.sqrt(nominal_fit["ms_held"]),
            "one_step_after_rms_V": math.sqrt(after_fit["ms_held_one_step"]),
            "held_out": (
                f"{int(np.sum(held))} of {prep['n']} block means of {prep['block']} samples: "
                f"{prep['held_rule']}"
            ),
            "block_samples": prep["block"],
            "held_out_blocks": _ranges(held),
            "fitted_samples": prep["n"] * prep["block"],
        }
    )
    fraction = next((e["explained_fraction"] for e in entries if e["effect"] == shown), 0.0)
    remaining = after_fit["gap_held"]
    where_text = _describe_where(after_fit["error"], prep, prep["view"], sigma)
    remaining_gap = {
        "V": remaining,
        "noise_floor_V": sigma,
        "over_floor": remaining / sigma if sigma > 0 else float("inf"),
        "model": shown or "nominal",
        "where": where_text,
    }
    reason = _reason(
        decision, nominal_fit, by_name, entries, prep, predictable, remaining, sigma, where_text
    )
    refit = _refit_report(nominal, nominal_fit, by_name, shown, prep, sigma, verdict)
    refit["nuisance_test"] = nuisances
    where = _localise(prep["view"], nominal_fit["error"], sigma, prep)
    where["predictability"] = predictable
    where["noise_floor"] = prep["floor"]
    where["domain"] = prep["domain"]
    chosen_fit = after_fit
    view = prep["view"]
    traces = {
        "t": np.asarray(view.t),
        "u_test": np.asarray(view.u_test),
        "measured": np.asarray(view.u_out),
        "block_samples": prep["block"],
        "nominal_unrefitted": nominal_fit["prior_prediction"],
        "nominal": nominal_fit["prediction"],
        "best": chosen_fit["prediction"],
        "best_name": shown or "nominal",
        "residual_before": nominal_fit["error"],
        "residual_after": chosen_fit["innovations"]
        if chosen_fit["stochastic"]
        else chosen_fit["error"],
        "held_out": held,
    }
    notes = list(getattr(data, "notes", ())) + list(prep.get("notes", []))
    return DiagnosisResult(
        kind="step",
        verdict=verdict,
        tied=decision["tied"],
        ranking=entries,
        gap=gap,
        where=where,
        refit=refit,
        traces=traces,
        notes=notes,
        explained_fraction=fraction,
        remaining_gap=remaining_gap,
        reason=reason,
    )


def _pct(x: float) -> str:
    return f"{x:+.1%}" if abs(x) < 10 else f"{x:+.3g}×"


def _reason(decision, nominal_fit, by_name, entries, prep, predictable, remaining, sigma, where):
    path = decision["path"]
    verdict = decision["verdict"]
    floor = f"{sigma:.3g} V noise floor"
    if path == "domain":
        return "; ".join(prep["domain_problems"]) + "."
    if path == "nuisances":
        return (
            "the refitted nominal model reaches the noise floor only with strained nuisances: "
            + strained_sentence(nuisance_test(nominal_fit, prep), nominal_fit)
            + "."
        )
    if verdict == "none":
        return (
            "the refitted nominal model leaves the held-out residual at the noise floor "
            f"(excess {nominal_fit['gap_held'] / sigma:.2f}× the {floor}) and white "
            f"(Ljung–Box p = {nominal_fit['whiteness']['p_value']:.2g}); no effect is significant."
        )
    entry = {e["effect"]: e for e in entries}
    if verdict == "cannot_tell":
        a, b = decision["tied"]
        return (
            f"{a} and {b} both bring the held-out gap to the floor and their evidence differs by "
            f"{abs(entry[a]['evidence'] - entry[b]['evidence']):.1f} (< 6 on the 2 ln B scale): "
            "the record cannot tell them apart."
        )
    if verdict != "unexplained":
        fit = by_name[verdict]
        text = (
            f"{verdict} brings the held-out gap from {nominal_fit['gap_held']:.3g} V to "
            f"{fit['gap_held']:.3g} V ({fit['gap_held'] / sigma:.2f}× the {floor}); evidence "
            f"2 ln B = {entry[verdict]['evidence']:.1f} over the nominal model"
        )
        if fit.get("explains_model_form"):
            text += (
                f"; what remains ({fit['gap_held'] / nominal_fit['gap_held']:.1%} of the gap it "
                "closed) stands above the floor: the effect is right, and the record's physics "
                "differs from its model in detail"
            )
        if fit["stochastic"]:
            text += (
                "; the misfit is not predictable from the input changes, a periodic component "
                "or a trend (held-out fractions removed: "
                f"{predictable['input_locked']:.2f}, {predictable['periodic']:.2f}, "
                f"{predictable['trend']:.2f}), and with the correlated noise the one-step "
                "prediction errors are white"
            )
        return text + "."
    parts = []
    if not nominal_fit["converged"]:
        parts.append("the nominal refit did not converge")
    if nominal_fit["out_of_prior"]:
        moved = []
        for field in nominal_fit["out_of_prior"]:
            if field in REFIT_FIELDS:
                j = REFIT_FIELDS.index(field)
                z = nominal_fit["z"][j]
                shift = math.exp(prep["prior_sigma"][j] * z) - 1
                moved.append(f"{field} {_pct(shift)} ({z:+.1f}σ)")
        shifts = ", ".join(moved)
        if "test_winding_gain" in nominal_fit["out_of_prior"]:
            shifts += (
                ", " if shifts else ""
            ) + f"test winding gain ×{abs(nominal_fit['gain']):.3g}"
        parts.append(
            f"the refit needs {shifts}: beyond {openworld.PRIOR_LIMIT:.0f}σ of the prior "
            "(not this device? give its values with --params)"
        )
    partial = decision["best_partial"]
    if partial:
        parts.append(
            f"the best library effect, {partial}, explains "
            f"{entry[partial]['explained_fraction']:.0%} "
            f"of the excess; {remaining:.3g} V ({remaining / sigma:.1f}× the {floor}) remains"
        )
    else:
        significant = [e for e in entries if e["significant"]]
        if nominal_fit["explains"] and not nominal_fit["whiteness"]["white"] and not significant:
            parts.append(
                "the held-out residual is at the floor but not white (Ljung–Box p = "
                f"{nominal_fit['whiteness']['p_value']:.2g}) and no library effect is significant"
            )
        else:
            parts.append(
                f"the held-out gap is {remaining:.3g} V ({remaining / sigma:.1f}× the {floor}) "
                "and no library effect that is significant and credible brings it to the floor"
            )
    stochastic = [e for e in entries if e["stochastic"] and e["significant"]]
    if stochastic and stochastic[0].get("deterministic_misfit"):
        best = max(("input_locked", "periodic", "trend"), key=lambda k: predictable[k])
        what = {
            "input_locked": "locked to the input changes",
            "periodic": f"periodic ({predictable['frequency_Hz']:.4g} Hz)",
            "trend": "a trend",
        }[best]
        parts.append(
            f"correlated noise would absorb it, but the misfit is {what} (a predictor fitted on "
            f"the training part removes {predictable[best]:.0%} of the held-out residual): "
            "deterministic, not noise"
        )
    if where:
        parts.append(where)
    return "; ".join(parts) + "."


def _parameter_shifts(nominal, fit, prep) -> dict:
    parameters = {}
    for j, field in enumerate(REFIT_FIELDS):
        if prep["prior_sigma"][j] == 0:
            continue
        value0 = float(getattr(nominal.params, field))
        value = value0 * math.exp(prep["prior_sigma"][j] * fit["z"][j])
        parameters[field] = {
            "nominal": value0,
            "refitted": value,
            "shift_relative": value / value0 - 1,
            "shift_sigma": float(fit["z"][j]),
        }
    return parameters


KNOWN_FIELDS = (
    ("torquer_time_constant", "T_dm"),
    ("filter_time_constant", "T_f"),
    ("pendulum_mass", "m"),
    ("pendulum_length", "l"),
    ("pickoff_gain", "k_dp"),
    ("amplifier_gain", "k_y"),
)
"""Values of the nominal device the step diagnosis takes as known (never refitted), as
listed in its summary (the lags: an effect is a departure from them)."""


def _known_values(nominal, prep) -> dict:
    known = {}
    for field, symbol in KNOWN_FIELDS:
        known[field] = {"symbol": symbol, "value": float(getattr(nominal.params, field))}
    refitted = {
        f: float(prep["prior_sigma"][j])
        for j, f in enumerate(REFIT_FIELDS)
        if prep["prior_sigma"][j]
    }
    for j, field in enumerate(REFIT_FIELDS):
        if not prep["prior_sigma"][j]:
            known[field] = {"symbol": field, "value": float(getattr(nominal.params, field))}
    return {"known": known, "refitted_prior_relative_sigma": refitted}


def _known_text(nominal) -> str:
    lags = ", ".join(
        f"{symbol} {time_text(float(getattr(nominal.params, field)))}"
        if float(getattr(nominal.params, field)) > 0
        else f"{symbol} 0"
        for field, symbol in KNOWN_FIELDS[:2]
    )
    return f"taken as known from the nominal device: {lags} (a lag effect departs from these)"


def _refit_report(nominal, nominal_fit, by_name, shown, prep, sigma, verdict):
    """The refit as the summary shows it: the device's values under the model the verdict
    names (or the first of a tie; the nominal model when it names none), and beside them
    the nominal model's own refit, labelled as such: the refit a model without the effect
    needs is not the device's state."""
    model_fit = by_name.get(shown) if shown else None
    if model_fit is None or model_fit.get("z") is None:
        model_fit = nominal_fit
    parameters = _parameter_shifts(nominal, model_fit, prep)
    w = nominal_fit["w"]
    ctx_scale = float(prep["ctx"].scale)
    shifts = change_shifts(np.asarray(w), prep["ctx"])[: prep["change_index"].size]
    measured = np.asarray(nominal_fit["prediction"]) + nominal_fit["error"]
    rms_prior = float(np.sqrt(np.mean((measured - nominal_fit["prior_prediction"]) ** 2)))
    rms_refit = float(np.sqrt(np.mean(nominal_fit["error"] ** 2)))
    refit = {
        "parameters": parameters,
        "model": shown if model_fit is not nominal_fit else "nominal",
        "nominal_model_parameters": _parameter_shifts(nominal, nominal_fit, prep),
        "nominal_model_out_of_prior": nominal_fit["out_of_prior"],
        "nominal_device": _known_values(nominal, prep),
        "converged": nominal_fit["converged"],
        "credible": nominal_fit["plausible"],
        "out_of_prior": nominal_fit["out_of_prior"],
        "nuisances": {
            "test_winding_polarity": "reversed" if prep["polarity"] < 0 else "as the nominal",
            "test_winding_gain": abs(nominal_fit["gain"]),
            "test_winding_gain_sigma": nominal_fit["z_gain"],
            "external_moment_V": ctx_scale * float(w[_I_MOMENT]),
            "external_moment_Nm": ctx_scale * float(w[_I_MOMENT]) * prep["host"]["torquer_gain"],
            "initial_displacement_V": ctx_scale * float(w[_I_DV]),
            "initial_velocity_V": ctx_scale * float(w[_I_DW]),
            "change_time_shift_samples": [float(x) for x in shifts],
            "adc_step_V": prep["floor"]["adc_step_V"],
        },
        "rms_before_refit_V": rms_prior,
        "rms_after_refit_V": rms_refit,
        "gap_closed_by_refit": 1 - rms_refit / rms_prior if rms_prior > 0 else 0.0,
        "description": "J, μ, c, k_dm refitted under their prior; the nuisances (test winding "
        "polarity and gain, offset, initial state, change times) fitted in every model; "
        + _known_text(nominal),
    }
    scale_factors = {}
    for label, fit in (
        ("nominal_refit", nominal_fit),
        ("with_effect", by_name.get(shown) or nominal_fit),
    ):
        device = refitted_device(
            nominal.params, jnp.asarray(fit["z"]), jnp.asarray(prep["prior_sigma"])
        )
        scale_factors[label] = float(scale_factor(device))
    scale_factors["prior"] = float(scale_factor(nominal.params))
    refit["scale_factor_V_per_mps2"] = scale_factors
    refit["scale_factor_shift_by_effect"] = (
        scale_factors["with_effect"] / scale_factors["nominal_refit"] - 1
    )
    refit["parameter_error"] = bool(
        verdict == "none" and rms_prior > 3 * sigma and rms_refit < 1.5 * sigma
    )
    return refit


def _localise(data: StepData, residual: np.ndarray, sigma: float, prep: dict) -> dict:
    """Where the nominal refit's residual lies: per input segment (transient vs steady
    state), in frequency against the white-noise floor, and its whiteness."""
    u = np.asarray(data.u_test)
    n = u.shape[0]
    dt = prep["dt"]
    edges = segments(u)
    conditions = []
    transient_sq, transient_n, steady_sq, steady_n = 0.0, 0, 0.0, 0
    for start, stop in zip(edges[:-1], edges[1:], strict=True):
        cut = start + max(1, int(TRANSIENT_FRACTION * (stop - start)))
        r_t, r_s = residual[start:cut], residual[cut:stop]
        transient_sq += float(np.sum(r_t**2))
        transient_n += r_t.size
        steady_sq += float(np.sum(r_s**2))
        steady_n += r_s.size
        conditions.append(
            {
                "t_start_s": float(data.t[start]),
                "u_test_V": float(u[start]),
                "held_out": bool(prep["held"][min(start, prep["held"].size - 1)]),
                "rms_transient_V": float(np.sqrt(np.mean(r_t**2))),
                "rms_steady_V": float(np.sqrt(np.mean(r_s**2))) if r_s.size else None,
            }
        )
    # Welch periodogram (Hann, 50 % overlap) against the white floor 2σ²dt [V²/Hz].
    length = int(min(256, 2 ** np.floor(np.log2(max(n // 4, 16)))))
    window = np.hanning(length)
    hop = length // 2
    frames = [residual[i : i + length] for i in range(0, n - length + 1, hop)]
    spectra = [np.abs(np.fft.rfft((f - f.mean()) * window)) ** 2 for f in frames]
    psd = 2 * dt * np.mean(spectra, axis=0) / np.sum(window**2)
    freqs = np.fft.rfftfreq(length, dt)
    floor = 2 * sigma**2 * dt
    above = psd[1:] > 4 * floor
    band = freqs[1:][above]
    return {
        "time": {
            "rms_transient_V": float(np.sqrt(transient_sq / max(transient_n, 1))),
            "rms_steady_V": float(np.sqrt(steady_sq / max(steady_n, 1))),
            "transient_fraction_of_segment": TRANSIENT_FRACTION,
        },
        "conditions": conditions,
        "frequency": {
            "noise_floor_V2_per_Hz": floor,
            "peak_excess_Hz": float(freqs[1:][np.argmax(psd[1:] / floor)]),
            "peak_excess_ratio": float(np.max(psd[1:]) / floor),
            "fraction_of_bins_above_4x_floor": float(np.mean(above)),
            "band_above_4x_floor_Hz": [float(band.min()), float(band.max())] if band.size else None,
            "frequency_Hz": freqs.tolist(),
            "psd_V2_per_Hz": psd.tolist(),
        },
        "whiteness": ljung_box(residual),
        "noise_sigma_pilot_V": sigma,
    }


def explains_deterministically(fit, prep) -> bool:
    if fit["stochastic"]:
        return False
    e, held, sigma = fit["error"], prep["held"], prep["sigma"]
    limit = openworld.FLOOR_FACTOR * sigma
    return (
        openworld.excess(float(np.mean(e[~held] ** 2)), sigma**2) <= limit
        and openworld.excess(float(np.mean(e[held] ** 2)), sigma**2) <= limit
    )


def _ranges(mask: np.ndarray) -> list[list[int]]:
    """[start, stop) of each run of True in a mask."""
    padded = np.concatenate([[False], mask, [False]]).astype(int)
    edges = np.flatnonzero(np.diff(padded))
    return [[int(a), int(b)] for a, b in zip(edges[::2], edges[1::2], strict=True)]
