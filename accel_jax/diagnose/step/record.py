"""The step diagnosis's view of a record (host side, NumPy): `prepare` reads a record into
a `StepRecord` (`state`) — its test sequence, the blocks it is fitted in, the noise floor
measured without a model, the domain check (`domain`), the held-out segments (`segments`)
and the starting points of the fits.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from ..._data import DataError, NominalDevice, StepData, check_input_delay
from ..._servo import closed_loop_test_gain, damping_ratio, time_constant
from ..._simulate.sequence import accel_moment
from .. import openworld
from .domain import check_domain
from .inputs import UNCLOCKED_CHANGES, clock_grid, level_groups, read_inputs
from .model import (
    DELAY_LATE_SIGMA,
    DELAY_LIMIT,
    DELAY_PRIOR_SIGMA,
    GAIN_SIGMA,
    KNOWN_DELAY_SIGMA,
    REFIT_BOUND,
    REFIT_FIELDS,
    TIMING_LIMIT,
    TIMING_PRIOR,
    StepContext,
)
from .layout import W
from .segments import held_out_samples, segments, sequence_key, time_text
from .state import (
    LevelGroups,
    NoiseFloor,
    RecordHost,
    RecordShape,
    RecordView,
    StepRecord,
)

MAX_CHANGES = UNCLOCKED_CHANGES
"""Most test-voltage changes a record may have with a change time (and, measured, a level)
fitted for each."""

MAX_CLOCKED_CHANGES = 1024
"""Most changes of a sequence on one bit clock (a PRBS or random telegraph, `clock_grid`):
fitted with the clock's shift and rate and one error per distinct level instead."""


def _changes(data: StepData, path=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sample indices where an input changes, ΔU_test there [V] and Δa_in [g] (zeros
    without an `a_in` column)."""
    u = np.asarray(data.u_test)
    a = np.zeros_like(u) if data.a_in is None else np.asarray(data.a_in)
    index = np.flatnonzero(np.diff(sequence_key(data)) != 0) + 1
    limit = MAX_CLOCKED_CHANGES if data.a_in is None else MAX_CHANGES
    if index.size > limit:
        what = "u_test" if data.a_in is None else "u_test or a_in"
        raise DataError(
            f"{path or '<data>'}: {what} changes at {index.size} samples; the step diagnosis "
            f"takes at most {limit} changes in one record (split it into shorter records)."
        )
    return index, u[index] - u[index - 1], a[index] - a[index - 1]


BLOCK_BUCKET = 256
"""Block counts are padded to a multiple of this (one compiled program per bucket)."""

MIN_MAX_BLOCK = 32
"""The compiled programs allow blocks of up to this many samples (more when a record needs
them): records sampled at 100 kHz and at 2 MHz then share one program."""

BLOCKS_PER_PERIOD = 30
"""Samples are averaged in blocks of about T/30 (T the nominal loop's time constant; at
most 10 µs for the reference device): a record sampled at 1 MHz is fitted as the exact
means of blocks of 10 samples. White noise averages down by √m with the signal kept, and
the model predicts the block means exactly (`_simulate.sequence.linear_record`), so little is lost
while the fit handles ~30 points per T however fast the record was sampled."""

COARSE_BIAS = 0.1
"""An output not dithered by its own noise (σ of its differences below half the ADC step)
whose plateaus keep a quantisation bias (`quantisation_bias`) above this fraction of the
record's noise floor σ has its levels fitted as errors in variables (σ that bias), as a
measured input's are: a plateau's mean, averaged over its ~10² blocks, resolves a bias of
about a tenth of σ, which a white output noise does not describe."""


def stack_on_host(trees: list):
    """Trees of the same structure stacked leaf by leaf along a new first axis: with NumPy
    on the host, each leaf then moved to the device once (an eager `jnp.stack` compiles a
    program per leaf shape, time a cold single-record diagnosis pays)."""
    return jax.tree_util.tree_map(
        lambda *xs: jnp.asarray(np.stack([np.asarray(x) for x in xs])), *trees
    )


def _clocked(inputs):
    """(the record as fitted, its `Clock` or None, its `LevelGroups` or None).

    A sequence of more than `MAX_CHANGES` changes must run on one bit clock
    (`inputs.clock_grid`; else `DataError`); measured, its plateaus are then replaced
    by their level groups' means (`inputs.level_groups`), the groups returned beside it."""
    data = inputs.data
    index = np.flatnonzero(np.diff(sequence_key(data)) != 0) + 1
    if index.size <= MAX_CHANGES:
        return data, None, None
    if data.a_in is not None:
        raise DataError(
            f"u_test and a_in change {index.size} times together; the step diagnosis takes "
            f"at most {MAX_CHANGES} changes in a record with an acceleration column (more "
            "only from a clocked u_test alone). Split the record into shorter ones."
        )
    clock = clock_grid(index)
    if clock is None:
        raise DataError(
            f"u_test changes {index.size} times, not on one bit clock (the intervals between "
            f"changes are not whole multiples of one bit within {CLOCK_TEXT}); the step "
            f"diagnosis takes more than {MAX_CHANGES} changes only from a clocked sequence "
            "(a PRBS or random telegraph). Split the record into shorter ones."
        )
    if inputs.level_sigmas is None:
        return data, clock, None
    u = np.asarray(data.u_test)
    levels = u[np.concatenate([[0], index])]
    grouped = LevelGroups(*level_groups(levels, inputs.level_sigmas))
    if np.any(grouped.group[1:] == grouped.group[:-1]):
        raise DataError(
            "u_test: two neighbouring plateaus of the measured clocked sequence read as one "
            "level; the step diagnosis cannot tell its changes apart. Split the record."
        )
    plateau = np.searchsorted(index, np.arange(u.size), side="right")
    rebuilt = StepData(
        t=data.t,
        u_test=grouped.means[grouped.group][plateau],
        u_out=data.u_out,
        notes=tuple(data.notes),
        input_delay=data.input_delay,
    )
    return rebuilt, clock, grouped


CLOCK_TEXT = "1.5 samples"


def _response_fit(t, u, y, base) -> tuple[float, float]:
    """(intercept, slope) of the output against the nominal loop's unit-gain response to
    the test voltage (SciPy's `lsim` of ω²/(s² + 2ζωs + ω²), from rest under the first
    level): the polarity, gain and offset starts of a sequence whose plateaus never settle."""
    from scipy import signal

    omega = 1 / float(time_constant(base))
    zeta = float(damping_ratio(base))
    system = signal.lti([omega**2], [1.0, 2 * zeta * omega, omega**2])
    _, response, _ = signal.lsim(system, u - u[0], t - t[0])
    columns = np.stack([np.ones_like(y), u[0] + response], 1)
    intercept, slope = np.linalg.lstsq(columns, y, rcond=None)[0]
    return float(intercept), float(slope)


def _coarse_note(quantum: float, bias: float, sigma: float) -> str:
    """The note of a record whose plateaus keep a quantisation bias (`COARSE_BIAS`)."""
    return (
        f"the output's ADC step ({quantum:.3g} V) is coarse against its noise: each plateau "
        f"keeps a quantisation bias (RMS {bias:.2g} V, {bias / sigma:.2g}× the noise floor), "
        "so the test levels are fitted as errors in variables with that σ (the input_level "
        "nuisances)"
    )


def _clock_notes(clock, grouped: LevelGroups | None, changes: int) -> list[str]:
    if clock is None:
        return []
    text = (
        f"u_test: {changes} changes on one bit clock (a bit {clock.period:.4g} samples; every "
        f"change within {np.max(np.abs(clock.residual)):.2g} samples of the grid): the change "
        "times fitted as the clock's shift and rate, not one by one"
    )
    if grouped is not None:
        levels = ", ".join(f"{v:.4g}" for v in grouped.means)
        text += (
            f"; the measured levels as {grouped.means.size} distinct levels ({levels} V), "
            "each fitted once"
        )
    return [text]


def _clock_layout(clock, index, j_padded):
    """The timing map (J, 2) and offsets (J,) [samples] of a clocked sequence: change j's
    shift from its index is (grid − index) + p₀ + p₁ (b_j − b̄)/(half the span of b), p₀ the
    common shift (the sampling's half sample and the channels' delay), p₁ the clock's rate
    error in samples at the ends; pads zero."""
    bits = clock.bits
    centre, half = bits.mean(), max(float(np.ptp(bits)) / 2, 1.0)
    timing_map = np.zeros((j_padded, 2))
    timing_map[: index.size, 0] = 1.0
    timing_map[: index.size, 1] = (bits - centre) / half
    offset = np.zeros(j_padded)
    offset[: index.size] = clock.phase + clock.period * bits - index
    return timing_map, offset


def prepare(data: StepData, nominal: NominalDevice, effects) -> StepRecord:
    """Host-side context of one record: blocks, floor, domain check, polarity, starts.

    A measured input (noise, ADC steps, relay spikes: `inputs.read_inputs`) is read
    as its plateaus first; `StepRecord.data` is the record as fitted, `.notes` says what
    was read, and the levels' standard error (times the test gain) joins the floor.

    **Arguments:**

    - `data`: a validated step record.
    - `nominal`: the nominal device and its prior.
    - `effects`: the candidate effects whose starts are prepared (`guesses_linear` holds
        the nominal's and the linear effects', `guesses_nonlinear` the stop effects').

    **Returns:** a `StepRecord`."""
    inputs = read_inputs(data, max_changes=MAX_CLOCKED_CHANGES)
    data, clock, grouped = _clocked(inputs)
    t, u, y = np.asarray(data.t), np.asarray(data.u_test), np.asarray(data.u_out)
    n = y.size
    dt = data.sample_period
    base = nominal.params
    period = float(time_constant(base))
    if np.ptp(y) == 0:
        raise DataError(
            f"step record: u_out is constant ({y[0]:.6g} V) over the whole record; no "
            "response to diagnose (a disconnected or saturated channel?)."
        )
    index, steps, accel_steps = _changes(data)
    a = None if data.a_in is None else np.asarray(data.a_in)
    key = sequence_key(data)
    near_change = np.zeros(n, dtype=bool)
    for i in index:
        near_change[max(i - 2, 0) : i + 3] = True
    full_floor = openworld.noise_floor(y, exclude=near_change)
    m = max(1, int(round(period / BLOCKS_PER_PERIOD / dt)))
    n_blocks = n // m
    if n_blocks < 50:
        raise DataError(
            f"the record holds {n} samples of {time_text(dt)}: {n_blocks} blocks of {m} "
            "(the fit's resolution, T/30 of the nominal device); at least 50 are needed."
        )
    yb = y[: n_blocks * m].reshape(n_blocks, m).mean(axis=1)
    view = RecordView(t[: n_blocks * m : m], u[: n_blocks * m : m], yb)
    near_block = np.zeros(n_blocks, dtype=bool)
    for i in index // m:
        near_block[max(i - 1, 0) : i + 2] = True
    block_floor = openworld.noise_floor(yb, exclude=near_block, order=4)
    q = full_floor.quantum
    dithered = full_floor.sigma_differences >= 0.5 * q
    quantised = q / math.sqrt(12) / (math.sqrt(m) if dithered else 1.0)
    # A measured input's levels are known to their standard error only: each plateau's
    # output level is then uncertain by the test gain times it (added in quadrature).
    plateau_sigmas = inputs.level_sigmas
    if grouped is not None:  # each plateau known to its level group's standard error
        plateau_sigmas = grouped.sigmas[grouped.group]
    rms_sigma = 0.0 if plateau_sigmas is None else float(np.sqrt(np.mean(plateau_sigmas**2)))
    input_floor = abs(float(closed_loop_test_gain(base))) * rms_sigma
    sigma = max(
        math.hypot(block_floor.sigma_differences, input_floor),
        quantised,
        1e-12 * max(float(np.max(np.abs(y))), 1.0),
    )
    floor = NoiseFloor(
        sigma=sigma,
        sigma_per_sample=full_floor.sigma,
        sigma_block_means=block_floor.sigma_differences,
        adc_step=q,
        quantisation_floor_block=quantised,
        block_samples=m,
        input_levels=input_floor,
    )
    problems, domain = check_domain(data, nominal, full_floor.sigma)
    held_samples, held_rule = held_out_samples(key)
    # A block is held out when any of its samples is.
    held = np.asarray(held_samples[: n_blocks * m].reshape(n_blocks, m).any(axis=1))
    edges = segments(key)
    # Settled levels (last quarter of each segment) against the test voltage (and the
    # acceleration): polarity, gain and offset starts.
    levels, accels, outputs = [], [], []
    for start, stop in zip(edges[:-1], edges[1:], strict=True):
        tail = y[stop - max((stop - start) // 4, 1) : stop]
        levels.append(u[start])
        accels.append(0.0 if a is None else a[start])
        outputs.append(float(np.mean(tail)))
    levels, accels, outputs = np.asarray(levels), np.asarray(accels), np.asarray(outputs)
    columns = [np.ones_like(levels)]
    if np.ptp(levels) > 0:
        columns.append(levels)
    if np.ptp(accels) > 0:
        columns.append(accels)
    coef = np.linalg.lstsq(np.stack(columns, 1), outputs, rcond=None)[0]
    intercept = float(coef[0])
    slope = float(coef[1]) if np.ptp(levels) > 0 else 1.0
    if clock is not None:  # bits shorter than the response: no settled levels to read
        intercept, slope = _response_fit(t, u, y, base)
    accel_slope = float(coef[-1]) if np.ptp(accels) > 0 else 1.0
    polarity = -1.0 if slope < 0 else 1.0
    accel_sign = -1.0 if accel_slope < 0 else 1.0
    k_test = float(closed_loop_test_gain(base))
    z_gain = np.log(max(abs(slope), 1e-12) / k_test) / GAIN_SIGMA
    w_gain = float(np.clip(z_gain, -REFIT_BOUND, REFIT_BOUND))
    train_y = yb[~held]
    scale = max(float(np.ptp(train_y)) / 2, 10 * sigma)
    first_accel = 0.0 if a is None else float(a[0])
    # The moment at the first sample: the external moment and the first acceleration level
    # (each later acceleration step is a source of its own).
    moment = (intercept + (0.0 if a is None else accel_slope * first_accel)) / k_test
    first_output = intercept + slope * u[0] + (0.0 if a is None else accel_slope * first_accel)
    dv = (y[0] - first_output) / k_test
    # Padded shapes (blocks to a multiple of BLOCK_BUCKET, changes to a multiple of 4, m to
    # a power of two): records of similar length share one compiled program whatever their
    # sample rate. Padding carries zero weight.
    n_padded = -(-n_blocks // BLOCK_BUCKET) * BLOCK_BUCKET
    j_padded = max(4, -(-index.size // 4) * 4)
    max_block = max(MIN_MAX_BLOCK, 2 ** math.ceil(math.log2(m)))
    change_index = np.zeros(j_padded, dtype=np.int32)
    change_step = np.zeros(j_padded)
    change_index[: index.size] = index
    change_step[: index.size] = steps
    change_accel = np.zeros(j_padded)
    change_accel[: index.size] = accel_steps
    # The changes that start a held-out segment: their times are refitted on it.
    starts_held = np.zeros(j_padded, dtype=bool)
    starts_held[: index.size] = held_samples[index]
    held_out_change = (starts_held & ((change_step != 0) | (change_accel != 0))).astype(np.float64)
    # A measured test input: each change's level known to its standard error (errors in
    # variables, `fit.unpack`); not with an acceleration column, whose changes share
    # the test levels' segments.
    level_sigma = held_out_level = drift_step = level_map = None
    # The output's plateaus seen through its ADC keep a bias the record's noise does not
    # average out (`quantisation_bias`): as the fit sees it, each level is known only to
    # that bias, referred to the input, beside its own standard error. Not for a clocked
    # sequence, whose bits are shorter than the response: its output never sits on one
    # place of the grid (`level_bias` 0).
    settled = np.zeros(n, dtype=bool)  # (the last half of each constant-input segment)
    for start, stop in zip(edges[:-1], edges[1:], strict=True):
        settled[(start + stop) // 2 : stop] = True
    level_bias = 0.0
    if clock is None:
        level_bias = quantisation_bias(y, q, settled) / max(abs(k_test), 1e-300)
    # An output quantised coarsely against its noise (not dithered, `quantisation_bias`
    # far from 0) gives each plateau a bias of its own, which a white output noise does
    # not describe: its levels are then errors in variables too, with an exact input.
    # (Not with an acceleration column, whose changes share the test levels' segments.)
    coarse = not dithered and level_bias * abs(k_test) > COARSE_BIAS * sigma and a is None
    if (rms_sigma > 0 or coarse) and a is None:
        # (rms_sigma > 0: a measured input, which has level errors and a drift shape)
        level_sigma = np.zeros(j_padded)
        drift_step = np.zeros(j_padded)
        if rms_sigma > 0:
            assert plateau_sigmas is not None and inputs.level_drift is not None
            level_sigma[: index.size] = np.hypot(plateau_sigmas[1:], level_bias)
            drift_step[: index.size] = np.diff(inputs.level_drift)
        else:
            level_sigma[: index.size] = level_bias
        held_out_level = np.append(starts_held.astype(np.float64), 0.0)  # (the drift: not)
        if grouped is not None:  # one error per distinct level, shared by train and test
            group, group_sigma = grouped.group, np.hypot(grouped.sigmas, level_bias)
            level_map = np.zeros((j_padded + 1, group_sigma.size))
            level_map[np.arange(group.size), group] = group_sigma[group]
            held_out_level = np.zeros(group_sigma.size + 1)
    # The level errors (one per change, or per level group) and the input channel's drift
    # nuisance.
    n_levels = 0 if held_out_level is None else held_out_level.size  # (set with level_sigma)
    # The change times: one shift per change, or a clock's shift and rate (`_clock_layout`).
    # A known delay of the input channels (`StepData.input_delay`): every change's shift
    # from its column is centred that much earlier, and a measured input's common delay is
    # then fitted about it within the sampling phase (`KNOWN_DELAY_SIGMA`).
    known = check_input_delay(data.input_delay, float(t[-1] - t[0]))
    known_samples = None if known is None else known / dt
    early = np.zeros(j_padded)
    early[: index.size] = 0.0 if known_samples is None else known_samples
    timing_map = timing_offset = timing_mean = timing_sigma = timing_limit = None
    timing_sigma_late = None
    timing_late = np.full(j_padded, TIMING_PRIOR[0])
    measured = level_sigma is not None
    delay = (DELAY_PRIOR_SIGMA, DELAY_LIMIT) if measured else (TIMING_PRIOR[1], TIMING_LIMIT)
    if measured and known is not None:
        delay = (KNOWN_DELAY_SIGMA, DELAY_LIMIT)
    if clock is not None:
        timing_map, timing_offset = _clock_layout(clock, index, j_padded)
        timing_offset = timing_offset - early
        timing_mean = np.array([TIMING_PRIOR[0], 0.0])
        timing_sigma = np.array([delay[0], TIMING_PRIOR[1]])
        timing_limit = np.array([delay[1], TIMING_LIMIT])
        if measured:  # the channel's delay: the changes later by about the phase at most
            timing_sigma_late = np.array([DELAY_LATE_SIGMA, TIMING_PRIOR[1]])
        timing_late = timing_mean.copy()
        held_out_change = np.zeros(2)
    elif measured:  # one shift per change and the input channel's delay, common to all
        timing_map = np.concatenate([np.eye(j_padded), np.ones((j_padded, 1))], axis=1)
        timing_map[index.size :] = 0.0
        timing_offset = -early
        timing_mean = np.append(np.full(j_padded, TIMING_PRIOR[0]), 0.0)
        timing_sigma = np.append(np.full(j_padded, TIMING_PRIOR[1]), delay[0])
        timing_limit = np.append(np.full(j_padded, TIMING_LIMIT), delay[1])
        timing_sigma_late = np.append(np.full(j_padded, TIMING_PRIOR[1]), DELAY_LATE_SIGMA)
        timing_late = timing_mean.copy()
        held_out_change = np.append(held_out_change, 0.0)
    elif known is not None:  # one shift per change, about the known delay
        timing_map = np.eye(j_padded)
        timing_map[index.size :] = 0.0
        timing_offset = -early
        timing_mean = np.full(j_padded, TIMING_PRIOR[0])
        timing_sigma = np.full(j_padded, TIMING_PRIOR[1])
        timing_limit = np.full(j_padded, TIMING_LIMIT)
        timing_late = timing_mean.copy()
    train = np.zeros(n_padded)
    test = np.zeros(n_padded)
    train[:n_blocks] = ~held
    test[:n_blocks] = held
    ctx = StepContext(
        dt=jnp.asarray(dt),
        duration=jnp.asarray(dt * (n_blocks * m - 1)),
        first_level=jnp.asarray(float(u[0])),
        polarity=jnp.asarray(polarity),
        sigma_ref=jnp.asarray(sigma),
        scale=jnp.asarray(scale),
        lag_unit=jnp.asarray(0.03 * period),
        mid=jnp.asarray(float(train_y.max() + train_y.min()) / 2),
        half=jnp.asarray(max(float(np.ptp(train_y)) / 2, 1e-12)),
        change_index=jnp.asarray(change_index),
        change_step=jnp.asarray(change_step),
        held_out_change=jnp.asarray(held_out_change),
        train=jnp.asarray(train),
        test=jnp.asarray(test),
        block=jnp.asarray(m, dtype=jnp.int32),
        max_block=max_block,
        change_accel=jnp.asarray(change_accel),
        accel_sign=jnp.asarray(accel_sign),
        level_sigma=None if level_sigma is None else jnp.asarray(level_sigma),
        held_out_level=None if held_out_level is None else jnp.asarray(held_out_level),
        drift_step=None if drift_step is None else jnp.asarray(drift_step),
        timing_map=None if timing_map is None else jnp.asarray(timing_map),
        timing_offset=None if timing_offset is None else jnp.asarray(timing_offset),
        timing_mean=None if timing_mean is None else jnp.asarray(timing_mean),
        timing_sigma=None if timing_sigma is None else jnp.asarray(timing_sigma),
        timing_limit=None if timing_limit is None else jnp.asarray(timing_limit),
        timing_sigma_late=None if timing_sigma_late is None else jnp.asarray(timing_sigma_late),
        level_map=None if level_map is None else jnp.asarray(level_map),
    )
    common = np.zeros(W.FIXED + timing_late.size + n_levels)
    common[W.MOMENT] = moment / scale
    common[W.GAIN] = w_gain
    common[W.DV] = dv / scale
    host = RecordHost(
        lag_unit=0.03 * period,
        gain=float(base.pickoff_gain * base.amplifier_gain),
        mid=float(ctx.mid),
        half=float(ctx.half),
        scale=scale,
        dt=dt * m,
        duration=dt * (n_blocks * m - 1),
        torquer_gain=float(base.torquer_gain),
        accel_per_g=float(accel_moment(base)),
        timing_late=timing_late,
        nominal_torquer_time_constant=float(base.torquer_time_constant),
        nominal_filter_time_constant=float(base.filter_time_constant),
        top=float(np.max(yb)),
        bottom=float(np.min(yb)),
        block_samples=int(m),
        k_test=float(closed_loop_test_gain(base)),
    )
    coarse_notes = ()
    if coarse and rms_sigma == 0:
        coarse_notes = (_coarse_note(q, level_bias * abs(k_test), sigma),)
    linear = [e for e in effects if not e.nonlinear and not e.loop_noise]
    nonlinear = [e for e in effects if e.nonlinear]
    return StepRecord(
        data=data,
        notes=tuple(inputs.notes) + tuple(_clock_notes(clock, grouped, index.size)) + coarse_notes,
        ctx=ctx,
        view=view,
        u_out=np.concatenate([yb, np.zeros(n_padded - n_blocks)]),
        n=n_blocks,
        block=m,
        dt=dt * m,
        dt_sample=dt,
        held=held,
        held_rule=held_rule,
        floor=floor,
        sigma=sigma,
        domain_problems=tuple(problems),
        domain=domain,
        polarity=polarity,
        k_test=k_test,
        levels_slope=float(slope),
        levels_intercept=float(intercept),
        change_index=index,
        change_block=index // m,
        change_step=steps,
        change_accel=accel_steps,
        accel_sign=accel_sign,
        accel_slope=accel_slope,
        has_accel=a is not None,
        period=period,
        shape=RecordShape(
            n_padded=n_padded,
            j_padded=j_padded,
            max_block=max_block,
            measured=level_sigma is not None,
            clocked=clock is not None,
            n_levels=n_levels,
            mapped_timing=timing_map is not None,
        ),
        clock=clock,
        level_groups=grouped,
        guesses_linear=_guesses(common, linear, host, nominal_first=True),
        guesses_nonlinear=_guesses(common, nonlinear, host, nominal_first=False),
        host=host,
        prior_sigma=prior_sigma_of(nominal),
        input_delay_known=known_samples,
        input_measured=rms_sigma > 0,
    )


STARTS = 2
"""Starting points per candidate (the nominal: change times at the samples, and half a
sample earlier — a sampled u_test column shows a change up to a sample late)."""


def _guesses(common, effects, host: RecordHost, *, nominal_first: bool) -> np.ndarray:
    """Starts, shape (candidates, STARTS, parameters): an effect's own starts, then the
    nominal's second start (changes half a sample earlier) with its last start."""
    late = common.copy()
    timing = host.timing_late
    late[W.timing(timing.size)] = timing
    rows = [[common, late]] if nominal_first else []
    for effect in effects:
        per = []
        starts = effect.record_starts(host)
        for k in range(STARTS):
            w = (common if k < len(starts) else late).copy()
            start = starts[min(k, len(starts) - 1)]
            w[W.effect(len(start))] = start
            per.append(w)
        rows.append(per)
    return np.asarray(rows)


def prior_sigma_of(nominal: NominalDevice) -> np.ndarray:
    return np.array([nominal.uncertainty.get(f, 0.0) for f in REFIT_FIELDS])


def quantisation_bias(y: np.ndarray, quantum: float, settled: np.ndarray) -> float:
    """RMS [V], over an unknown place on the grid, of the bias that a quantised output `y`'s
    mean over a plateau keeps, whatever its length: the mean of Q(x + noise) departs from x
    by a periodic function of x's place on the grid, the sum over k ≥ 1 of harmonics of
    amplitude (q/πk)·exp(−2π²k²σₐ²/q²) (Widrow and Kollár, *Quantization Noise*, 2008: the
    noise's characteristic function at k/q), σₐ the noise before the ADC; with none, the
    sawtooth of RMS q/√12. σₐ² is taken as half the mean square of `y`'s first
    differences where the output has settled (`settled`, both samples; differences beyond
    max(6 robust σ, 3q) left out) less q²/12, the ADC's own variance: a robust spread of
    the differences over-counts it on a coarse grid (harness record 91: 0.00074 V by their
    MAD, 0.00031 V so, 0.00030 V drawn). 0 for an unquantised output (q = 0)."""
    if not quantum > 0:
        return 0.0
    settled = np.asarray(settled, dtype=bool)
    d = np.diff(np.asarray(y, dtype=np.float64))[settled[1:] & settled[:-1]]
    analog2 = 0.0
    if d.size >= 2:
        spread = 1.4826 * float(np.median(np.abs(d)))
        d = d[np.abs(d) <= max(6.0 * spread, 3.0 * quantum)]
        analog2 = max(0.5 * float(np.mean(d**2)) - quantum**2 / 12.0, 0.0)
    k = np.arange(1, 65, dtype=np.float64)
    power = (quantum / (math.pi * k)) ** 2 * np.exp(-4.0 * math.pi**2 * k**2 * analog2 / quantum**2)
    return math.sqrt(0.5 * float(np.sum(power)))
