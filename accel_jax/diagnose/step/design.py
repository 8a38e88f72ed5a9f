"""The next experiment for a lag tie of the joint step diagnosis.

**Next experiment.** With `cannot_tell`, each experiment of a menu (`experiment_menu`) is
simulated noise-free from the fitted first candidate and refitted by the second (all
records together, the new one added): the expected 2 ln B is the misfit that remains,
Σ r²/σ², and the same the other way round; the smaller of the two is reported.

Float64 throughout (x64 must be enabled).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Mapping

import jax
import jax.numpy as jnp
import numpy as np

from ..._data import NominalDevice, StepData
from ..._deprecated import LegacyItems
from ..._io import field_dict
from ..._runtime import in_background, thread_map, usable_cpus
from ..._servo import closed_loop_test_gain
from ..._simulate.sequence import accel_moment
from .joint import (
    CANDIDATES,
    N_SHARED,
    PreparedSet,
    _record_prediction_compiled,
    _transfer_start,
    compile_fit,
    fit_set,
    nominal_stop_voltage,
    prepare_set,
    stack,
)
from .record import prior_sigma_of
from .state import JointFit, StepRecord


@dataclasses.dataclass(frozen=True, eq=False)
class ExperimentDesign(LegacyItems):
    """An experiment a user can run on the device (`experiment_menu`).

    - `description`: what to record, in words;
    - `record`: the design as a `StepData` (t [s], u_test [V], a_in [g] or None; u_out
        zeros, a placeholder);
    - `noise_V` [V]: the noise per sample assumed for it;
    - `levels_V` [V]: the test voltage of each equal segment;
    - `accel_levels_g` [g]: the input acceleration of each segment (None: no `a_in`).

    It was a plain dict; `design["record"]` still reads for one release, with a
    `DeprecationWarning`.
    """

    description: str
    record: StepData
    noise_V: float
    levels_V: list[float]
    accel_levels_g: list[float] | None

    @classmethod
    def from_mapping(cls, design: Mapping) -> ExperimentDesign:
        """From the plain dict `experiment_menu` returned before (keys as the fields)."""
        return cls(**design)

    def to_dict(self) -> dict:
        return field_dict(self)

    def _legacy(self) -> dict:
        return self.to_dict()


def experiment_menu(
    nominal: NominalDevice, sample_rate: float, noise_V: float
) -> list[ExperimentDesign]:
    """Experiments a user can run on the device, each an `ExperimentDesign`: a record design
    (t, u_test, a_in) at `sample_rate`, 8 ms long, in equal segments (`levels_V`,
    `accel_levels_g`): stop-level test steps (±1.3 × the nominal stop voltage over the test
    gain), a larger small step, an acceleration step of ±1 g, and the small step sampled 4×
    faster."""
    params = nominal.params
    k_test = float(closed_loop_test_gain(params))
    v_stop = nominal_stop_voltage(params)
    u_stop = round(1.3 * v_stop / k_test, 1)
    menu = []

    def design(rate, levels, *, accel=None, description, duration=8e-3):
        n = int(round(duration * rate))
        t = np.arange(n) / rate
        edges = np.linspace(0, n, len(levels) + 1).astype(int)[1:-1]
        index = np.searchsorted(edges, np.arange(n), side="right")
        u = np.asarray(levels, float)[index]
        a = None if accel is None else np.asarray(accel, float)[index]
        return ExperimentDesign(
            description=description,
            record=StepData(t=t, u_test=u, u_out=np.zeros(n), a_in=a),
            noise_V=noise_V,
            levels_V=[float(x) for x in levels],
            accel_levels_g=None if accel is None else [float(x) for x in accel],
        )

    menu.append(
        design(
            sample_rate,
            [0.0, u_stop, -u_stop, u_stop, 0.0],
            description=f"record +{u_stop:g} V and −{u_stop:g} V test steps onto the stops",
        )
    )
    menu.append(
        design(
            sample_rate,
            [0.0, 0.0, 0.0, 0.0, 0.0],
            accel=[0.0, 1.0, -1.0, 1.0, 0.0],
            description="record ±1 g acceleration steps along the input axis (tilt or "
            "centrifuge), test voltage off",
        )
    )
    menu.append(
        design(
            sample_rate,
            [0.0, 2.0, -2.0, 2.0, 0.0],
            description="record another ±2 V small-step sequence",
        )
    )
    menu.append(
        design(
            4 * sample_rate,
            [0.0, 2.0, -2.0, 2.0, 0.0],
            description=f"record the ±2 V steps at {4 * sample_rate / 1e6:g} MHz",
        )
    )
    return menu


def _simulate_design(
    fit: JointFit, prepared: PreparedSet, nominal, candidate, design: ExperimentDesign
) -> StepData:
    """The design's record as the fitted `candidate` predicts it (noise-free): the set's
    shared values, polarity +1, no offset, at rest at the start."""
    record = design.record
    probe = prepare_set([_with_output(record, nominal)], nominal)
    ctx = jax.tree_util.tree_map(lambda leaf: leaf[0], probe.ctx)
    shared = jnp.asarray(fit.x[:N_SHARED])
    own = np.zeros(probe.layout.width)  # the design's changes at its samples' boundaries
    ctx = dataclasses.replace(ctx, polarity=jnp.asarray(1.0), accel_sign=jnp.asarray(1.0))
    n = probe.layout.n_padded
    out = _record_prediction_compiled(
        shared,
        jnp.asarray(own),
        jnp.asarray(CANDIDATES.index(candidate)),
        nominal.params,
        jnp.asarray(prior_sigma_of(nominal)),
        ctx,
        n,
        jnp.asarray(prepared.stop_voltage),
        probe.layout.stops[0],
    )
    m = probe.preps[0].block
    blocks = np.asarray(out)[: probe.preps[0].n]
    y = np.repeat(blocks, m)
    y = np.concatenate([y, np.full(record.t.size - y.size, y[-1])])
    return StepData(t=record.t, u_test=record.u_test, u_out=y, a_in=record.a_in)


def _design_probe(design: ExperimentDesign, nominal) -> StepRecord:
    """A design's record as `prepare_set` prepares it (its padded shapes, `shape`, and
    whether it reaches the stops, `on_stops`), with a placeholder response."""
    return prepare_set([_with_output(design.record, nominal)], nominal).preps[0]


def _with_output(record: StepData, nominal) -> StepData:
    """A design record with a placeholder response (its linear settled levels plus a
    ramp, so that `prepare` finds a non-constant output)."""
    k = float(closed_loop_test_gain(nominal.params))
    y = k * np.asarray(record.u_test) + 1e-6 * np.arange(record.t.size)
    if record.a_in is not None:
        y = y + k * float(accel_moment(nominal.params)) * np.asarray(record.a_in)
    return StepData(t=record.t, u_test=record.u_test, u_out=y, a_in=record.a_in)


def expected_evidence(
    prepared: PreparedSet,
    nominal,
    fits,
    truth: str,
    rival: str,
    design: ExperimentDesign | Mapping,
    at_least: tuple[int, int, int] = (0, 0, 0),
) -> float:
    """Expected 2 ln B of `truth` over `rival` once `design` is added to the set: the fitted
    `truth` simulated noise-free on every record (the set's and the design's), `rival`
    refitted to all of them; its misfit Σ r²/σ² (σ each record's floor; the design's its
    `noise_V` per sample over √(samples per block)). Both models have the same number of
    parameters, so no penalty enters. (`design`: an `ExperimentDesign`, or the dict of its
    fields that `experiment_menu` returned before; `at_least` the set's least padded shapes,
    `joint_set.stack`.)"""
    if not isinstance(design, ExperimentDesign):
        design = ExperimentDesign.from_mapping(design)
    truth_fit = fits[truth]
    new = prepare_set([_simulate_design(truth_fit, prepared, nominal, truth, design)], nominal)
    preps = []
    for r, p in enumerate(prepared.preps):
        u_out = np.zeros_like(p.u_out)
        u_out[: p.n] = truth_fit.prediction[r, : p.n]
        preps.append(dataclasses.replace(p, u_out=u_out))
    added = new.preps[0]
    added = dataclasses.replace(added, sigma=design.noise_V / math.sqrt(added.block))
    combined = stack(preps + [added], prepared.stop_voltage, prepared.layout.lag_states, at_least)
    start = _transfer_start(fits[rival].x, prepared, combined)
    fit = fit_set(combined, nominal, candidates=[rival], starts={rival: start})[rival]
    chi2 = 0.0
    for r, p in enumerate(combined.preps):
        n = p.n
        error = combined.data[r, :n] - fit.prediction[r, :n]
        chi2 += float(np.sum(error**2)) / p.sigma**2
    return chi2


def _menu(prepared: PreparedSet, nominal):
    """The experiment menu for the set, each design's probe (`_design_probe`) and the
    menu's largest shapes (blocks, changes, largest block m): every design's set is padded
    to them, so that one compiled refit serves the designs off the stops and one those on
    them, where each new record length or block (a design at 4× the rate) compiled its own
    (3.6 s each on the 2-core CPU)."""
    rate = 1.0 / prepared.preps[0].dt_sample
    noise = max(p.floor.sigma_per_sample for p in prepared.preps)
    menu = experiment_menu(nominal, rate, noise)
    probes = [_design_probe(design, nominal) for design in menu]
    shapes = [(p.shape.n_padded, p.shape.j_padded, p.shape.max_block) for p in probes]
    at_least = tuple(max(column) for column in zip(*shapes, strict=True))
    return menu, probes, at_least


def compile_refits(prepared: PreparedSet, nominal) -> list:
    """Where the process has two CPUs or more, the designs' refit programs (one on the
    stops, one off them) compiled on threads of their own (`joint.compile_fit` on each
    design's set with its placeholder output, shaped as `next_experiments` will shape it),
    and the designs' simulations on a third (one per record shape), while the caller fits
    the set itself; their `Future`s, which `next_experiments` waits for. The same programs,
    compiled earlier: the same results."""
    if len(usable_cpus()) < 2:
        return []
    menu, probes, at_least = _menu(prepared, nominal)
    lag_states = prepared.layout.lag_states
    futures = []
    for on_stops in sorted({p.on_stops for p in probes}):
        probe = next(p for p in probes if p.on_stops == on_stops)
        combined = stack(prepared.preps + [probe], prepared.stop_voltage, lag_states, at_least)
        futures += in_background(_quietly(functools.partial(compile_fit, combined, nominal)))
    shapes = {}  # a design of each simulation program (its record's shapes, on the stops)
    for design, p in zip(menu, probes, strict=True):
        shapes.setdefault((p.shape, p.on_stops), design)
    # (a fit's shared values are all a simulation reads of it)
    placeholder = JointFit(np.zeros(N_SHARED), 0.0, np.zeros((0, 0)), np.zeros(0), False, [])
    simulations = [
        _quietly(
            functools.partial(_simulate_design, placeholder, prepared, nominal, "nominal", d)
        )
        for d in shapes.values()
    ]
    return futures + in_background(*simulations)


def _quietly(call):
    """`call`, its error dropped: a program compiled ahead that fails changes nothing (the
    real call raises the same error where it happens)."""

    def run():
        try:
            call()
        except Exception:
            pass

    return run


def next_experiments(prepared: PreparedSet, nominal, fits, tied, ahead=()) -> list[dict]:
    """The menu's experiments ranked by the expected 2 ln B that separates the tied pair
    (the smaller of the two directions); `ahead` the futures of `compile_refits`."""
    menu, probes, at_least = _menu(prepared, nominal)
    for future in ahead:
        future.result()
    calls = [(design, pair) for design in menu for pair in (tied, tied[::-1])]

    def evidence(call):
        design, (truth, rival) = call
        return expected_evidence(prepared, nominal, fits, truth, rival, design, at_least)

    # The refits on as many threads as there are CPUs (`thread_map`; each is one XLA call,
    # the same calls and results in any order). With the programs compiled ahead
    # (`ahead`), all at once, the refits on the stops (the slow ones: their sample-by-sample
    # simulation) first; else first one call of each program (on the stops and off them),
    # compiled side by side, then the rest, which find them compiled (two threads asking
    # for one program not yet compiled would both compile it).
    on_stops = {id(d): p.on_stops for d, p in zip(menu, probes, strict=True)}
    if ahead:
        batches = [sorted(range(len(calls)), key=lambda i: not on_stops[id(calls[i][0])])]
    else:
        first = {}
        for i, (design, _) in enumerate(calls):
            first.setdefault(on_stops[id(design)], i)
        order = sorted(first.values())
        batches = [order, [i for i in range(len(calls)) if i not in order]]
    values = {}
    for batch in batches:
        values.update(zip(batch, thread_map(evidence, [calls[i] for i in batch]), strict=True))
    out = []
    for k, design in enumerate(menu):
        one, two = values[2 * k], values[2 * k + 1]
        record = design.record
        out.append(
            {
                "description": design.description,
                "expected_2lnB": float(min(one, two)),
                f"expected_2lnB_if_{tied[0]}": float(one),
                f"expected_2lnB_if_{tied[1]}": float(two),
                "levels_V": design.levels_V,
                "accel_levels_g": design.accel_levels_g,
                "sample_rate_Hz": float(1 / record.sample_period),
                "duration_s": float(record.t[-1] + record.sample_period),
            }
        )
    out.sort(key=lambda e: -e["expected_2lnB"])
    return out
