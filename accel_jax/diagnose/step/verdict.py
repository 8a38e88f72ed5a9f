"""The step diagnosis's verdict (host side): each candidate's held-out gap, credibility and
evidence (`assess`), the open-world decision (`openworld.decide`), the reason in words,
and the refit and where the residual lies (`refit`).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..._data import NominalDevice
from .. import openworld
from ..base import SIGNIFICANCE, DiagnosisResult, held_out_gap
from . import assess, noise_null, nuisance
from .assess import assess_fit
from .model import DELAY_LIMIT, REFIT_FIELDS
from .refit import _describe_where, _localise, _ranges, _refit_report
from .state import RankingEntry, StepFit, StepRecord

LOCK_WINDOW = 10.0
"""Window after each change for the input-locked predictor, in loop time constants T."""


def evaluate(
    data, nominal: NominalDevice, rec: StepRecord, fits: list[StepFit]
) -> DiagnosisResult:
    held, sigma = rec.held, rec.sigma
    fits = [assess_fit(fit, rec) for fit in fits]
    nominal_fit, candidates = fits[0], fits[1:]
    n_train = int(np.sum(~held))
    whiteness = openworld.whiteness(nominal_fit.error[held])
    nominal_fit = dataclasses.replace(
        nominal_fit,
        whiteness=whiteness,
        explains=bool(
            nominal_fit.gap_train <= openworld.FLOOR_FACTOR * sigma
            and nominal_fit.gap_held <= openworld.FLOOR_FACTOR * sigma
        ),
    )
    # A deterministic effect also explains the record when what it leaves is a small part
    # of the gap it closed (a model-form difference, e.g. another contact law at a stop):
    # named, with the remaining gap reported (`openworld.MODEL_FORM`).
    candidates = [
        fit if fit.stochastic or fit.explains else _up_to_model_form(fit, nominal_fit)
        for fit in candidates
    ]
    window = max(int(LOCK_WINDOW * rec.period / rec.dt), 4)
    predictable = openworld.predictability(
        nominal_fit.error, held, rec.dt, rec.change_block, rec.change_step, window
    )
    # The nominal fit may stop short of its minimum: an effect's evidence is then overstated
    # by up to what the rest of the way would add to the nominal's log-likelihood.
    slack = 0.0 if nominal_fit.converged else assess.evidence_slack(nominal_fit, rec, n_train)
    nominal_fit = dataclasses.replace(
        nominal_fit, plausible=bool(nominal_fit.converged and not nominal_fit.out_of_prior)
    )
    fits = [nominal_fit, *candidates]
    # A noise candidate's predictability judged against its own fitted noise
    # (`noise_null`): only where the fixed fraction calls the misfit deterministic (the
    # calibrated test can only call it so less often).
    own = {
        fit.effect: noise_null.calibrated(predictable, fit, rec, nominal.params, window)
        for fit in candidates
        if fit.stochastic and fit.model is not None and predictable.deterministic
    }
    entries = [
        ranking_entry(
            fit, nominal_fit, n_train=n_train, slack=slack,
            predictable=own.get(fit.effect, predictable),
        )
        for fit in candidates
    ]
    nominal_status = openworld.NominalStatus(
        explains=nominal_fit.explains, white=whiteness.white, plausible=nominal_fit.plausible
    )
    decision = openworld.decide(nominal_status, entries, domain=list(rec.domain_problems))
    # The nuisances judged together: a record whose nominal refit needs strained nuisances
    # is not `none` (an effect they absorbed would go unseen).
    nuisances = nuisance.nuisance_test(nominal_fit, rec)
    if decision.verdict == "none" and nuisances.strained:
        decision = dataclasses.replace(decision, verdict="unexplained", path="nuisances")
    # A named effect's own fit judged the same way: named with strained nuisances, the
    # effect may stand in for another that they complete (a torquer lag and an input delay
    # for an output filter). Stated, the verdict kept.
    named = {f.effect: f for f in candidates}.get(decision.verdict)
    effect_nuisances = nuisance.nuisance_test(named, rec) if named is not None else None
    entries.sort(key=lambda r: (not r.fit_failed, r.significant, r.evidence), reverse=True)
    verdict = decision.verdict
    by_name = {f.effect: f for f in fits}
    shown = decision.chosen or decision.best_partial
    after_fit = by_name[shown] if shown else nominal_fit
    floor_after = after_fit.model_noise_variance if after_fit.stochastic else None
    gap = held_out_gap(
        nominal_fit.error[held], after_fit.error[held], sigma**2, floor_after=floor_after
    )
    gap.update(
        {
            "unit": "V",
            "model_after": shown or "nominal",
            "metric": "held-out free-run simulation error (RMS) in excess of the noise floor",
            "one_step_before_rms_V": math.sqrt(nominal_fit.ms_held),
            "one_step_after_rms_V": math.sqrt(after_fit.ms_held_one_step),
            "held_out": (
                f"{int(np.sum(held))} of {rec.n} block means of {rec.block} samples: "
                f"{rec.held_rule}"
            ),
            "block_samples": rec.block,
            "held_out_blocks": _ranges(held),
            "fitted_samples": rec.n * rec.block,
        }
    )
    fraction = next((e.explained_fraction for e in entries if e.effect == shown), 0.0)
    remaining = after_fit.gap_held
    where_text = _describe_where(after_fit.error, rec, rec.view, sigma)
    remaining_gap = {
        "V": remaining,
        "noise_floor_V": sigma,
        "over_floor": remaining / sigma if sigma > 0 else float("inf"),
        "model": shown or "nominal",
        "where": where_text,
    }
    reason = _reason(
        decision, nominal_fit, by_name, entries, rec, predictable, remaining, sigma, where_text,
        nuisances,
    )
    if effect_nuisances is not None and effect_nuisances.strained:
        reason = (
            reason.rstrip(".") + ". Its own fit needs strained nuisances: "
            + nuisance.strained_sentence(effect_nuisances, by_name[verdict])
            + f"; {verdict} may stand in for an effect they complete."
        )
    refit = _refit_report(nominal, nominal_fit, by_name, shown, rec, sigma, verdict, nuisances)
    refit["effect_nuisance_test"] = (
        effect_nuisances.to_dict() if effect_nuisances is not None else None
    )
    where = {
        **_localise(rec.view, nominal_fit.error, sigma, rec),
        "predictability": predictable.to_dict(),
        "noise_floor": rec.floor.to_dict(),
        "domain": rec.domain,
    }
    chosen_fit = after_fit
    view = rec.view
    traces = {
        "t": np.asarray(view.t),
        "u_test": np.asarray(view.u_test),
        "measured": np.asarray(view.u_out),
        "block_samples": rec.block,
        "nominal_unrefitted": nominal_fit.prior_prediction,
        "nominal": nominal_fit.prediction,
        "best": chosen_fit.prediction,
        "best_name": shown or "nominal",
        "residual_before": nominal_fit.error,
        "residual_after": chosen_fit.innovations
        if chosen_fit.stochastic
        else chosen_fit.error,
        "held_out": held,
    }
    notes = list(getattr(data, "notes", ())) + list(rec.notes)
    if verdict == "none" and rec.input_measured and rec.input_delay_known is None:
        notes.append(_hidden_lag_note(nuisances, rec))
    questioned = next((e for e in entries if e.effect == verdict), None)
    if questioned is not None and _in_question(questioned.to_dict()):
        notes.append(_in_question_note(questioned, predictable))
    return DiagnosisResult(
        kind="step",
        verdict=verdict,
        tied=list(decision.tied),
        ranking=[e.to_dict() for e in entries],
        gap=gap,
        where=where,
        refit=refit,
        traces=traces,
        notes=notes,
        explained_fraction=fraction,
        remaining_gap=remaining_gap,
        reason=reason,
    )


def _in_question(entry: dict) -> bool:
    """Whether a noise verdict's ranking entry leaves its misfit in question: the fixed
    fraction (`openworld.PREDICTABLE`) called the misfit deterministic, and only the noise's
    own null (`noise_null`) kept the noise (its quantiles recorded)."""
    return bool(
        entry.get("stochastic")
        and entry.get("predictability_null_quantile")
        and not entry.get("deterministic_misfit")
    )


def noise_in_question(result: DiagnosisResult) -> dict | None:
    """The ranking entry of `result`'s verdict where it is a noise effect whose misfit is in
    question (`_in_question`): the misfit partly predictable, kept only by the noise's own
    null (a note says so). None elsewhere. Discovery weighs every noise verdict
    (`noise_verdict`), not only these."""
    entry = noise_verdict(result)
    return entry if entry is not None and _in_question(entry) else None


def noise_verdict(result: DiagnosisResult) -> dict | None:
    """The ranking entry of `result`'s verdict where it is a noise effect, in question
    (`noise_in_question`) or not: the records on which discovery (`step.discover`) also
    runs, to weigh a deterministic term outside the library against the noise
    (`question.weigh_discovery`). None elsewhere (a deterministic effect, a tie,
    `unexplained`, `none`). Not only those in question: on 6 of 19 blind records of a
    215–461 Hz disturbance read `moment_noise` (the measured-input harness's clean twins)
    no predictor removed the fixed fraction, so the noise was not in question; the
    discovery, run on them all the same, found `forcing_sinusoid` credible at the held-out
    floor on 5, where the noise's free run missed by 0.77–17.6 mV."""
    entry = next((e for e in result.ranking if e["effect"] == result.verdict), None)
    return entry if entry is not None and entry.get("stochastic") else None


def _in_question_note(entry: RankingEntry, predictable) -> str:
    null = entry.predictability_null_quantile or {}
    # among the predictors that removed the fixed fraction (one did: else no null was drawn)
    fired = [k for k in null if predictable.removed(k) >= openworld.PREDICTABLE] or list(null)
    best = max(fired, key=lambda k: predictable.removed(k) - null[k])
    return (
        f"{entry.effect} is named, but a predictor fitted on the training part removes "
        f"{predictable.removed(best):.2f} of the held-out residual ({best}), against up to "
        f"{null[best]:.2f} from the fitted noise alone in {noise_null.NULL_QUANTILE:.0%} of "
        f"{noise_null.NULL_DRAWS} draws: a deterministic term outside the library may "
        "describe the record better (a disturbance near the loop's resonance is one); the "
        "discovery (`--discover`, the command's default) weighs one against the noise"
    )


def _up_to_model_form(fit: StepFit, nominal_fit: StepFit) -> StepFit:
    """`fit` (deterministic, not explaining the record) with `explains_model_form`: what it
    leaves is within `openworld.MODEL_FORM` of the nominal's gap on both parts."""
    form = bool(
        fit.gap_train <= openworld.MODEL_FORM * nominal_fit.gap_train
        and fit.gap_held <= openworld.MODEL_FORM * nominal_fit.gap_held
    )
    return dataclasses.replace(fit, explains_model_form=form, explains=form)


def _hidden_lag_note(nuisances: nuisance.NuisanceTest, rec: StepRecord) -> str:
    """What a `none` on a measured input cannot rule out: a lag of the loop up to
    `nuisance_test`'s `hidden_lag_samples`, which the input channel's fitted delay takes up."""
    delay = nuisances.input_delay_samples
    hidden = nuisances.hidden_lag_samples
    return (
        f"the input channel's delay behind the output was fitted (the output moves "
        f"{abs(delay):.2f} samples {'before' if delay >= 0 else 'after'} the column shows a "
        f"change, {rec.dt_sample * 1e6:.3g} µs a sample): a lag of the loop (a torquer lag, "
        f"an output filter) of up to {hidden:.1f} samples ({nuisances.hidden_lag_s * 1e6:.3g}"
        f" µs, for a channel delay of at most {DELAY_LIMIT:g} samples and the sampling phase) "
        "would hide in it and "
        "is not ruled out; where that delay is known, give it (`--input-delay`, "
        "`StepData.input_delay`) and the output's lateness is judged beyond it"
    )


def ranking_entry(
    fit: StepFit,
    nominal_fit: StepFit,
    *,
    n_train: int,
    slack: float,
    predictable: openworld.Predictability,
) -> RankingEntry:
    """A candidate's entry in the diagnosis's ranking (`RankingEntry`; its `to_dict` is
    `DiagnosisResult.ranking`'s row): its evidence 2 ln B over the nominal model (Schwarz:
    ln n per parameter), whether it is significant (by `slack` more than `SIGNIFICANCE`,
    improving the held-out error, its nested fit not failed), explains and is credible, and
    what it closes of the nominal's held-out gap; a noise model's whiteness and whether the
    misfit it absorbs is predictable (`predictable`: `openworld.predictability`, or
    `noise_null.calibrated`'s against the candidate's own noise)."""
    evidence = 2 * (
        fit.log_likelihood
        - 0.5 * fit.k * math.log(n_train)
        - assess.baseline(fit, nominal_fit).log_likelihood
    )
    if fit.stochastic:
        improves = fit.ms_held_one_step < nominal_fit.ms_held
    else:
        improves = fit.ms_held < nominal_fit.ms_held
    if not np.isfinite(evidence):
        evidence = -np.inf
    fraction = openworld.explained_fraction(nominal_fit.gap_held, fit.gap_held)
    # A nested fit that ended below the nominal's likelihood is a solver failure (it
    # was restarted from the nominal optimum first): flagged, never an effect.
    # And one whose reported ln L, which the evidence compares, ended below the nominal's
    # (`assess.reported_below`): its evidence is no evidence.
    solver_failed = assess.nested_failed(fit, nominal_fit)
    failed = solver_failed or assess.reported_below(fit, nominal_fit)
    # A noise that absorbs a predictable misfit explains none of it.
    absorbed = fit.stochastic and bool(predictable.deterministic)
    noise = {}
    if fit.stochastic:
        noise = {
            "one_step_whiteness": fit.one_step_whiteness,
            "variance_consistent": fit.variance_consistent,
            # What each predictor removes from the fitted noise alone (`noise_null`; None
            # where the fixed fraction did not call the misfit deterministic).
            "predictability_null_quantile": (
                predictable.null_quantile
                if isinstance(predictable, noise_null.CalibratedPredictability)
                else None
            ),
        }
    return RankingEntry(
        effect=fit.effect,
        evidence=float(evidence),
        fit_failed=failed,
        solver_failed=solver_failed,
        objective_below_nominal=max(assess.nested_shortfall(fit, nominal_fit), 0.0),
        objective_round_off=assess.nested_round_off(fit, nominal_fit),
        at_no_effect=fit.optimum_shortfall is not None,
        optimum_log_likelihood_below_nominal=fit.optimum_shortfall,
        log_likelihood_below_nominal=max(assess.log_likelihood_shortfall(fit, nominal_fit), 0.0),
        significant=bool(evidence - slack >= SIGNIFICANCE and improves and not failed),
        stochastic=fit.stochastic,
        explains=fit.explains,
        explains_up_to_model_form=fit.explains_model_form,
        plausible=fit.plausible and not failed,
        explained_fraction=0.0 if failed or absorbed else fraction,
        gap_after_V=fit.gap_held,
        gap_shrink=(
            1 - fit.gap_held / nominal_fit.gap_held if nominal_fit.gap_held > 0 else 0.0
        ),
        held_out_mean_square=fit.ms_held,
        held_out_one_step_mean_square=fit.ms_held_one_step,
        params=fit.params,
        converged=fit.converged,
        fit_steps=fit.steps,
        out_of_prior=list(fit.out_of_prior),
        deterministic_misfit=absorbed,
        **noise,
    )


def _noise_not_credited(name: str, fit: StepFit, entry: RankingEntry) -> str:
    """Why the best library effect, a noise model, does not explain the record: its
    held-out one-step errors are not white, or its free-run errors are not of the size it
    predicts (`assess.assess_fit`)."""
    why = []
    white = fit.one_step_whiteness
    if white is not None and not white.white:
        why.append(
            "its one-step prediction errors on the held-out part are not white (Ljung–Box "
            f"p = {white.p_value:.2g} over {white.lags} lags)"
        )
    if fit.variance_consistent is False:
        ratios = ", ".join(f"{r:.2g}" for r in fit.free_run_over_noise_variance or ())
        why.append(
            "its free-run errors are not of the size it predicts (mean square over its "
            f"variance, training and held-out: {ratios}; within "
            f"{1 / assess.NOISE_VARIANCE_FACTOR:g}–{assess.NOISE_VARIANCE_FACTOR:g} "
            "expected)"
        )
    if not why:
        why.append("it is not significant and credible")
    described = f"{fit.model.description}; " if fit.model is not None else ""
    return (
        f"the best library effect, {name} ({described}evidence "
        f"2 ln B = {entry.evidence:.1f}), does not explain the record: "
        + " and ".join(why)
        + " — the record's noise is not that model's (coloured another way, or entering "
        "at another place) or a deterministic misfit remains"
    )


def _pct(x: float) -> str:
    return f"{x:+.1%}" if abs(x) < 10 else f"{x:+.3g}×"


def _reason(
    decision,
    nominal_fit: StepFit,
    by_name: dict[str, StepFit],
    entries,
    rec: StepRecord,
    predictable: openworld.Predictability,
    remaining,
    sigma,
    where,
    nuisances: nuisance.NuisanceTest,
):
    whiteness = nominal_fit.whiteness  # (the nominal fit's, set by `evaluate`)
    assert whiteness is not None
    path = decision.path
    verdict = decision.verdict
    floor = f"{sigma:.3g} V noise floor"
    if path == "domain":
        return "; ".join(rec.domain_problems) + "."
    if path == "nuisances":
        return (
            "the refitted nominal model reaches the noise floor only with strained nuisances: "
            + nuisance.strained_sentence(nuisances, nominal_fit)
            + "."
        )
    if verdict == "none":
        return (
            "the refitted nominal model leaves the held-out residual at the noise floor "
            f"(excess {nominal_fit.gap_held / sigma:.2f}× the {floor}) and white "
            f"(Ljung–Box p = {whiteness.p_value:.2g}); no effect is significant."
        )
    entry = {e.effect: e for e in entries}
    if verdict == "cannot_tell":
        a, b = decision.tied
        return (
            f"{a} and {b} both bring the held-out gap to the floor and their evidence differs by "
            f"{abs(entry[a].evidence - entry[b].evidence):.1f} (< 6 on the 2 ln B scale): "
            "the record cannot tell them apart."
        )
    if verdict != "unexplained":
        fit = by_name[verdict]
        text = (
            f"{verdict} brings the held-out gap from {nominal_fit.gap_held:.3g} V to "
            f"{fit.gap_held:.3g} V ({fit.gap_held / sigma:.2f}× the {floor}); evidence "
            f"2 ln B = {entry[verdict].evidence:.1f} over the nominal model"
        )
        if fit.explains_model_form:
            text += (
                f"; what remains ({fit.gap_held / nominal_fit.gap_held:.1%} of the gap it "
                "closed) stands above the floor: the effect is right, and the record's physics "
                "differs from its model in detail"
            )
        if fit.stochastic:
            null = entry[verdict].predictability_null_quantile
            beyond = (
                " no more than from the fitted noise alone (its "
                f"{noise_null.NULL_QUANTILE:.0%} quantiles over {noise_null.NULL_DRAWS} draws: "
                f"{null['input_locked']:.2f}, {null['periodic']:.2f}, {null['trend']:.2f})"
                if null
                else ""
            )
            text += (
                "; the misfit is not predictable from the input changes, a periodic component "
                "or a trend (held-out fractions removed: "
                f"{predictable.input_locked:.2f}, {predictable.periodic:.2f}, "
                f"{predictable.trend:.2f}{beyond}), and with the correlated noise the "
                "one-step prediction errors are white"
            )
        return text + "."
    parts = []
    if not nominal_fit.converged:
        parts.append("the nominal refit did not converge")
    if nominal_fit.out_of_prior:
        moved = []
        for field in nominal_fit.out_of_prior:
            if field in REFIT_FIELDS:
                j = REFIT_FIELDS.index(field)
                z = nominal_fit.z[j]
                shift = math.exp(rec.prior_sigma[j] * z) - 1
                moved.append(f"{field} {_pct(shift)} ({z:+.1f}σ)")
        shifts = ", ".join(moved)
        if "test_winding_gain" in nominal_fit.out_of_prior:
            shifts += (
                ", " if shifts else ""
            ) + f"test winding gain ×{abs(nominal_fit.gain):.3g}"
        parts.append(
            f"the refit needs {shifts}: beyond {openworld.PRIOR_LIMIT:.0f}σ of the prior "
            "(not this device? give its values with --params)"
        )
    partial = decision.best_partial
    if partial and by_name[partial].stochastic:
        # A noise model is credited by its one-step errors and the size of its free-run
        # errors, not by a free-run gap (which a noise cannot close): say which failed.
        parts.append(_noise_not_credited(partial, by_name[partial], entry[partial]))
    elif partial:
        parts.append(
            f"the best library effect, {partial}, explains "
            f"{entry[partial].explained_fraction:.0%} "
            f"of the excess; {remaining:.3g} V ({remaining / sigma:.1f}× the {floor}) remains"
        )
    else:
        significant = [e for e in entries if e.significant]
        if nominal_fit.explains and not whiteness.white and not significant:
            parts.append(
                "the held-out residual is at the floor but not white (Ljung–Box p = "
                f"{whiteness.p_value:.2g}) and no library effect is significant"
            )
        else:
            parts.append(
                f"the held-out gap is {remaining:.3g} V ({remaining / sigma:.1f}× the {floor}) "
                "and no library effect that is significant and credible brings it to the floor"
            )
    stochastic = [e for e in entries if e.stochastic and e.significant]
    if stochastic and stochastic[0].deterministic_misfit:
        null = stochastic[0].predictability_null_quantile
        tests = ("input_locked", "periodic", "trend")
        if null:  # among the tests that beat the noise's own null
            tests = tuple(
                k for k in tests
                if predictable.removed(k) >= openworld.PREDICTABLE
                and predictable.removed(k) > null[k]
            ) or tests
        best = max(tests, key=predictable.removed)
        what = {
            "input_locked": "locked to the input changes",
            "periodic": f"periodic ({predictable.frequency_Hz:.4g} Hz)",
            "trend": "a trend",
        }[best]
        beyond = (
            f", against at most {null[best]:.0%} from the fitted noise alone in "
            f"{noise_null.NULL_QUANTILE:.0%} of {noise_null.NULL_DRAWS} draws"
            if null
            else ""
        )
        parts.append(
            f"correlated noise would absorb it, but the misfit is {what} (a predictor fitted on "
            f"the training part removes {predictable.removed(best):.0%} of the held-out residual"
            f"{beyond}): deterministic, not noise"
        )
    if where:
        parts.append(where)
    return "; ".join(parts) + "."

