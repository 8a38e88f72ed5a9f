"""The `step` kind's entry: `diagnose_step` prepares each record (`record.prepare`), fits
every linear candidate of records of one shape as one batch, restarts a nested fit that
ended below the nominal's from the nominal optimum, fits the stop candidate where no linear
model explains a record, fits again at its nominal's residual scale a fit whose reported ln L
ended below the nominal's (`rescale`), and judges each record (`verdict.evaluate`); a lag
tie gets the experiment that would break it (`design`). The kind itself is described in the
package `accel_jax.diagnose.step`.
"""

from __future__ import annotations

import concurrent.futures

import numpy as np

from ..._data import NominalDevice, StepData
from ..._deprecated import moved_names
from ..._runtime import in_background, spare_cpu
from ..base import DiagnosisResult, require_float64
from .assess import (
    NESTED_ABSOLUTE,
    NESTED_RESTART_ABOVE,
    explains_deterministically,
    nested_failed,
    nested_losers,
    nested_shortfall,
)
from .batch import compile_grouped
from .batch import fit_grouped as _fit_grouped
from .effects import step_effects
from .fit import fit_contact, fit_linear, fit_moment, fit_nonlinear
from .layout import W
from .record import _guesses, prepare
from .starts import CONTACT_GRID, contact_from_clamp, nominal_start
from .state import StepFit, StepRecord
from .question import weigh_discovery
from .rescale import (
    put_back_at_sigma_hat,
    retry_at_residual_scale,
    reweight_far_records,
    settle_at_no_effect,
    to_floor,
)
from .verdict import evaluate, noise_verdict


DOMAIN_NOTE = (
    "no effect fitted: the record failed the domain check, so it lies outside the model "
    "family the effects belong to (only the nominal model is refitted, for the gap)"
)
"""The note of a record that failed the domain check (`record.prepare`). Its verdict is the
check's `unexplained` whatever the effects would reach, so they are not fitted (they were,
restarted and reweighted too: 57.1 s against 12.3 s now on a slow sensor's record,
docs/performance.md)."""

LAG_PAIR = frozenset({"torquer_lag", "output_filter"})
"""The tie that another experiment can break (`design.next_experiments`)."""


def diagnose_step(
    datasets: list[StepData],
    nominal: NominalDevice,
    *,
    recommend: bool = True,
    discover: bool | str = False,
    ceiling: bool = False,
) -> list[DiagnosisResult]:
    """Diagnose step records against a nominal device (docs/models.md §5, `step` kind).

    Records of one length and test sequence size are fitted together: one compilation, the
    batch vmapped and sharded across devices (`accel_jax.sweep`), every candidate model and
    start of a record vmapped. The stop candidate (simulated sample by sample) is fitted
    only for records that no linear model explains.

    **Arguments:**

    - `datasets`: validated `StepData` records (e.g. from `read_csv`).
    - `nominal`: the nominal device and its prior (`NominalDevice`).
    - `recommend`: with a `cannot_tell` between `torquer_lag` and `output_filter`, compute
        the experiment that would separate them (`result.next_experiment`, from the joint
        fit of `joint`: ~10–60 s per such record on a CPU).
    - `discover`: True: for an `unexplained` record that passed the domain check, look for
        the missing term in the term library (`discover`: `result.discovery`, a typed
        `Discovery`, a hypothesis; the verdict stays `unexplained`), and for a noise
        verdict (`verdict.noise_verdict`), where a credible term that brings the held-out
        gap to the floor, while the noise's free run leaves it above the record's floor,
        makes the verdict `unexplained` (`question.weigh_discovery`); "all": for every
        record that passed it (a check that nothing is found where nothing is missing).
    - `ceiling`: with `discover`, also fit the network reference of what a term of the
        loop's states could remove of the held-out gap (`ceiling`: the discovery's
        `ceiling` and each candidate's `ceiling_fraction`; an estimate, never a
        verdict; on a CPU 1–2 min more, the discovery itself ~90 s).

    **Returns:** one `DiagnosisResult` per record, in order. Float64 (needs x64 enabled;
    a `ValueError` otherwise).
    """
    require_float64("the evidence compares log-likelihoods of ~1e4 to within ~1")
    if not (discover is False or discover is True or discover == "all"):
        raise ValueError(f"discover must be False, True or 'all', got {discover!r}.")
    if ceiling and not discover:
        raise ValueError("ceiling=True needs discover: the reference is part of a discovery.")
    effects = step_effects()
    linear, loop_noise, nonlinear, clamp, contact = _stages(effects)
    records = [prepare(data, nominal, effects) for data in datasets]
    # The effects only inside the model family (outside, the nominal alone: `DOMAIN_NOTE`).
    inside = [i for i, rec in enumerate(records) if not rec.domain_problems]
    entries = _fit_grouped(
        fit_linear, nominal, records, {i: records[i].guesses_linear for i in inside},
        linear, effects, "diagnose step",
    )
    outside = {i: rec.guesses_linear[:1] for i, rec in enumerate(records) if rec.domain_problems}
    entries.update(
        _fit_grouped(
            fit_linear, nominal, records, outside, [0], effects, "diagnose step (nominal only)"
        )
    )
    for i in outside:
        records[i] = records[i].with_note(DOMAIN_NOTE)
    # Every record's linear fits (the nominal's alone outside the model family).
    fits: list[list[StepFit]] = [entries[i] for i in range(len(records))]
    # The later stages' programs compiled meanwhile on a spare CPU, for the records that no
    # linear fit explains so far (`_compile_ahead`).
    ahead = _compile_ahead(fits, records, nominal, effects, loop_noise, clamp)
    # Each from the best one's nuisances too, where one ended far below another.
    _restart_from_best(fits, records, effects, linear, nominal)
    # Nested fits never lose: an effect at z = 0 is the nominal model, so a linear
    # candidate whose best fit ends below the nominal's log-likelihood started in the wrong
    # basin. Its record is fitted again with every candidate's second start at the nominal
    # optimum (same program; only where a candidate lost).
    _restart_losers(fits, records, effects, linear, nominal)
    # A record that no linear candidate brings near its noise floor, after the restarts
    # (from its optimum the nominal's own refit may reach the floor: a device far from its
    # prior): its linear fits again at the nominal's residual scale (`rescale.REWEIGHT_ABOVE`),
    # restarted as above where one lost there.
    floor = reweight_far_records(fits, records, effects, linear, nominal)
    _restart_losers(fits, records, effects, linear, nominal, among=set(floor))
    # The later fits (noise in the loop, stops) at the noise floor again: a model that
    # explains the record leaves residuals at the floor, not at the nominal's σ̂. They
    # start from the nominal's fit at the floor (from its optimum, a nested
    # fit cannot end above its objective there), and are judged against it
    # (`StepFit.baseline`); the nominal at σ̂ is put back for the verdict.
    at_sigma_hat = to_floor(fits, records, floor)
    n_linear = len(linear)  # the nominal (0) and the linear candidates: `fits[i][:n_linear]`
    # Noise inside the loop, for the records that no deterministic linear model explains:
    # from its own starts (the nominal fit's device and nuisances), from the output noise's
    # fit (its two parameters have the same meaning) and from the nominal optimum.
    _wait(ahead, "moment")
    _fit_loop_noise(fits, records, effects, loop_noise, nominal)
    # The stop candidate, for the records that no linear model explains.
    stop_starts = {}
    for i, rec in enumerate(records):
        if rec.domain_problems or not nonlinear:
            continue
        if not any(explains_deterministically(f, rec) for f in fits[i]):
            # One start from the nominal fit's device, output offset, gain and initial
            # state with the input's nuisances (change times; a measured input's levels and
            # drift) where the record shows them: the nominal fit may have bent those to
            # absorb the clipping (a measured input's levels by thousands of their standard
            # errors, seen on blind stop records, where no stop fit came back from them in
            # its steps). One from the record's own starting point.
            guesses = np.array(rec.guesses_nonlinear)
            guesses[:, 0, W.BEFORE_EFFECT] = fits[i][0].w[W.BEFORE_EFFECT]
            # And a third: the nominal optimum itself, the effect at its no-effect value
            # (z = 0 is the nominal model), so that a nested fit never ends below the
            # nominal's likelihood (from the peak starts alone, a stop fit lost by
            # thousands on records that a compliant contact clipped).
            at_nominal = np.broadcast_to(
                nominal_start(fits[i][0].w_trained), guesses[:, :1].shape
            )
            stop_starts[i] = np.concatenate([guesses, at_nominal], axis=1)
    rows = {i: nonlinear.index(i) for i in nonlinear}  # each one's row of the guesses
    _wait(ahead, "clamp")
    entries = _fit_grouped(
        fit_nonlinear, nominal, records,
        {i: s[[rows[c] for c in clamp]] for i, s in stop_starts.items()}, clamp, effects,
        "diagnose step (stops)",
    )
    for i, record_fits in entries.items():
        fits[i] = fits[i] + record_fits
    # Compliant stops, where the clamp does not explain the record either: from the
    # record's own starts, from the clamp's fit (its stops as the two clearances) and from
    # the nominal optimum.
    contact_starts = {}
    for i, s in stop_starts.items():
        if not contact or any(explains_deterministically(f, records[i]) for f in fits[i]):
            continue
        mine = s[[rows[c] for c in contact]]
        own, at_nominal = mine[:, :-1], mine[:, -1:]  # its own starts, the nominal optimum
        from_clamp = [
            f for f in fits[i] if f.model is not None and f.model.nonlinear
            and not f.model.contact_stops
        ]
        starts = [own]
        if from_clamp:
            for z_stiffness, z_damping in CONTACT_GRID:
                moved = contact_from_clamp(from_clamp[0], records[i], own[:, :1])
                moved[..., W.EFFECT.start + 2] = z_stiffness
                moved[..., W.EFFECT.start + 3] = z_damping
                starts.append(moved)
        contact_starts[i] = np.concatenate(starts + [at_nominal], axis=1)
    entries = _fit_grouped(
        fit_contact, nominal, records, contact_starts, contact, effects,
        "diagnose step (compliant stops)",
    )
    for i, record_fits in entries.items():
        fits[i] = fits[i] + record_fits
    put_back_at_sigma_hat(fits, floor, at_sigma_hat, n_linear)
    # A fit whose reported ln L ended below its nominal's, its objective not: the two
    # likelihoods part where σ̂ lies far from σ_ref; fitted again at σ̂ (`rescale`).
    stages = [(fit_linear, linear), (fit_moment, loop_noise), (fit_nonlinear, clamp),
              (fit_contact, contact)]
    judged = retry_at_residual_scale(
        fits, records, effects, [(fn, c) for fn, c in stages if c], nominal, floor
    )
    # What is still below: the nested model at its no-effect value, the nominal exactly.
    settle_at_no_effect(fits, records, floor, nominal.params, judged)
    results = []
    for rec, record_fits in zip(records, fits, strict=True):
        fitted = {f.effect for f in record_fits}
        if rec.domain_problems:
            pass  # no effect fitted (`DOMAIN_NOTE`)
        elif not any(effects[i - 1].name in fitted for i in clamp):
            skipped = [e.name for e in effects if e.nonlinear]
            rec = rec.with_note(
                f"{', '.join(skipped)} not fitted: a linear model already explains the record"
            )
        elif contact and not any(effects[i - 1].name in fitted for i in contact):
            rec = rec.with_note(
                f"{', '.join(effects[i - 1].name for i in contact)} not fitted: a model with "
                "inelastic stops or a linear model already explains the record"
            )
        results.append(evaluate(rec.data, nominal, rec, record_fits))
    if discover:
        from .discover import discover as discover_term

        for i, (rec, record_fits, result) in enumerate(zip(records, fits, results, strict=True)):
            noise = noise_verdict(result) is not None
            wanted = discover == "all" or result.verdict == "unexplained" or noise
            if wanted and not rec.domain_problems:
                # From the nominal's fit at the floor, the scale its refits weigh the
                # residual at: from the fit at σ̂ (`rescale.REWEIGHT_ABOVE`) the vibrating stand's
                # CLI test took 477 s, from the floor 318 s (292 s before the rescale
                # existed; one run each on the 2-core CPU).
                start = floor[i][1] if i in floor else record_fits[0]
                result.discovery = discover_term(rec, nominal, start, effects, reference=ceiling)
                weigh_discovery(result)  # a noise verdict against the term
    if recommend:
        for data, rec, result in zip(datasets, records, results, strict=True):
            if result.verdict == "cannot_tell" and set(result.tied) == LAG_PAIR:
                if rec.clock is not None:  # the joint fit takes ≤ MAX_CHANGES
                    result.notes.append(
                        "no next experiment designed: the joint fit that designs it takes "
                        "step sequences, not a clocked sequence of hundreds of changes"
                    )
                    continue
                _recommend(result, data, nominal)
    return results


def _stages(effects) -> tuple[list[int], list[int], list[int], list[int], list[int]]:
    """The candidates (1-based indices into `effects`; 0 the nominal) of each stage, in
    the order their fits are appended to a record's: the nominal and the linear effects,
    noise in the loop, then the nonlinear ones (the clamp's, then the compliant stops')."""
    linear = [0] + [
        i for i, e in enumerate(effects, start=1) if not e.nonlinear and not e.loop_noise
    ]
    loop_noise = [i for i, e in enumerate(effects, start=1) if e.loop_noise]
    nonlinear = [i for i, e in enumerate(effects, start=1) if e.nonlinear]
    clamp = [i for i in nonlinear if not effects[i - 1].contact_stops]
    contact = [i for i in nonlinear if effects[i - 1].contact_stops]
    return linear, loop_noise, nonlinear, clamp, contact


def _compile_ahead(fits, records, nominal, effects, loop_noise, clamp) -> dict:
    """Where a CPU is spare (`_runtime.spare_cpu`), the loop noise's program (`fit_moment`)
    and then the clamp's (`fit_nonlinear`) compiled on a background thread, for the
    records that no linear fit explains after the first linear fits (both stages' own
    test), while the restarts, the rescaled fits and the loop-noise stage run: {stage: its
    future} (`moment`, `clamp`; empty where nothing is compiled ahead). The starts' shapes
    are the stages'. A stage waits for its future and then finds its program compiled;
    where a shape differs it compiles its own, as without this. A record that a restart
    or a rescaled fit explains has had them compiled for nothing, on the spare CPU. The
    results do not change: the same programs, compiled earlier (5–6 s each on a
    6,000-sample record). The compliant contact's program (10 s since 6b8bda1, ~20 s when
    this was measured) is not compiled ahead: it is needed only where the clamp does not
    explain the record, and compiled beside the clamp's fits it made a record that the
    clamp explains 14 s slower (77.2 against 63.6 s, one run each)."""
    if not (loop_noise or clamp) or not spare_cpu():
        return {}
    moment = _loop_noise_starts(fits, records, effects, loop_noise) if loop_noise else {}
    needed = [
        i for i, rec in enumerate(records)
        if not rec.domain_problems
        and not any(explains_deterministically(f, rec) for f in fits[i])
    ]
    if not needed:
        return {}

    def clamp_shape(i):
        _, starts, size = records[i].guesses_nonlinear.shape
        return (len(clamp), starts + 1, size)  # + 1: the nominal optimum

    def compile_for(fn, starts, candidates):
        return lambda: compile_grouped(fn, nominal, records, starts, candidates)

    calls = {}
    if moment:
        calls["moment"] = compile_for(
            fit_moment, {i: s.shape for i, s in moment.items()}, loop_noise
        )
    if clamp:
        calls["clamp"] = compile_for(
            fit_nonlinear, {i: clamp_shape(i) for i in needed}, clamp
        )
    return dict(zip(calls, in_background(*calls.values()), strict=True))


def _wait(ahead: dict, stage: str) -> None:
    """Wait for the compile of `stage` that `_compile_ahead` started, if any; a compile
    that failed there fails again, with its message, where the stage compiles its own
    program."""
    if stage in ahead:
        concurrent.futures.wait([ahead[stage]])


def _fit_loop_noise(fits, records: list[StepRecord], effects, loop_noise, nominal) -> None:
    """Fit the noise-inside-the-loop candidates (`loop_noise`) of the records that no
    deterministic linear model explains; their fits are appended to `fits` in place."""
    if not loop_noise:
        return
    entries = _fit_grouped(
        fit_moment, nominal, records, _loop_noise_starts(fits, records, effects, loop_noise),
        loop_noise, effects, "diagnose step (noise inside the loop)",
    )
    for i, record_fits in entries.items():
        fits[i] = fits[i] + record_fits


def _loop_noise_starts(fits, records: list[StepRecord], effects, loop_noise) -> dict:
    """{record index: the loop-noise candidates' starts} of the records that no
    deterministic linear model explains: their own, the nominal optimum, and the output
    noise's fit (its two parameters have the same meaning)."""
    chosen = [effects[i - 1] for i in loop_noise]
    starts = {}
    for i, rec in enumerate(records):
        if rec.domain_problems or any(explains_deterministically(f, rec) for f in fits[i]):
            continue
        nominal_w = np.asarray(fits[i][0].w_trained)
        own = _guesses(nominal_w, chosen, rec.host, nominal_first=False)
        output_noise = [f for f in fits[i] if f.effect == "colored_noise"]
        extra = [nominal_start(nominal_w)]
        if output_noise:
            moved = np.array(output_noise[0].w_trained, dtype=np.float64)
            extra.append(moved)
        extra_rows = np.broadcast_to(
            np.stack(extra)[None], (own.shape[0], len(extra), own.shape[2])
        )
        starts[i] = np.concatenate([own, extra_rows], axis=1)
    return starts


NESTED_RESTARTS = 2
"""Rounds of restarts from the nominal optimum for candidates that lost to it, each taking
the nominal's own refit too where it ends lower (one that had stopped at its step limit,
or on a record the nominal misfits by thousands of σ, where the solver's relative
tolerance leaves the objective ~1e-6 of itself short). Where a candidate still loses after
them, one more round holds the nominal fit as it is, so that a candidate started at its
optimum (the effect at 0: the nominal model) can only end at or above its likelihood
(Levenberg–Marquardt accepts only steps that lower the objective)."""


RESTART_NOTE = "a candidate's fit ended below the nominal model's likelihood"
"""The start of the record's note when its linear candidates were refitted from the nominal
optimum (`_restart_from_nominal`); the note goes on with each candidate's shortfall."""


def _restart_losers(
    fits, records: list[StepRecord], effects, linear, nominal, among: set[int] | None = None
) -> None:
    """Restart the records (of `among`, default all) whose linear candidates lost to the
    nominal fit by more than `NESTED_RESTART_ABOVE` (`NESTED_RESTARTS` rounds, then one
    holding the nominal); `fits` and `records` are updated in place."""
    for round_ in range(NESTED_RESTARTS + 1):
        losing = [
            i for i in range(len(records))
            if (among is None or i in among) and nested_losers(fits[i], NESTED_RESTART_ABOVE)
        ]
        if not losing:
            return
        _restart_from_nominal(
            fits, records, losing, effects, linear, nominal,
            keep_nominal=round_ == NESTED_RESTARTS,
        )


RESTART_FROM_BEST = 10.0
"""How far above the best linear candidate's objective (χ², twice −ln of the penalised
likelihood) another's fit must end before it is fitted again from the best one's device and
nuisances (`_restart_from_best`)."""


def _restart_from_best(fits, records: list[StepRecord], effects, linear, nominal) -> None:
    """On a record with a measured input, where a linear candidate's fit (the nominal's
    included) ended more than `RESTART_FROM_BEST` above the best one's objective, its priors
    costing more than the best's by as much, fit it again with one start at the
    best fit's device and nuisances (the record's offset, initial state, test gain, change
    times and a measured input's levels and drift) and its own effect's values there (the
    nominal's: none); the other starts at its own optimum. A fit that ends
    lower replaces the old one, and the record says so in its notes.

    Seen on a measured-input record of a drifting disturbance (record 450 of the
    measured-input harness's 100-per-class draw): the nominal took the ramp up in the input
    channel's drift, 34σ of its prior, with its levels and change times bent (objective
    5,262); the drift fit, from there, stopped at 4,334 with the levels still bent, while the
    output-noise fit, from its own start, reached 1,033 with every nuisance within its prior.
    The record read `unexplained`."""
    starts = {}
    for i, rec in enumerate(records):
        # (Only a measured input's record, whose levels and channel drift a model can bend
        # for what another explains, and only a fit whose priors cost more than the best's:
        # on three of the tests' plain records, where the nominal bends its change times
        # for a lag, refitting cost ~50 % of a warm diagnosis, 14.5–14.9 s against 8.9–9.6 s.)
        if rec.ctx.level_sigma is None:
            continue
        best = min(fits[i], key=lambda f: float(f.objective))
        penalty = _penalties(fits[i], rec)
        behind = [
            k for k, f in enumerate(fits[i])
            if float(f.objective) > float(best.objective) + RESTART_FROM_BEST
            and penalty[k] > penalty[fits[i].index(best)] + RESTART_FROM_BEST
        ]
        if not behind:
            continue
        guesses = np.array(rec.guesses_linear)
        for k, fit in enumerate(fits[i]):
            guesses[k, :, :] = fit.w_trained
            if k in behind:
                start = np.array(best.w_trained, dtype=np.float64)
                start[W.EFFECT] = np.asarray(fit.w_trained)[W.EFFECT]
                guesses[k, 0, :] = start
        starts[i] = guesses
    entries = _fit_grouped(
        fit_linear, nominal, records, starts, linear, effects,
        "diagnose step (restarts from the best fit)",
    )
    for i, again in entries.items():
        drops = {
            new.effect: float(old.objective) - float(new.objective)
            for old, new in zip(fits[i], again, strict=True)
        }
        fits[i] = _lower_of(fits[i], again)
        lower = [name for name, drop in drops.items() if drop > RESTART_FROM_BEST]
        if lower:
            records[i] = records[i].with_note(
                f"{', '.join(lower)} refitted from the best linear fit's device and nuisances"
                f" (objective lower by up to {max(drops[n] for n in lower):.3g})"
            )


def _lower_of(fits: list[StepFit], again: list[StepFit], hold_nominal: bool = False):
    """Each candidate's fit of `fits` or of `again` (a refit of the same candidates), the
    one with the lower objective; with `hold_nominal`, the nominal's (first) as it was."""
    return [
        new if new.objective < old.objective and not (hold_nominal and k == 0) else old
        for k, (old, new) in enumerate(zip(fits, again, strict=True))
    ]


def _penalties(fits: list[StepFit], rec: StepRecord) -> list[float]:
    """Each fit's objective less its training residuals' part (Σ of the squared training
    innovations over σ_ref²): what its priors and penalties cost, in χ²."""
    n_train = int(np.sum(~np.asarray(rec.held)))
    scale = float(np.asarray(rec.ctx.sigma_ref)) ** 2
    return [
        float(f.objective) - n_train * float(f.innovation_variance) / scale for f in fits
    ]


def _restart_from_nominal(
    fits, records: list[StepRecord], losing, effects, linear, nominal, *, keep_nominal: bool
) -> None:
    """Fit the records `losing` again, every candidate's second start at the nominal
    optimum with the effect at 0 (the same compiled program); keep each candidate's better
    fit (lower objective), and note it on the record (`records[i]` replaced). With
    `keep_nominal`, the nominal fit (`fits[i][0]`) stays as it was, the reference the
    others started from."""
    # What each candidate lost by before its restart (in ln L), for the record's note.
    lost = {
        i: [
            (f.effect, nested_shortfall(f, fits[i][0])) for f in fits[i][1:]
            if nested_failed(f, fits[i][0], NESTED_RESTART_ABOVE)
        ]
        for i in losing
    }
    again_starts = {}
    for i in losing:
        guesses = np.array(records[i].guesses_linear)
        guesses[:, 1, :] = nominal_start(fits[i][0].w_trained)
        again_starts[i] = guesses
    entries = _fit_grouped(
        fit_linear, nominal, records, again_starts, linear, effects,
        "diagnose step (nested restarts)",
    )
    for i, again in entries.items():
        # (With the nominal held, what its own refit reached from the same start: the
        # solver's tolerance on this record, by which every candidate's evidence is
        # uncertain; stated, not hidden.)
        held_short = 0.5 * (float(fits[i][0].objective) - float(again[0].objective))
        fits[i] = _lower_of(fits[i], again, hold_nominal=keep_nominal)
        if not any(n.startswith(RESTART_NOTE) for n in records[i].notes):
            sizes = ", ".join(f"{name} by {short:.3g}" for name, short in lost[i])
            sizes = f" ({sizes} in ln L; restarted above {NESTED_RESTART_ABOVE:g})" * bool(sizes)
            records[i] = records[i].with_note(
                f"{RESTART_NOTE}{sizes}; refitted from the nominal optimum"
            )
        if keep_nominal and held_short > NESTED_ABSOLUTE:
            records[i] = records[i].with_note(
                f"the nominal fit kept moving on over {NESTED_RESTARTS} restarts and was held "
                f"for the last (its refit from there ended {held_short:.3g} higher in ln L): the "
                "evidence of every effect is uncertain by about that much (the solver's "
                "tolerance on this record)"
            )


def _recommend(result: DiagnosisResult, data: StepData, nominal: NominalDevice) -> None:
    """Attach the next experiment to a lag tie (the record alone, fitted as a set of one)."""
    from .design import compile_refits, next_experiments
    from .joint import fit_set, prepare_set

    prepared = prepare_set([data], nominal)
    ahead = compile_refits(prepared, nominal)  # the designs' programs, beside the set's fit
    fits = fit_set(prepared, nominal)
    result.next_experiment = next_experiments(prepared, nominal, fits, list(result.tied), ahead)
    if result.next_experiment:
        best = result.next_experiment[0]
        result.reason += (
            f" To separate {result.tied[0]} from {result.tied[1]}: {best['description']} "
            f"(expected 2 ln B ≈ {best['expected_2lnB']:.3g})."
        )


# `REWEIGHT_ABOVE` moved to `rescale`, with the rescaling it sets (CHANGELOG.md).
__getattr__ = moved_names(__name__, "accel_jax.diagnose.step.rescale", "REWEIGHT_ABOVE")
