"""The step fits at a record's residual scale: a record that no linear candidate brings near
its noise floor has them fitted again at the nominal fit's σ̂ (`reweight_far_records`, with
`to_floor` and `put_back_at_sigma_hat` around the later fits, made at the floor); a nested
fit whose reported ln L ended below its nominal's is fitted again where the two likelihoods
agree (`retry_at_residual_scale`); one still below beyond round-off, and one below by less
than the slack that triggers the refits, is reported at its no-effect value
(`settle_at_no_effect`).

The solver maximises a penalised likelihood with the noise fixed at σ_ref (`StepFit.objective`);
the evidence compares the profiled one, the noise variance estimated (`StepFit.log_likelihood`).
From the nominal optimum a nested fit cannot end below the nominal's objective, but where the
nominal fit's residual RMS σ̂ lies far from σ_ref the two weigh the residual against the
priors differently, and the nested fit can end below the nominal's reported ln L: at a fixed
σ_ref far below σ̂ a unit of residual is worth more than a unit of prior, and a fit that
trades a measured input's levels or the device's prior for a little residual gains in the
objective and loses in ln L. With σ_ref = σ̂ the two agree to first order: for a fit whose
objective (residual sum RSS over 2σ̂², plus penalty P) ends at or below the nominal's,
ΔlnL ≥ n/2 (r − 1 − ln r) ≥ 0, r the ratio of the two RSS, when σ̂² = RSS_nominal / n (the
reported ln L also leaves out the effect's own prior, so not exactly).
The nominal's own refit at σ̂ moves (its σ̂ grows as it trades residual for its priors), so
a fit still below is fitted again at the new σ̂ (`RESCALE_ROUNDS`), towards σ_ref = σ̂.

Seen in the measured-input harness's 100-per-class draw at 01ff127: 305 fits flagged on
2,200 rankings (`fit_failed`), none below the nominal's objective. On a lag record with a
measured input (record 122) the nominal, 219 × the floor off, bent the input's levels by
thousands of their σ and the drift fit, from there, ended 26,626 below its ln L; on a
band-pass record (710, 4,400 × the floor off) the stop fits at the floor ended 7,005 and
7,070 below the nominal's fit there.
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .assess import (
    NESTED_LNL_SLACK,
    at_no_effect,
    below_beyond_round_off,
    log_likelihood_shortfall,
    nested_failed,
    reported_below,
)
from .batch import fit_grouped
from .fit import fit_linear
from .model import REFIT_BOUND
from .starts import nominal_start
from .state import Baseline, StepFit, StepRecord


def at_noise_scale(rec: StepRecord, sigma: float) -> StepRecord:
    """`rec` with its fits' noise floor σ_ref set to `sigma` [V] (its context's
    `sigma_ref`, data to the compiled fits: no recompilation)."""
    ctx = eqx.tree_at(lambda c: c.sigma_ref, rec.ctx, jnp.asarray(sigma))
    return dataclasses.replace(rec, ctx=ctx)


REWEIGHT_ABOVE = 2.0
"""A record that no linear candidate fits to within this many noise floors σ_ref (each one's
training residual RMS above it, after the restarts from the nominal optimum, which may take
the nominal's own refit to a device far from its prior and to the floor) has its linear
candidates fitted again with σ_ref = σ̂, the nominal fit's residual RMS, each from its own
optimum (the same compiled program: σ_ref is data). The solver weighs the residual against
the priors at σ_ref, the reported ln L (the evidence's) at the σ̂ it estimates: far above
the floor the two optima part, and a nested fit could end below the nominal's ln L although
its objective did not (`assess.NESTED_LNL_SLACK`). One σ_ref for all the linear candidates
keeps their objectives comparable. Where one candidate comes near the floor the record is
left alone: weighed at the nominal's larger scale, the priors of a fit that explains the
record pull its nuisances (an output-filter record then read `torquer_lag`). The later fits
(noise in the loop, stops) stay at the floor, where a model that explains the record leaves
its residuals (at σ̂ a stop fit stopped short, its device 6σ out, and a stop record read
`unexplained`), each judged against the nominal's fit at the floor
(`StepFit.baseline`)."""


def reweight_far_records(fits, records: list[StepRecord], effects, linear, nominal) -> dict:
    """Refit the linear candidates of the records that none of them brings near the floor at
    the nominal fit's residual scale (`REWEIGHT_ABOVE`); `fits` and `records` updated in place.
    Returns {record index: (its context at the floor, the nominal's fit there)}. (Not a
    record outside the model family, whose nominal alone was fitted: `entry.DOMAIN_NOTE`.)"""
    starts, floor = {}, {}
    for i, rec in enumerate(records):
        if rec.domain_problems:
            continue
        sigma_ref = float(np.asarray(rec.ctx.sigma_ref))
        sigma_hat = math.sqrt(max(float(fits[i][0].innovation_variance), 0.0))
        # (Only where no linear candidate comes near the floor: one that explains the
        # record, weighed at the nominal's scale, strains its nuisances.)
        least = math.sqrt(max(min(float(f.innovation_variance) for f in fits[i]), 0.0))
        if not least > REWEIGHT_ABOVE * sigma_ref:
            continue
        floor[i] = (rec.ctx, fits[i][0])
        records[i] = at_noise_scale(rec, sigma_hat).with_note(
            f"linear models fitted at the record's residual scale ({sigma_hat / sigma_ref:.3g} × "
            "the noise floor)"
        )
        guesses = np.array(rec.guesses_linear)
        guesses[:, -1, :] = np.stack([f.w_trained for f in fits[i]])  # each from its optimum
        starts[i] = guesses
    entries = fit_grouped(
        fit_linear, nominal, records, starts, linear, effects, "diagnose step (reweighted)"
    )
    for i, again in entries.items():
        fits[i] = again
    return floor


def to_floor(fits, records: list[StepRecord], floor: dict) -> dict:
    """On the rescaled records (`floor`, `reweight_far_records`'s), the context at the
    floor and the nominal's fit there in place of those at σ̂, for the later fits (noise in
    the loop, stops); returns {i: the nominal's fit at σ̂} for `put_back_at_sigma_hat`.
    `fits` and `records` updated in place."""
    at_sigma_hat = {}
    for i, (ctx, nominal_at_floor) in floor.items():
        records[i] = dataclasses.replace(records[i], ctx=ctx)
        at_sigma_hat[i], fits[i][0] = fits[i][0], nominal_at_floor
    return at_sigma_hat


def put_back_at_sigma_hat(fits, floor: dict, at_sigma_hat: dict, n_linear: int) -> None:
    """`to_floor` undone for the verdict: on the rescaled records (`floor`: {i: (context,
    the nominal's fit at the floor)}), the nominal's fit at σ̂ back in `fits[i][0]`; the
    linear candidates (`fits[i][1:n_linear]`, fitted at σ̂ with it) judged against it as
    they are; the later fits (noise in the loop, stops: at the floor) judged against the
    floor's nominal, and their evidence measured from it (`StepFit.baseline`). `fits`
    updated in place."""
    for i, (_, nominal_at_floor) in floor.items():
        at_floor = Baseline.of(nominal_at_floor)
        fits[i] = [at_sigma_hat[i], *fits[i][1:n_linear]] + [
            dataclasses.replace(f, baseline=at_floor) for f in fits[i][n_linear:]
        ]


RESCALED_NOTE = "refitted at σ̂, the residual RMS of the nominal fit that each is judged against"
"""Part of a record's note where a candidate was refitted by `retry_at_residual_scale`."""


def _past_bound(nominal_fit: StepFit) -> list[str]:
    """The nominal refit's shifts past `model.REFIT_BOUND` ("name +13.1σ"; empty if none)."""
    return [
        f"{name} {z:+.1f}σ" for name, z in nominal_fit.device_shifts() if abs(z) > REFIT_BOUND
    ]


def _losers(fits: list[StepFit]) -> list[int]:
    """The candidates (indices into `fits`, the nominal first) whose reported ln L ended
    below the nominal's (`assess.reported_below`) though their objective did not: the two
    likelihoods' disagreement, not the solver's failure (`assess.nested_failed`). None
    where the nominal's refit rests past `model.REFIT_BOUND`: there the bound's penalty,
    in the objective and not in the reported ln L at any scale, is what a nested fit
    trades, and counting that trade as evidence would credit an effect for easing a device
    far outside its prior (`settle_at_no_effect` reports them at the no-effect value)."""
    if _past_bound(fits[0]):
        return []
    return [
        k for k, f in enumerate(fits) if k > 0
        and reported_below(f, fits[0]) and not nested_failed(f, fits[0])
    ]


RESCALE_ROUNDS = 4
"""Rounds of `retry_at_residual_scale`, each at the σ̂ of the last round's nominal refit.
Refitted at a larger σ_ref the nominal trades residual for its priors and its σ̂ grows
(on the drift twin of the tests' measured inputs from 2.34 to 5.5 × the floor in one
round), so a fit at the old scale is not yet where the two likelihoods agree: after one
round the lag fits there still ended 4.6 below (from 45). The rounds go on towards the
fixed point σ_ref = σ̂, the profile likelihood's optimum."""


def retry_at_residual_scale(
    fits: list[list[StepFit]],
    records: list[StepRecord],
    effects,
    stages: list[tuple[object, list[int]]],
    nominal,
    floor: dict,
) -> dict[tuple[int, int], StepFit]:
    """Fit each candidate of `_losers` again with σ_ref the residual RMS σ̂ of the nominal
    fit it is judged against (`assess.baseline`: the record's nominal fit, or on a record
    of `floor` — `reweight_far_records` — the nominal's fit at the floor for the later
    fits), from its own optimum and from that nominal's optimum with the effect off, and
    judge it against the nominal's refit at that scale (its `StepFit.baseline`). The refit
    replaces the old one where it ends less far below its baseline's reported ln L (and not
    below its objective). A fit still below is fitted again at the σ̂ of that refit, up to
    `RESCALE_ROUNDS` rounds. The record's note says what was refitted. `stages`: (compiled
    fit, its candidates — 1-based indices into `effects`, 0 the nominal) in the order of a
    record's fits, the linear stage first. `fits` and `records` updated in place. Returns
    {(record, candidate): the nominal's refit each refit taken is judged against}, for
    `settle_at_no_effect`."""
    # {(record, judged at the floor): (the nominal fit judged against, the losers)}: a
    # record's two kinds are fitted in turn (one record's fits are one batch row).
    pending: dict[tuple[int, bool], tuple[StepFit, list[int]]] = {}
    before: dict[int, dict[int, float]] = {}
    for i, rec in enumerate(records):
        if rec.domain_problems:
            continue
        for k in _losers(fits[i]):
            at_floor = fits[i][k].baseline is not None
            base = floor[i][1] if at_floor else fits[i][0]
            pending.setdefault((i, at_floor), (base, []))[1].append(k)
            before.setdefault(i, {})[k] = log_likelihood_shortfall(fits[i][k], fits[i][0])
    kept: dict[int, dict[int, float]] = {}  # {record: {candidate: the scale it was taken at}}
    judged: dict[tuple[int, int], StepFit] = {}
    for _ in range(RESCALE_ROUNDS):
        for at_floor in (False, True):
            wanted = {i: v for (i, f), v in pending.items() if f == at_floor}
            if not wanted:
                continue
            for i, nominal_at, took in _refit_at_scale(
                fits, records, effects, stages, nominal, wanted
            ):
                del pending[(i, at_floor)]
                for k, scale in took.items():
                    kept.setdefault(i, {})[k] = scale
                    judged[(i, k)] = nominal_at
                still = [k for k in wanted[i][1] if reported_below(fits[i][k], fits[i][0])]
                if still and took:
                    pending[(i, at_floor)] = (nominal_at, still)
    for i, took in kept.items():
        names = ", ".join(fits[i][k].effect for k in took)
        sigma_ref = float(np.asarray(records[i].ctx.sigma_ref))
        lo, hi = (f(took.values()) / sigma_ref for f in (min, max))
        scales = f"{lo:.3g}" if f"{lo:.3g}" == f"{hi:.3g}" else f"{lo:.3g}–{hi:.3g}"
        records[i] = records[i].with_note(
            f"{names} {RESCALED_NOTE} (σ̂ = {scales} × this record's σ_ref): at σ_ref the "
            f"reported ln L of each had ended up to {max(before[i][k] for k in took):.4g} "
            "below that nominal's, the solver weighing the residual against the priors "
            "otherwise than the likelihood the evidence compares"
        )
    return judged


def _refit_at_scale(fits, records, effects, stages, nominal, wanted):
    """One round of `retry_at_residual_scale` for the records of `wanted` ({record: (the
    nominal fit its losers are judged against, the losers)}): yields (record, the nominal's
    refit at that fit's σ̂, {each loser taken: σ̂})."""
    def name(candidate: int) -> str:
        return "nominal" if candidate == 0 else effects[candidate - 1].name

    linear_fn, linear = stages[0]
    scaled = list(records)
    for i, (base, _) in wanted.items():
        scaled[i] = at_noise_scale(records[i], math.sqrt(max(float(base.innovation_variance), 0)))
    # The nominal and the linear candidates at σ̂: each from its own optimum and from the
    # baseline's optimum with the effect off (the same compiled program as the first fits:
    # σ_ref and the starts are data).
    starts = {}
    for i, (base, _) in wanted.items():
        own = {f.effect: f.w_trained for f in fits[i]}
        guesses = np.array(records[i].guesses_linear)
        for row, candidate in enumerate(linear):
            guesses[row, 0, :] = own.get(name(candidate), nominal_start(base.w_trained))
            guesses[row, 1, :] = nominal_start(base.w_trained)
        starts[i] = guesses
    refits = fit_grouped(
        linear_fn, nominal, scaled, starts, linear, effects, "diagnose step (at σ̂)"
    )
    new = {i: {f.effect: f for f in again} for i, again in refits.items()}
    # The nominal's refit moved from the start they shared: a linear loser whose refit ends
    # above its objective there is fitted once more, its second start that refit's optimum
    # with the effect off (from which it cannot end above it), the nominal's refit held.
    # (Seen on a periodic-disturbance record with a measured input, harness record 817: both
    # lags ended 0.26–0.29 above the nominal's refit in objective, their ln L above it.)
    again_starts = {}
    for i, (_, mine) in wanted.items():
        nominal_at = new[i]["nominal"]
        if any(
            fits[i][k].effect in new[i] and nested_failed(new[i][fits[i][k].effect], nominal_at)
            for k in mine
        ):
            guesses = np.array(starts[i])
            for row, candidate in enumerate(linear):
                guesses[row, 0, :] = new[i][name(candidate)].w_trained
                guesses[row, 1, :] = nominal_start(nominal_at.w_trained)
            again_starts[i] = guesses
    if again_starts:
        for i, again in fit_grouped(
            linear_fn, nominal, scaled, again_starts, linear, effects, "diagnose step (at σ̂)"
        ).items():
            for fit in again[1:]:  # (the nominal's refit held)
                if fit.objective < new[i][fit.effect].objective:
                    new[i][fit.effect] = fit
    # The later stages' losers, from their own optimum and the nominal refit's.
    for fn, members in stages[1:]:
        names = [name(c) for c in members]
        stage_starts = {}
        for i, (_, mine) in wanted.items():
            if not any(fits[i][k].effect in names for k in mine):
                continue
            at_nominal = nominal_start(new[i]["nominal"].w_trained)
            own = {f.effect: f.w_trained for f in fits[i]}
            rows = [[own.get(n, at_nominal), at_nominal] for n in names]
            stage_starts[i] = np.asarray(rows, dtype=np.float64)
        if not stage_starts:
            continue
        for i, again in fit_grouped(
            fn, nominal, scaled, stage_starts, members, effects, "diagnose step (at σ̂)"
        ).items():
            new[i].update({f.effect: f for f in again})
    for i, (_, mine) in wanted.items():
        nominal_at = new[i]["nominal"]
        took = {}
        for k in mine:
            old = fits[i][k]
            candidate = dataclasses.replace(new[i][old.effect], baseline=Baseline.of(nominal_at))
            if nested_failed(candidate, nominal_at):
                continue
            if log_likelihood_shortfall(candidate, nominal_at) < log_likelihood_shortfall(
                old, fits[i][0]
            ):
                fits[i][k] = candidate
                took[k] = float(np.asarray(scaled[i].ctx.sigma_ref))
        yield i, nominal_at, took


NO_EFFECT_NOTE = "reported at the no-effect value, where each is the nominal model exactly"
"""Part of a record's note where `settle_at_no_effect` replaced a fit."""


def settle_at_no_effect(
    fits: list[list[StepFit]],
    records: list[StepRecord],
    floor: dict,
    base,
    judged: dict[tuple[int, int], StepFit] | None = None,
) -> None:
    """Replace each nested fit whose reported ln L still ends below the nominal's beyond
    round-off after `retry_at_residual_scale` (`assess.below_beyond_round_off`: within
    `assess.NESTED_LNL_SLACK` no refit is tried), and whose objective does not (a solver
    failure stays flagged, `assess.nested_failed`), by its
    effect at the no-effect value (`assess.at_no_effect`): the nominal model exactly, and a
    point of the nested model, whose maximised ln L is therefore at least the nominal's. The
    solver's optimum maximised the penalised objective, not this ln L; where the nominal's
    refit rests past `model.REFIT_BOUND` the steep penalty that holds it there is in the one
    and not the other, and the nested fits trade ln L for easing it (seen on the tests'
    device with three times the moment of inertia, its refit at +13.1σ: the lag and
    output-noise fits, each below the nominal's objective, 2,661 and 2,574 lower, read
    evidence −216 and −1,368; 33 of the 36 flags left on 86 flagged records of the
    measured-input harness at e8998dd, all on band-pass records; on the draw's other 111
    flagged records at ae77032, 38 fits so reported, 37 past the bound). Its evidence is then
    −k ln n, its ranking entry says so (`at_no_effect`), and the record's note says why.
    `floor` as in `retry_at_residual_scale` (a fit judged against the nominal's fit at the
    floor takes that fit's values), `judged` what it returns (a fit it refitted takes the
    values of the nominal's refit it is judged against); `base` the nominal device
    (`ServoParams`). `fits` and `records` updated in place."""
    judged = judged or {}
    for i, rec in enumerate(records):
        if rec.domain_problems:
            continue
        settled = {}
        for k, fit in enumerate(fits[i]):
            if k == 0 or nested_failed(fit, fits[i][0]):
                continue
            if not below_beyond_round_off(fit, fits[i][0]):
                continue
            nominal_fit = judged.get((i, k))
            if nominal_fit is None:
                nominal_fit = floor[i][1] if fit.baseline is not None else fits[i][0]
            fits[i][k] = at_no_effect(nominal_fit, fit, rec, base)
            settled[fit.effect] = fits[i][k].optimum_shortfall
        if not settled:
            continue
        past = _past_bound(fits[i][0])
        if past:
            why = (
                f"the nominal's refit rests past its bound of ±{REFIT_BOUND:g}σ "
                f"({', '.join(past)}), held there by a steep penalty that the solver "
                "minimises and the reported ln L leaves out, and each fit eased it at the cost "
                "of ln L; the device is far outside its prior"
            )
        elif max(settled.values()) > NESTED_LNL_SLACK:
            why = (
                "the solver weighs the residual against the priors otherwise than the ln L "
                "the evidence compares, and the refits at σ̂ did not close it"
            )
        else:
            why = (
                "the solver weighs the residual against the priors at the noise floor, the "
                "reported ln L at the residual's estimated variance, and it holds the "
                "effect's own prior, which the ln L leaves out: each fit traded a little ln L "
                "for them"
            )
        records[i] = records[i].with_note(
            f"{', '.join(settled)} {NO_EFFECT_NOTE} (evidence −k ln n): the solver's optimum "
            f"of each had ended up to {max(settled.values()):.4g} below the nominal's "
            f"reported ln L, its penalised ln L, which the solver maximised, not below the "
            f"nominal's; {why}"
        )

