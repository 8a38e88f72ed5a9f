"""Effects real sensors show in a static record, found by forward selection.

`select_sensor_noise` starts from the nominal model (white noise about a constant level)
and adds, one at a time, the effect whose evidence is largest, while it is significant:

- stochastic (fitted by the Whittle likelihood of `accel_jax._noise.spectral`):
  `gauss_markov`, `exp_cosine`, `random_walk`, `flicker` (bias instability, exact 1/f
  spectrum), `high_frequency_noise` (a spectrum rising above a corner towards the Nyquist
  frequency), `bandlimit` (the sensor's output low-pass: a Butterworth filter, tried as
  second-order, alone and with the white noise its signal chain adds after it
  (`filter_floor`, reported as `bandlimit`'s `white_after_filter_sigma`); orders 1, 3 and
  4, Bessel low-passes and moving averages (`chain_filters`) tried in its place once the
  selection is done, `_low_pass_order`; its `shape` reported);
- deterministic: `sinusoid` (a periodic line; added again for each further line, up to
  `MAX_LINES`) and `startup_transient` (a warm-up a e^{−t/τ} at the start of the record);
- `quantization`: the output lies on an ADC grid of step q (found from the values, not
  from the spectrum: the grid's white noise q²/12 is indistinguishable from white noise
  there). It is named when the grid noise is at least `QUANTIZATION_SHARE` of the white
  variance; a finer grid is reported as the record's resolution only.

**Evidence** of an addition (`sensor_model._evidence`): 2 ln B ≈ 2 Δ ln L − k ln J, the
whole record's Whittle likelihood gain with the parameters fitted on the training part (the
first 2/3) alone; added when at least `EVIDENCE` and the paired **held-out check** on the
last third does not refuse it (z below −`HELD_OUT_Z`). A start-up transient is judged by
its exact time-domain likelihood ratio instead, and added before any noise component when
it clears the bar (its decay's power lies in the lowest bins, which a random walk or
flicker fitted first takes for its own). **Backward check** (`_backward`): each effect
judged again against the final model without it, the weakest below `EVIDENCE` removed
until every one stands. **Exchange** (`_exchanges`): each Gauss–Markov, random walk,
flicker or exponential-cosine process tried against the others in its place; better by
`EVIDENCE` replaces it, within `EVIDENCE` either way is a tie. **Explained fraction**: the
share of the nominal model's held-out excess Whittle deviance the model removes. What the
final model leaves is **unexplained** when its held-out excess deviance stands more than
`UNEXPLAINED_Z` standard errors above zero, or a screen of `sensor_screens` finds what no
named effect makes (impulsive events, a linear drift, a rail, a far-from-Gaussian residual,
a spectrum that changes between the halves), or the level shifts (`_level_shift`, against
the final model's own wander; a shift is taken out and the selection run again, up to
`MAX_LEVEL_SHIFTS`, so that no effect of the library takes the credit for it).

Float64, host-driven (NumPy); the fits are one jitted, vmapped Whittle fit per record
length (`accel_jax._noise.spectral`).
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import numpy as np

from .._runtime import beside
from . import spectral
from .held_out import HeldOutCheck
from .record import _sample_interval, _validate_record
from .sensor_model import (
    HELD_OUT_Z,
    PARAMETER_COUNT,
    _evaluate,
    _evaluate_many,
    _evidence,
    _explained,
    _fit_line,
    _held_out_deviance,
    _held_out_z,
    _Model,
    _named,
    _parameters,
    _physical,
    _Record,
    _standardised_peak,
    _transient_test,
    _variogram,
)
from .sensor_arbiter import transient_ties
from .sensor_refine import (
    _backward,
    _collapsed_floor,
    _exchanges,
    _low_pass_order,
    _white_floor,
)
from .sensor_screens import (
    DRIFT_T,
    QUANTIZATION_SHARE,
    SHIFT_SIZE_Z,
    _bursts,
    _drift,
    _haar_scan,
    _haar_variance,
    _non_gaussian,
    _shift_critical_z,
    _spectral_change,
    detect_quantization,
    detect_saturation,
)

EVIDENCE = 10.0
"""2 ln B an effect needs to be added ("strong" on the Kass–Raftery scale)."""


MAX_LINES = 4


MAX_STEPS = 8


UNEXPLAINED_Z = 4.0


@dataclasses.dataclass(frozen=True)
class SensorNoiseSelection:
    """What `select_sensor_noise` found.

    **Fields:** `effects` the named effects in the order added (`quantization` last when
    named); `unexplained` whether the final model leaves a significant held-out misfit;
    `steps` one dict per forward step (the model, its 2 ln B, held-out gain and the
    explained fraction; the steps of effects the backward check removed are left out, and
    the last step's fraction and z are the final model's); `parameters` the final model's
    physical parameters by effect; `held_out` the final model's held-out deviance test
    and what the screens found in its residual (a `HeldOutCheck`: the effects the backward
    check removed, the exchanges and ties, impulsive events, the residual's non-Gaussian
    and spectral-change tests, the level's drift, level shifts and rails);
    `quantization` the grid found (or None); `verdict` the effects joined by '+' ('none'
    when nothing is named and nothing is left, 'unexplained' alone when nothing is named
    but the misfit stays).
    """

    effects: tuple
    unexplained: bool
    steps: list
    parameters: dict
    held_out: HeldOutCheck
    quantization: dict | None
    sample_interval: float
    n_samples: int

    @property
    def verdict(self) -> str:
        names = list(self.effects)
        if self.unexplained:
            names.append("unexplained")
        return "+".join(names) if names else "none"


def select_sensor_noise(
    record, sample_interval: float, *, evidence: float = EVIDENCE, max_lines: int = MAX_LINES
) -> SensorNoiseSelection:
    """Forward selection of the effects a static record shows (module docstring).

    **Arguments:** `record` x (n ≥ 64 samples, any unit); `sample_interval` Δ [s];
    `evidence` the 2 ln B an addition needs; `max_lines` the most periodic lines.

    **Returns:** a `SensorNoiseSelection`. Parameters are in the record's unit. Bad input
    raises `ValueError`.
    """
    with jax.enable_x64(True):
        x = np.asarray(_validate_record("select_sensor_noise", record, min_samples=64), np.float64)
        _sample_interval("select_sensor_noise", sample_interval)
        dt = float(sample_interval)
        shifts = []
        grid = detect_quantization(x)
        record_values = x  # as given: steps taken out below would move its extremes
        fits: dict = {}  # every fit of this call's passes, by record and model (`_evaluate`)
        selection, model, floor, residual = _select(x, dt, evidence, max_lines, grid, fits)
        for attempt in range(MAX_LEVEL_SHIFTS + 1):
            found = _level_shift(residual, dt, model, floor)
            selection = _with_held_out(selection, level_shift_test=found)
            if found is None or not found["significant"]:
                break
            if _at_burst(found, selection):  # an impulsive event, reported as such
                break
            if attempt == MAX_LEVEL_SHIFTS:  # one more than taken out: said, not hidden
                selection = _with_held_out(selection, more_level_shifts=True)
                break
            # Outside the library: taken out of the record, and the selection run again on
            # what is left, so that no effect takes the credit for the step.
            size = found["size"]
            if grid is not None:  # a whole number of grid steps keeps the record on its grid
                size = round(size / grid["step"]) * grid["step"]
            taken_out = size != 0 and math.isfinite(size)  # not under half a grid step
            near = next(
                (
                    sh
                    for sh in shifts
                    if abs(sh["index"] - found["index"]) * dt
                    <= max(sh["size_window_s"], found["size_window_s"])
                ),
                None,
            )
            if near is not None:  # what the first estimate of that step left
                near["size"] += size if taken_out else 0.0
            else:
                shifts.append(
                    {
                        **{
                            k: found[k]
                            for k in ("time_s", "index", "z", "window_s", "size_window_s")
                        },
                        "size": size if taken_out else found["size"],
                        "taken_out": bool(taken_out),
                        # the held-out misfit with the step still in, beside the final one
                        "held_out_z_with_it": selection.held_out.z,
                        "effects_with_it": list(selection.effects),
                    }
                )
            if not taken_out:
                break
            corrected = x - size * (np.arange(x.size) >= found["index"])
            try:
                rerun = _select(corrected, dt, evidence, max_lines, grid, fits)
            except ValueError:  # nothing left but the steps (a record without noise)
                break
            x = corrected
            selection, model, floor, residual = rerun
        if not shifts and "random_walk" in model.names:
            test, swapped = _shift_in_place_of_walk(
                x, dt, evidence, max_lines, grid, model, floor, selection, fits
            )
            if swapped is not None:
                shift, rerun = swapped
                shift["held_out_z_with_it"] = selection.held_out.z
                shift["effects_with_it"] = list(selection.effects)
                selection, model, floor, residual = rerun
                selection = _with_held_out(
                    selection, level_shift_test=_level_shift(residual, dt, model, floor)
                )
                shifts.append(shift)
            selection = _with_held_out(selection, step_or_walk=test, step_or_walk_tested=True)
        rails = detect_saturation(record_values, grid)
        selection = _with_held_out(selection, level_shifts=shifts, saturation=rails)
        if shifts or selection.held_out.more_level_shifts or rails:
            selection = dataclasses.replace(selection, unexplained=True)
        return selection


def _with_held_out(selection: SensorNoiseSelection, **changes) -> SensorNoiseSelection:
    """`selection` with the fields `changes` of its `held_out` replaced."""
    return dataclasses.replace(
        selection, held_out=dataclasses.replace(selection.held_out, **changes)
    )


def _select(
    x: np.ndarray,
    dt: float,
    evidence: float,
    max_lines: int,
    grid: dict | None,
    fits: dict | None = None,
    transient_first: bool = True,
):
    """The forward selection on x, whose output grid is `grid` (`detect_quantization`;
    a step taken out is a whole number of its steps); returns (selection, final model,
    floor, residual). With `transient_first`, a start-up transient that clears the bar is
    added before a noise component that scores higher; should the backward check remove
    it (harness record 128256395, a walk, was named Gauss–Markov after a false one), the
    selection is run again in the order of the evidence alone, and the transient weighed
    in the time domain against the final low-frequency effect (`transient_ties`)."""
    rec = _Record(x, dt, fits)
    if not rec.variance > (1e-10 * float(np.max(np.abs(x)))) ** 2:
        raise ValueError(
            "select_sensor_noise: the record's first differences are constant over its "
            "training part (a pure ramp or a staircase of one step): no noise to model."
        )
    floor = grid["step"] ** 2 / 12 if grid else 1e-9 * rec.variance
    model = _evaluate(rec, floor, (), (), None)
    nominal_dev = _held_out_deviance(rec, floor, model)
    steps = [
        {
            "model": "white",
            "added": None,
            "evidence": 0.0,
            "held_out_gain": 0.0,
            "explained_fraction": 0.0,
            "held_out_z": nominal_dev["z"],
        }
    ]
    train_gram, held_gram = rec.grams((), None)
    log_j = math.log(train_gram.n_bins + held_gram.n_bins)
    promoted = False  # a transient added before a noise component that scored higher
    for _ in range(MAX_STEPS):
        labels, specs, counts = [], [], []
        filtered = spectral.low_pass(model.names) is not None
        for name in spectral.COMPONENTS:
            if name in model.names or (name == "filter_floor" and not filtered):
                continue
            if name == "bandlimit":
                if filtered:
                    continue
                # the second-order low-pass, alone and with the white noise after it (the
                # other orders once the selection is done: `_low_pass_order`)
                for extra in ((), ("filter_floor",)):
                    labels.append(name)
                    names = (*model.names, name, *extra)
                    specs.append((names, model.lines, model.transient, model))
                    counts.append(sum(PARAMETER_COUNT[n] for n in (name, *extra)))
                continue
            labels.append(name)
            specs.append(((*model.names, name), model.lines, model.transient, model))
            counts.append(PARAMETER_COUNT[name])
        if len(model.lines) < max_lines:
            f0, width = _standardised_peak(rec, floor, model)
            r = rec.residual(model.lines, model.transient)
            line = _fit_line(r[: rec.split], rec.t[: rec.split], f0, width)
            labels.append("sinusoid")
            specs.append((model.names, (*model.lines, line), model.transient, model))
            counts.append(PARAMETER_COUNT["sinusoid"])
        tested = None  # the transient test, run beside the fits: (its record, its future)
        if model.transient is None:
            start = rec.residual(model.lines, None)[: rec.split]
            tested = (start, *beside(functools.partial(_transient_test, start, dt, model, floor)))
        trials = list(zip(labels, counts, _evaluate_many(rec, floor, specs), strict=True))
        scored = [(_evidence(m, model, k, log_j), name, m) for name, k, m in trials]
        if tested is not None:
            start, future = tested
            found = future.result()
            transient = found["transient"]
            score = found["evidence"] - PARAMETER_COUNT["startup_transient"] * log_j
            score = score if math.isfinite(score) else -math.inf
            # the noise refit without the transient only when it can be accepted
            refit = None
            if score >= evidence:
                refit = _evaluate(rec, floor, model.names, model.lines, transient, model)
                # Tested again against that refit: the current model's noise took in
                # the transient's power (a white variance inflated by it makes the
                # transient look small beside a slow Gauss–Markov fitted to it).
                found = _transient_test(start, dt, refit, floor)
                transient = found["transient"]
                score = found["evidence"] - PARAMETER_COUNT["startup_transient"] * log_j
                refit = _evaluate(rec, floor, model.names, model.lines, transient, refit)
            scored.append((score, "startup_transient", refit))
        scored.sort(key=lambda s: -s[0])
        # A start-up transient that clears the bar goes in first: a random walk or flicker
        # fitted before it takes its power in the lowest bins and leaves it under the bar
        # (harness record 1079240685: flicker 0.38 mg + an 11 mg, τ 4.5 s warm-up was
        # named a walk alone). The backward check removes it should later noise explain it.
        top = scored[0][1] if scored else None
        if transient_first:
            scored.sort(key=lambda s: not (s[1] == "startup_transient" and s[0] >= evidence))
        accepted = None
        for score, name, m in scored:
            if score < evidence:
                break
            # A start-up transient lies in the training part (τ ≤ a quarter of
            # `TRANSIENT_WINDOW` samples): the held-out part has nothing to check, and
            # the refit of the noise without it moves the held-out likelihood by
            # sampling error alone. Its time-domain test is its evidence.
            if name == "startup_transient" or _held_out_z(m, model) >= -HELD_OUT_Z:
                accepted = (score, name, m)
                break
        if accepted is None:
            break
        score, name, new = accepted
        promoted = promoted or (name == "startup_transient" and top != name)
        dev = _held_out_deviance(rec, floor, new)
        fraction = _explained(dev, nominal_dev)
        steps.append(
            {
                "model": "+".join(["white", *_named(new)]),
                "added": name,
                "evidence": float(score),
                "held_out_gain": float(new.held - model.held),
                "held_out_check_z": (
                    None if name == "startup_transient" else _held_out_z(new, model)
                ),
                "explained_fraction": float(fraction),
                "held_out_z": dev["z"],
            }
        )
        model = new
    model, removed = _backward(rec, floor, model, log_j, evidence)
    if promoted and model.transient is None:
        again, model, floor, r = _select(x, dt, evidence, max_lines, grid, fits, False)
        ties = list(again.held_out.ties)  # (the rerun may have weighed it too)
        ties += [t for t in transient_ties(rec, floor, model, evidence, removed) if t not in ties]
        return _with_held_out(again, ties=ties), model, floor, r
    kept_before = set(_named(model))
    model, exchanged, ties = _exchanges(rec, floor, model, log_j, evidence)
    if exchanged:  # the substitute may leave another effect without evidence
        model, again = _backward(rec, floor, model, log_j, evidence)
        removed += again
    reordered, dropped, shape_ties = _low_pass_order(rec, floor, model, log_j, evidence)
    if reordered is not model:  # a companion that took up the roll-off's misfit may go
        removed += dropped
        model, again = _backward(rec, floor, reordered, log_j, evidence)
        removed += again
    # a white floor gone into a process white over the low band: a decimation filter's
    # response in its place (the first process it replaces is exchanged for `bandlimit`)
    chained, gone, gain, decimation_ties = _collapsed_floor(rec, floor, model, dt, log_j, evidence)
    if gone:
        shape_ties = decimation_ties
        exchanged.append({"effect": gone[0], "by": "bandlimit", "evidence": gain})
        if gain < evidence:  # within the bar of the process it replaces: said
            ties.append(
                {"effect": "bandlimit", "alternative": gone[0], "evidence": gain, "bar": evidence}
            )
        removed += [{"effect": c, "evidence": -gain} for c in gone[1:]]
        model, again = _backward(rec, floor, chained, log_j, evidence)
        removed += again
        ties = [t for t in ties if t["effect"] in _named(model)]  # the processes gone
    ties += transient_ties(rec, floor, model, evidence, removed)
    if removed or exchanged:
        swap = {}  # the effect the forward path added → the one now in its place
        for e in exchanged:
            origin = next((k for k, v in swap.items() if v == e["effect"]), e["effect"])
            swap[origin] = e["by"]
        kept = set(_named(model))
        steps = [
            steps[0],
            *(
                st
                for st in steps[1:]
                if st["added"] in kept_before and swap.get(st["added"], st["added"]) in kept
            ),
        ]
        for st in steps[1:]:
            tokens = [
                swap.get(t, t) for t in st["model"].split("+") if t == "white" or t in kept_before
            ]
            st["model"] = "+".join(t for t in tokens if t == "white" or t in kept)
            if st["added"] in swap:  # its evidence is the replaced effect's
                st["replaced"], st["added"] = st["added"], swap[st["added"]]
        dev = _held_out_deviance(rec, floor, model)
        steps[-1] = {
            **steps[-1],
            "explained_fraction": _explained(dev, nominal_dev),
            "held_out_z": dev["z"],
        }
    final = _held_out_deviance(rec, floor, model)
    effects = [e for e in _named(model) if e != "filter_floor"]  # a part of `bandlimit`'s
    params = _physical(model, dt, floor, rec.split)
    quantization = None
    share = grid["step"] ** 2 / 12 / rec.variance if grid is not None else 0.0
    if grid is not None:
        quantization = {**grid, "noise_share_of_white": float(share)}
        if share >= QUANTIZATION_SHARE:
            effects.append("quantization")
            params["quantization"] = {"step": grid["step"]}
    residual = rec.residual(model.lines, model.transient)
    bursts = _bursts(residual, dt)
    gaussian = _non_gaussian(residual, share)
    change = _spectral_change(residual, dt)
    # The first difference makes a linear drift a constant, which the periodogram never
    # sees: test it in the time domain unless a wandering level was named.
    drift = _drift(residual, dt)
    drifting = drift["t"] > DRIFT_T and not {"random_walk", "flicker"} & set(effects)
    held_out = HeldOutCheck(
        excess_deviance=final["excess_deviance"],
        z=final["z"],
        bins=final["bins"],
        removed=removed,
        exchanged=exchanged,
        ties=ties,
        bursts=bursts,
        non_gaussian=gaussian,
        spectral_change=change,
        drift=drift,
        drifting=bool(drifting),
        white_floor=_white_floor(model, dt),
        low_pass_ties=shape_ties if spectral.low_pass(model.names) else [],
    )
    selection = SensorNoiseSelection(
        effects=tuple(effects),
        unexplained=bool(
            final["z"] > UNEXPLAINED_Z
            or bursts
            or drifting
            or gaussian["significant"]
            or change["significant"]
        ),
        steps=steps,
        parameters=params,
        held_out=held_out,
        quantization=quantization,
        sample_interval=dt,
        n_samples=int(x.size),
    )
    return selection, model, floor, residual


MAX_LEVEL_SHIFTS = 3


def _level_shift(r: np.ndarray, dt: float, model: _Model, floor: float) -> dict | None:
    """The most significant shift of the level in the residual r against the model's own noise: the
    Haar statistic z_w(j) = D_w(j)/√Var D_w, D_w(j) the mean of the w samples after j less
    the mean of the w before, over every j and dyadic w from 4 to n/8, Var D_w from the
    model's variogram (so a random walk or flicker in the model widens it as it should), on
    r less its least-squares line. A step is concentrated in time, where a random walk of
    the same low-frequency power spreads its increments over the record: the periodogram
    cannot tell them apart, this can. Critical |z|: Bonferroni over Σ_w 2n/w nearly
    independent positions at `LEVEL_SHIFT_ALPHA`. Returns the largest |z| (time of the shift
    [s], its size, the window w Δ [s]) with the critical value, or None for a record too
    short (n < 32)."""
    n = r.size
    scales = [1 << k for k in range(2, 40) if 8 << k <= n]
    if not scales:
        return None
    v = _variogram(model, floor, 2 * scales[-1])
    best, raw = _haar_scan(r, v, scales)
    if best is None:
        return None
    # The size at that place from the window whose D has the least variance under the
    # model (the widest the record allows for white noise, shorter where the model
    # wanders): the window that located the step is picked for its |z|, which biases its
    # own D upwards.
    j = best["index"]
    var, w = min((_haar_variance(v, w), w) for w in scales if w <= min(j, n - j))
    # (on r as it is: the line taken out above would bias a step's size)
    size = float(((raw[j + w] - raw[j]) - (raw[j] - raw[j - w])) / w)
    critical = _shift_critical_z(n, scales)
    size_z = size / math.sqrt(var)
    return {
        "z": best["z"],
        "critical_z": float(critical),
        "time_s": j * dt,
        "index": j,
        "size": size,
        # A step holds its size in every window; a spike's D falls as 1/w: the size must
        # stand in its own window too (a shape check, `SHIFT_SIZE_Z`; the false-alarm rate
        # is the located |z|'s). A spike is a burst (`_bursts`), not a shift.
        "size_z": float(size_z),
        "significant": bool(abs(best["z"]) > critical and abs(size_z) > SHIFT_SIZE_Z),
        "window_s": best["window"] * dt,
        "size_window_s": w * dt,
    }


def _at_burst(found: dict, selection) -> bool:
    """Whether a level shift found lies at an impulsive event of `selection` (a shock that
    settles at a new level is reported as the event, not as a step)."""
    margin = found["size_window_s"]
    return any(
        b["start_s"] - margin <= found["time_s"] <= b["end_s"] + margin
        for b in selection.held_out.bursts
    )


def _shift_in_place_of_walk(
    x, dt, evidence, max_lines, grid, model: _Model, floor: float, selection, fits=None
):
    """A random walk named where the record holds a step of its level instead: the two have
    the same 1/f² spectrum, and once the walk is in the model its wander covers the step,
    so the level-shift test against the final model cannot see it. Here the step is sought
    against the model *without* the walk (the rest refitted); one found there is taken out
    and the selection run again on what is left, and the step replaces the walk when the
    whole record's likelihood says so: 2 Δ ln L of (the new selection + the step) over the
    walk's model, less Δk ln J for the noise parameters, at least the shift test's own
    critical z² (the price of searching its place and size) plus `evidence`. A true walk
    keeps its wander after one step is taken out: the new selection names it again and
    gains little. Returns (the test: the step sought, its score and bar, or None where no
    step stands against the reduced model; (shift, the new `_select` result) or None)."""
    rec = _Record(x, dt, fits)
    names = tuple(n for n in model.names if n != "random_walk")
    reduced = _evaluate(rec, floor, names, model.lines, model.transient)
    residual = rec.residual(model.lines, model.transient)
    found = _level_shift(residual, dt, reduced, floor)
    if found is None or not found["significant"] or _at_burst(found, selection):
        return None, None
    size = found["size"]
    if grid is not None:
        size = round(size / grid["step"]) * grid["step"]
    if not (size != 0 and math.isfinite(size)):
        return None, None
    corrected = x - size * (np.arange(x.size) >= found["index"])
    try:
        rerun = _select(corrected, dt, evidence, max_lines, grid, fits)
    except ValueError:
        return None, None
    new = rerun[1]
    gain = 2 * ((new.train + new.held) - (model.train + model.held))
    train, held = rec.grams((), None)
    score = gain - (_parameters(new) + 1 - _parameters(model)) * math.log(
        train.n_bins + held.n_bins
    )
    test = {
        "time_s": found["time_s"],
        "size": size,
        "z_without_the_walk": found["z"],
        "evidence_over_the_walk": float(score),
        "bar": float(found["critical_z"] ** 2 + evidence),
        "effects_with_the_step_out": list(rerun[0].effects),
    }
    # the step in the walk's place: a walk still named once the step is out is a step in
    # a walk, which the level-shift test against the walk's model judges
    if not score >= test["bar"] or "random_walk" in new.names:
        return test, None
    shift = {
        **{k: found[k] for k in ("time_s", "index", "z", "window_s", "size_window_s")},
        "size": size,
        "taken_out": True,
        "in_place_of": "random_walk",
        "evidence_over_the_walk": float(score),
    }
    return test, (shift, rerun)
