"""Records of a piecewise-constant test-voltage sequence (the step diagnosis's model of a
record): the closed loop under a test voltage whose changes fall anywhere between samples,
from any initial state, with the test winding of unknown polarity and gain, an external
moment that may drift, and optional mechanical stops.

**State** (6, every entry in volts so that all are O(1)): the deflection as the amplifier
voltage v = k_dp k_y l θ; the velocity w = k_dp k_y l T θ' (T the loop's time constant);
the torquer moment m = M_dm/k_dm; the output filter's state U_f; the external moment
M̃ = M/k_dm; and its change over the record, r = Ṁ·t_rec/k_dm (M̃' = r/t_rec, r' = 0, so a
drifting moment is part of the state, not an input). The loop's matrices are
`accel_jax._simulate.state_space`'s, rescaled; the output is U_out = C x.

**Linear record** (`linear_record`): exact superposition. With the test-voltage changes
ΔU_j at times τ_j = t_{i_j} + δ_j Δ (δ_j real, in samples: a change between samples, e.g.
from a DAC on another clock or a sampled u_test column) and the input g·U_test (g the test
winding's signed gain),

    U_out(t) = C x_eq + C e^{A t} (x_0 − x_eq) + g Σ_j ΔU_j S(t − τ_j)·[t > τ_j],

S(s) = C ∫_0^s e^{Aσ} dσ B the unit step response. On the affine state z = [x; u] every
change is a source, z(t) = e^{[[A, B], [0, 0]](t − τ_j)} [0; gΔU_j]; the record is the sum
of the sources carried from block to block by M^m (M the one-sample map), read out
either at the samples (m = 1) or as exact means over blocks of m samples. The matrix
exponentials are `expm_minus_identity`'s (e^X − I, exact for the small X of a sample step
and for stiff lags). The tests check it against `simulate_linear` on a grid 50 times
finer and against the SciPy truth simulator of `studies/step_truth.py`, to 1e-10 V.

**Record with stops** (`stop_record`): the same loop, stepped sample by sample
(`lax.scan`), with inelastic stops at v = v_hi and v = v_lo (asymmetric in general: an
external moment, or an output offset, shifts the deflection between them). A pendulum that
reaches a stop within a sample step loses its velocity at the contact time (found by
interpolation within the step) and moves on from the stop for the rest of the step (a
fourth-order Taylor expansion of the flow, exact to ‖AΔ‖⁵/120); one pushed into a stop
stays there, and leaves it at the exact (sub-sample) time of the test-voltage change that
reverses the push. With lags (T_dm, T_f > 0) the pendulum may stay on the stop after a
change until the lagged torquer moment pulls it off: on the stop the lag states follow the
clamped flow, and the release is found within the sample step where the pressing moment
crosses zero (regula falsi, `RELEASE_ITERATIONS`). Checked against the SciPy event
simulator of `studies/step_truth.py` (stop-level steps with T_dm, T_f of 10–30 µs at 1 MHz:
within 11 µV of a 4 V stop level; exact to 1e-13 V with ideal lags).

Float64 throughout (the fitted change times are ~1e-7 s against records of ~1e-2 s, and
the evidence compares log-likelihoods of ~1e4 to within ~1).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from .._params import ServoParams
from .._servo import loop_stiffness, time_constant
from .._static import STANDARD_GRAVITY
from .matrix import expm_minus_identity, power_rows, zoh
from .state_space import state_space

N_STATES = 6
"""v, w, m, U_f, M̃, r (see the module docstring)."""

TAYLOR_ORDER = 4
"""Order of the flow's Taylor expansion after a stop contact within a sample step."""

RELEASE_ITERATIONS = 3
"""Regula falsi iterations for a release from a stop within a sample step."""


def loop_system(params: ServoParams, duration):
    """(A, B, C) of the scaled loop with the moment states: shapes (6, 6), (6,), (6,).

    B is the column of the test voltage [V] (before the test winding's gain); the external
    moment enters through the states M̃ and r. `duration` [s] scales r."""
    a, b, c, _ = state_space(params)
    gain = params.pickoff_gain * params.amplifier_gain * params.pendulum_length
    period = time_constant(params)
    one = jnp.ones_like(gain)
    scale = jnp.stack([1 / gain, 1 / (gain * period), params.torquer_gain, one])
    inputs = jnp.stack([one, params.torquer_gain])
    b = b[:, jnp.array([0, 2])]
    a_s = a * scale[None, :] / scale[:, None]
    b_s = b * inputs[None, :] / scale[:, None]
    c_s = c[0] * scale
    dtype = a_s.dtype
    a_full = jnp.zeros((N_STATES, N_STATES), dtype)
    a_full = a_full.at[:4, :4].set(a_s).at[:4, 4].set(b_s[:, 1]).at[4, 5].set(1 / duration)
    b_full = jnp.zeros(N_STATES, dtype).at[:4].set(b_s[:, 0])
    c_full = jnp.zeros(N_STATES, dtype).at[:4].set(c_s)
    return a_full, b_full, c_full


def accel_moment(params: ServoParams):
    """M̃ [V] per g of input acceleration: the inertial moment m l g₀ over k_dm."""
    return params.pendulum_mass * params.pendulum_length * STANDARD_GRAVITY / params.torquer_gain


def equilibrium(params: ServoParams, drive, moment):
    """The state at rest under a test-winding drive g·U_test = `drive` [V] and the external
    moment M̃ = `moment` [V] (moment rate zero)."""
    gain = params.pickoff_gain * params.amplifier_gain * params.pendulum_length
    v = gain * params.torquer_gain * (drive + moment) / loop_stiffness(params)
    return jnp.stack([v, 0 * v, drive - v, v, moment + 0 * v, 0 * v])


def initial_state(params: ServoParams, drive, moment, rate, dv, dw, lag_states=(0.0, 0.0)):
    """The state at the first sample: at rest under the first drive, displaced by dv [V]
    in deflection and dw [V] in velocity (a record that starts in a transient), the moment
    drifting at `rate` [V per record].

    The lag states follow the displacement to first order in their time constants: the
    torquer's M̃ = g·U − v + T_dm·v̇ and the filter's U_f = v − T_f·v̇ (v̇ = w/T in the scaled
    velocity w), the solutions of T_dm·Ṁ̃ = g·U − v − M̃ and T_f·U̇_f = v − U_f along the
    transient, exact to O((T_lag/T)²). With ideal lags they are the quasi-static values.
    `lag_states` (M̃, U_f) [V] are added to them: a start whose lag states depart from that
    rule (a long lag, a start soon after a stop contact) is then described exactly."""
    rest = equilibrium(params, drive, moment)
    rate_v = dw / time_constant(params)
    torquer = -dv + params.torquer_time_constant * rate_v + lag_states[0]
    output = dv - params.filter_time_constant * rate_v + lag_states[1]
    return rest + jnp.stack([dv, dw, torquer, output, 0 * dv, rate + 0 * dv])


class SequenceInputs(NamedTuple):
    """What a record's simulation takes besides the device and the sampling: the test
    voltage sequence and the state the record starts from.

    - `first_level`: U_test at t_0 [V];
    - `gain`: g, the test winding's signed gain;
    - `moment`: M̃ = M/k_dm [V], the external moment; `rate`: r, its change over the
      record [V];
    - `dv`, `dw`: the initial displacement from equilibrium of v and w [V];
    - `change_index` (J,) int, `change_step` ΔU_j [V] (0 pads), `change_shift` δ_j (J,) in
      samples: change j at t_{i_j} + δ_j Δ.
    - `change_moment` (J,) [V]: the jump of the external moment M̃ at change j (an
      acceleration step along the input axis, ΔM̃ = m l Δa/k_dm; default none). A change
      may move the test voltage, the moment or both.
    - `lag_states` (M̃, U_f) [V]: the initial torquer and filter states' departure from
      their first-order rule (`initial_state`; default none).
    """

    first_level: float | jax.Array
    gain: float | jax.Array
    moment: float | jax.Array
    rate: float | jax.Array
    dv: float | jax.Array
    dw: float | jax.Array
    change_index: jax.Array
    change_step: jax.Array
    change_shift: jax.Array
    change_moment: jax.Array | None = None
    lag_states: tuple[float | jax.Array, float | jax.Array] = (0.0, 0.0)


def _moment_jumps(sequence: SequenceInputs, dtype):
    """`change_moment`, zeros when the sequence has none."""
    if sequence.change_moment is None:
        return jnp.zeros(jnp.shape(sequence.change_step), dtype)
    return jnp.asarray(sequence.change_moment, dtype)


def _change_split(change_shift):
    """For a change at t_i + δΔ (any real δ): the offset o of the first sample it reaches,
    i + o (the first t_k > t_i + δΔ), and ρ/Δ ∈ (0, 1], the part of a sample step it has
    acted for at that sample. The record is continuous (C¹) in δ across the jumps of o."""
    offset = jnp.floor(change_shift).astype(jnp.int32) + 1
    fraction = offset - change_shift
    return offset, fraction


def linear_record(
    params: ServoParams,
    dt,
    n: int,
    sequence: SequenceInputs,
    *,
    block=1,
    max_block: int = 1,
    duration=None,
):
    """Noise-free U_out [V] of the linear loop (no stops): at t_k = t_0 + kΔ, k < n, or,
    with `block` = m > 1, the means of the n blocks of m samples (samples bm … bm + m − 1).

    Block means are exact, not a resampling: with the unit-input affine state z = [x; u]
    (transition M = e^{[[A, B], [0, 0]]Δ}), a change that first reaches sample s = qm + p
    adds (1/m) c P_{m−p} ζ to block q and r̄ (M^m)^{b−q−1} ζ' to every later block b,
    with P_L = Σ_{l<L} M^l, r̄ = (1/m) c P_m, ζ = gΔU [Γ(ρ); 1] its state after the ρ it
    has acted before s and ζ' its state at the next block boundary; the initial
    displacement is the source at s = 0.

    **Arguments:** `params` (its `external_moment` is ignored: the sequence's `moment`),
    `dt` Δ [s], `n` (static) the number of outputs, `sequence` the record's `SequenceInputs`
    (test voltage, winding gain, moment, initial state); `block` m (may be traced:
    records sampled at different rates share one compiled program) and `max_block`
    (static) the largest m it may take (a Python int m raises it as needed); `duration`
    [s] the record's length that r refers to (default (n·m − 1)Δ). jit/vmap/grad-safe;
    float64.
    """
    (first_level, gain, moment, rate, dv, dw, change_index, change_step, change_shift) = sequence[
        :9
    ]
    m = block
    if isinstance(m, int) and m > max_block:
        max_block = m
    duration = dt * (n * m - 1) if duration is None else duration
    a, b, c = loop_system(params, duration)
    dtype = a.dtype
    size = N_STATES + 1
    augmented = jnp.zeros((size, size), dtype)
    augmented = augmented.at[:N_STATES, :N_STATES].set(a).at[:N_STATES, N_STATES].set(b)
    eye = jnp.eye(size, dtype=dtype)

    def flow(time):  # e^{[[A, B], [0, 0]] time}: the unit-input affine flow
        return expm_minus_identity(augmented * time) + eye

    offset, fraction = _change_split(change_shift)
    first = (change_index + offset).astype(jnp.int32)  # the first sample each change reaches
    q, p = first // m, first % m
    # Every exponential the record needs, as one batch (one instance of the squaring loop
    # in the program, not four): the sample step M, the block step M^m, and per change its
    # flow over ρ (to its first sample) and to the next block boundary.
    times = jnp.concatenate(
        [jnp.stack([dt, m * dt]).astype(dtype), fraction * dt, (fraction + m - p) * dt]
    )
    flows = jax.vmap(flow)(times)
    count = change_step.shape[0]
    sample_map, block_map = flows[0], flows[1]
    to_first, to_boundary = flows[2 : 2 + count], flows[2 + count :]

    c_aug = jnp.concatenate([c, jnp.zeros(1, dtype)])
    within = power_rows(sample_map, c_aug, max(max_block, 1))  # c M^l
    within = jnp.where((jnp.arange(within.shape[0]) < m)[:, None], within, 0.0)
    cumulative = jnp.cumsum(within, axis=0)  # c P_{l+1}, constant from l = m − 1 on
    mean_row = cumulative[-1] / m  # (1/m) c P_m
    rest = equilibrium(params, gain * first_level, moment)
    start = initial_state(params, gain * first_level, moment, rate, dv, dw, sequence.lag_states)
    # A change at τ leaves the state deviation e^{[[A, B], [0, 0]](t − τ)}[ΔM̃ e_M; gΔU] at
    # t ≥ τ: ζ at its first sample (after ρ), ζ' at the next block boundary.
    jumps = jnp.zeros((change_step.shape[0], size), dtype)
    jumps = (
        jumps.at[:, N_STATES].set(gain * change_step).at[:, 4].set(_moment_jumps(sequence, dtype))
    )
    zeta = jnp.einsum("jab,jb->ja", to_first, jumps)
    zeta_next = jnp.einsum("jab,jb->ja", to_boundary, jumps)
    weight = jnp.ones_like(change_step)
    initial = jnp.concatenate([start - rest, jnp.zeros(1, dtype)])
    head = jnp.concatenate(
        [
            (cumulative[-1] @ initial / m)[None],
            jnp.sum(cumulative[m - 1 - p] * zeta, 1) / m * weight,
        ]
    )
    tail = jnp.concatenate([(block_map @ initial)[None], weight[:, None] * zeta_next])
    q = jnp.concatenate([jnp.zeros(1, jnp.int32), q])
    level = c @ rest

    # Block recurrence of the summed sources: z_{b+1} = M^m z_b + (tails entering at b),
    # ȳ_b = C x_eq + r̄·z_b + (heads at b). A short loop (one step per block, 7 states);
    # a vectorised superposition (a convolution of r̄ (M^m)^i with the tails) computes the
    # same but was 4× slower to differentiate, vmapped, on the CPU.
    def step(z, b):
        here = (q == b).astype(dtype)
        return block_map @ z + here @ tail, level + mean_row @ z + here @ head

    _, record = jax.lax.scan(step, jnp.zeros(N_STATES + 1, dtype), jnp.arange(n), unroll=2)
    return record


def _taylor_flow(a, state, velocity_field, s):
    """x(s) of x' = A x + b from x(0) = `state`, with `velocity_field` = A x(0) + b:
    x + Σ_{k=1..K} s^k/k! A^{k−1} f (b constant over the step)."""
    term = velocity_field
    out = state
    factor = jnp.ones_like(s)
    for k in range(1, TAYLOR_ORDER + 1):
        factor = factor * s / k
        out = out + factor * term
        term = a @ term
    return out


WHOLE_BLOCK_MIN = 4
"""Blocks of at least this many samples are taken whole by the sample-stepped records
(`stop_record`, `contact.contact_record`) where no change falls within them and no stop
acts (`whole_blocks`); shorter ones sample by sample. The whole-block step computes all
`max_block` + 1 states whatever m is: measured on the 2-core CPU (`contact_record`, 6,000
samples, one stop, its Jacobian in three parameters, `max_block` 32), m = 1 ran 2× slower
that way, m = 4 2× faster, m = 20 3× faster."""


def not_tried(x):
    """A block try's answer where it was not made: (taken, x_end, total) = (False, x, 0)."""
    return jnp.zeros((), bool), x, jnp.zeros((), x.dtype)


def whole_blocks(
    transition,
    forcing,
    c,
    gain,
    first_level,
    change_step,
    interval,
    active,
    m,
    max_block: int,
    held_forcing=None,
):
    """`try_block(x, first, free_states)` → (taken, x_end, total) for the block of m samples
    from sample `first` at state x: with no change within it (steps k ∈ [first, first + m)
    never hit one) its states are x_k = Φ^k x + Σ_{i<k} Φ^i γ u (k ≤ m: the powers of the
    affine sample map [[Φ, γ], [0, 1]], `max_block` + 1 of them, made once), the same free
    steps the sample loop takes, as one product; total = Σ_{k<m} c·x_k; u the level the
    changes before the block left (gain g, `first_level`, `change_step` at the steps
    `interval` where `active`). `taken` is false for a short block (m < `WHOLE_BLOCK_MIN`:
    the states are then not computed), one longer than `max_block`, one with a change, and
    where `free_states(states)` (one bool per state: no stop acts there) is false for some
    x_k, k ≤ m.

    `held_forcing`: the sample map's column of a second constant input v (the stop a
    compliant contact presses on, `contact.contact_record`), given to `try_block` as
    `held`; the states are then x_k = Φ^k x + Σ_{i<k} Φ^i (γ u + γ_v v)."""
    size = transition.shape[0]
    columns = [forcing] if held_forcing is None else [forcing, held_forcing]
    inputs = len(columns)
    affine = jnp.eye(size + inputs, dtype=transition.dtype).at[:size, :size].set(transition)
    for i, column in enumerate(columns):
        affine = affine.at[:size, size + i].set(column)
    stack, power = jnp.eye(size + inputs, dtype=affine.dtype)[None], affine
    while stack.shape[0] < max_block + 1:  # M^k by doubling
        stack = jnp.concatenate([stack, stack @ power])
        power = power @ power
    powers = stack[: max_block + 1]
    k_index = jnp.arange(max_block + 1)

    def try_block(x, first, free_states, held: float | jax.Array = 0.0):
        def attempt(x):
            before = active & (interval < first)
            drive = gain * (first_level + jnp.sum(jnp.where(before, change_step, 0.0)))
            given = [drive] if held_forcing is None else [drive, jnp.asarray(held, x.dtype)]
            states = (powers @ jnp.concatenate([x, jnp.stack(given)]))[:, :size]
            free = jnp.all(free_states(states) | (k_index > m))
            quiet = ~jnp.any(active & (interval >= first) & (interval < first + m))
            total = jnp.sum(jnp.where(k_index < m, states @ c, 0.0))
            return free & quiet, states[m], total

        # (m ≤ max_block: a traced m beyond the powers made goes sample by sample.)
        return jax.lax.cond((m >= WHOLE_BLOCK_MIN) & (m <= max_block), attempt, not_tried, x)

    return try_block


def stop_record(
    params: ServoParams,
    dt,
    n: int,
    sequence: SequenceInputs,
    stop_high,
    stop_low,
    *,
    block=1,
    max_block: int = 1,
    duration=None,
):
    """Noise-free U_out [V] of the loop with inelastic stops at v = `stop_high` and
    v = `stop_low` [V] (stop_low < stop_high; far away for none), stepped sample by sample
    (a free block without a change whole: `whole_blocks`): at the samples (m = 1) or as the
    means of n blocks of `block` = m samples (m may be traced; `max_block` as in
    `linear_record`). Arguments otherwise as `linear_record`."""
    (first_level, gain, moment, rate, dv, dw, change_index, change_step, change_shift) = sequence[
        :9
    ]
    m = block
    if isinstance(m, int) and m > max_block:
        max_block = m
    duration = dt * (n * m - 1) if duration is None else duration
    a, b, c = loop_system(params, duration)
    jumps = _moment_jumps(sequence, a.dtype)
    transition, forcing = zoh(a, b, dt)
    offset, fraction = _change_split(change_shift)
    # Step k (from t_k to t_{k+1}) holds the change j when τ_j lies in [t_k, t_{k+1}).
    interval = change_index + offset - 1
    active = (change_step != 0) | (jumps != 0)
    partial_t, partial_f = jax.vmap(lambda s: zoh(a, b, s))(fraction * dt)
    start = initial_state(params, gain * first_level, moment, rate, dv, dw, sequence.lag_states)

    held_a = a.at[:2].set(0.0)
    held_b = b.at[:2].set(0.0)

    def clip_to(state, stop):
        return state.at[0].set(stop).at[1].set(0.0)

    def sample_step(k, carry):
        x, held, total = carry
        before = (k > interval) & active
        level_k = first_level + jnp.sum(jnp.where(before, change_step, 0.0))
        hit = (k == interval) & active
        change = jnp.any(hit)
        j = jnp.argmax(hit)
        step_k = jnp.where(change, change_step[j], 0.0)
        # A moment jump at τ within the step: its state deviation e_M ΔM̃ carried over ρ.
        jump_k = jnp.where(change, jumps[j], 0.0) * partial_t[j][:, 4]
        drive_old = gain * level_k
        drive_new = gain * (level_k + step_k)
        total = total + c @ x
        x_free = transition @ x + drive_old * forcing + gain * step_k * partial_f[j] + jump_k
        # Held on a stop and pushed into it by the old input: it stays there until the
        # change, then moves from the stop for the rest of the step.
        push = (a @ x + b * drive_old)[1]
        pushed = ((held > 0) & (push > 0)) | ((held < 0) & (push < 0))
        x_held = partial_t[j] @ x + partial_f[j] * drive_new + jump_k
        x_next = jnp.where(change & pushed, x_held, x_free)
        beyond = (x_next[0] > stop_high) | (x_next[0] < stop_low)

        def contact(x_next):
            # A stop reached within the step: the velocity is lost at the contact (found by
            # interpolation), and the flow goes on from the stop for the rest of the step.
            # (At most one stop is reached in a step: the one on the side it moved to.)
            upper = x_next[0] > stop_high
            sign = jnp.where(upper, 1.0, -1.0)
            stop = jnp.where(upper, stop_high, stop_low)
            gap_before = sign * (stop - x[0])
            travelled = sign * (x_next[0] - x[0])
            safe = jnp.where(travelled > 0, travelled, 1.0)
            at = jnp.clip(jnp.where(travelled > 0, gap_before / safe, 0.0), 0.0, 1.0)
            on_stop = clip_to(x + at * (x_next - x), stop)
            # Held through a change that does not pull it off at once (a lagged torquer's
            # moment follows the new input gradually): on the stop until the change, then as
            # after a contact at the change time.
            held_change = change & pushed
            raw_jump = jnp.zeros_like(x).at[4].set(jnp.where(change, jumps[j], 0.0))
            at = jnp.where(held_change, 1 - fraction[j], at)
            on_stop = jnp.where(held_change, clip_to(x + raw_jump, stop), on_stop)
            moved = _taylor_flow(a, on_stop, a @ on_stop + b * drive_new, (1 - at) * dt)
            still_beyond = sign * (moved[0] - stop) >= 0

            # Released within the step: pressed onto the stop at the contact (or at a change)
            # and pulled off it before the step ends, as a lagged torquer's moment does after
            # a change. On the stop, v and w are held and the lag states follow the clamped
            # flow (A, b with the rows of v and w zeroed); the release is where the pressing
            # moment crosses zero along it (regula falsi), and the flow goes on free from there.
            def held_flow(state, span):
                return _taylor_flow(held_a, state, held_a @ state + held_b * drive_new, span * dt)

            def press(state):
                return sign * (a @ state + b * drive_new)[1]

            remaining = 1 - at
            held_end = held_flow(on_stop, remaining)
            press_start, press_end = press(on_stop), press(held_end)
            release = (press_start > 0) & (press_end < 0)

            def released(_):
                low, high = jnp.zeros_like(at), remaining
                p_low, p_high = press_start, jnp.where(release, press_end, -1.0)
                mid = low  # set by the first iteration (RELEASE_ITERATIONS ≥ 1)
                for _ in range(RELEASE_ITERATIONS):
                    mid = low + (high - low) * p_low / jnp.where(release, p_low - p_high, 1.0)
                    p_mid = press(held_flow(on_stop, mid))
                    inside = p_mid > 0
                    low, p_low = jnp.where(inside, mid, low), jnp.where(inside, p_mid, p_low)
                    high, p_high = jnp.where(inside, high, mid), jnp.where(inside, p_high, p_mid)
                at_release = held_flow(on_stop, mid)
                return _taylor_flow(
                    a, at_release, a @ at_release + b * drive_new, (remaining - mid) * dt
                )

            x_next = jax.lax.cond(
                release, released, lambda _: jnp.where(still_beyond, held_end, moved), None
            )
            new_held = jnp.where(still_beyond & ~release, sign.astype(held.dtype), 0)
            return x_next, new_held

        # Only a step that ends beyond a stop needs the contact (a branch taken at run
        # time when not vmapped: most steps of a record are free).
        x_next, new_held = jax.lax.cond(
            beyond, contact, lambda x_next: (x_next, jnp.zeros_like(held)), x_next
        )
        return x_next, new_held, total

    try_block = whole_blocks(
        transition, forcing, c, gain, first_level, change_step, interval, active, m, max_block
    )

    def within_stops(states):
        return (states[:, 0] <= stop_high) & (states[:, 0] >= stop_low)

    def block_step(carry, index):
        x, held = carry

        def sample_loop(x):
            zero = jnp.zeros((), x.dtype)
            return jax.lax.fori_loop(index * m, index * m + m, sample_step, (x, held, zero))

        # Free of the stops at its start (not held) and throughout: the block whole.
        taken, x_fast, total_fast = try_block(x, index * m, within_stops)
        taken = taken & (held == 0)
        x, held, total = jax.lax.cond(
            taken, lambda _: (x_fast, held, total_fast), sample_loop, x
        )
        return (x, held), total / m

    _, ys = jax.lax.scan(block_step, (start, jnp.zeros((), jnp.int32)), jnp.arange(n))
    return ys
