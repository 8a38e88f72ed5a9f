"""Records of a piecewise-constant test-voltage sequence with compliant mechanical stops:
the loop of `sequence` whose pendulum meets a spring-damper contact at each stop.

**Contact.** Beyond a stop the pendulum presses into a unilateral spring-damper: with
the penetration δ = θ − θ_hi (upper stop; δ = θ_lo − θ for the lower one) the contact
moment is −max(0, K_c δ + C_c δ') (it pushes, never pulls). K_c = κ·k_loop is given by
its ratio κ (`stiffness`) to the loop's static stiffness k_loop = c + k_dm k_dp k_y l,
and C_c = 2 ζ_c √(K_c J) by the contact's damping ratio ζ_c (`damping_ratio`). A stiff,
well-damped contact (κ ≳ 10⁴, ζ_c ≈ 1) approaches the inelastic clamp of
`sequence.stop_record`; a soft one (κ ~ 10) lets the loop push well past the stop.

In the scaled state of `sequence` (v, w, m, U_f, M̃, r; volts) the contact moment enters
as the external moment does, through A's column of M̃: in contact with the upper stop
at v = v_hi,

    x' = A x + b g U + a_M (−s (v − v_hi) − d w),   s = K_c/(g k_dm), d = C_c/(g T k_dm)

(g = k_dp k_y l, T the loop's time constant, a_M the column of M̃): one linear affine
system per regime (free, upper contact, lower contact), the two contacts sharing one
matrix.

**Stepping.** Block by block (`lax.scan`): a block of m ≥ `sequence.WHOLE_BLOCK_MIN`
samples with no change in it and every sample's state free of both contacts is one
product (`sequence.whole_blocks`), and so is one whose every state lies in the contact it
starts in (the powers of that contact's affine sample map: a pendulum resting on its
stop); any other block sample by sample. A sample step that starts free and whose exact
free flow ends inside neither contact is taken in one exact step (a branch taken at run
time when not vmapped: most steps are free), and so is one without a change that starts
in a contact and whose exact flow of that contact ends in it. Otherwise the step is cut
into `substeps` equal parts, each taken with the exact flow (`matrix.zoh`, Van Loan) of
the regime in force at its start; when the regime at its end differs, the switch time within
the part is found by regula falsi on the switching function (the penetration, or the
contact force, crossing zero) along the first regime's flow, and the two pieces are taken
with a fourth-order Taylor expansion of each regime's flow (`sequence._taylor_flow`:
accurate while ‖A h‖ ≲ 0.3 for a part h, i.e. up to κ of a few thousand with 8 parts at
0.5 MHz; a stiffer contact needs more parts). A test-voltage change
(or a moment jump) within a part enters exactly, by superposition (its input's flow over
the rest of the part). A contact that starts and ends within one free sample step (a
graze shorter than a sample) is missed; a contact period is tens of samples at the
largest κ of interest (κ = 3000 with the reference device: ~33 µs).

Checked against `linear_record` with the stops out of reach (exact), against the
inelastic `stop_record` in the stiff, damped limit, for convergence in `substeps`, and
against an independent SciPy simulator of the same physics (`studies/contact_truth.py`,
written without this code). Float64 throughout, as `sequence`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .._params import ServoParams
from .._servo import loop_stiffness, time_constant
from .matrix import expm_minus_identity
from .sequence import N_STATES, SequenceInputs, _change_split, _moment_jumps, _taylor_flow
from .sequence import not_tried, whole_blocks
from .sequence import initial_state, loop_system

SUBSTEPS = 8
"""Default parts of a sample step in or near a contact."""

SWITCH_ITERATIONS = 3
"""Regula falsi iterations for a contact's start or end within a part of a step."""


def contact_system(params: ServoParams, duration, stiffness, damping_ratio):
    """(A, A_contact, f, b, c, s, d) of the scaled loop (`sequence.loop_system`) and its
    contact regime: in contact with the stop at v_s, x' = A_contact x + b g U + f v_s; f is
    the spring's column s·a_M, and s, d the contact's spring and damper in the scaled units
    (the upper contact's force, in volts of M̃, is s (v − v_s) + d w; module docstring)."""
    a, b, c = loop_system(params, duration)
    gain = params.pickoff_gain * params.amplifier_gain * params.pendulum_length
    spring_k = stiffness * loop_stiffness(params)
    damper_c = 2 * damping_ratio * jnp.sqrt(spring_k * params.moment_of_inertia)
    spring = spring_k / (gain * params.torquer_gain)
    damper = damper_c / (gain * time_constant(params) * params.torquer_gain)
    column = a[:, 4]
    row = jnp.zeros(N_STATES, a.dtype).at[0].set(-spring).at[1].set(-damper)
    return a, a + jnp.outer(column, row), column * spring, b, c, spring, damper


def _flow_maps(a, b, f, time):
    """(e^{A t}, ∫₀ᵗ e^{As} ds b, ∫₀ᵗ e^{As} ds f) from one exponential of the augmented
    matrix [[A, b, f], [0, 0, 0]] t (Van Loan)."""
    size = N_STATES + 2
    augmented = (
        jnp.zeros((size, size), a.dtype)
        .at[:N_STATES, :N_STATES]
        .set(a)
        .at[:N_STATES, N_STATES]
        .set(b)
        .at[:N_STATES, N_STATES + 1]
        .set(f)
    )
    e = expm_minus_identity(augmented * time)
    return e[:N_STATES, :N_STATES] + jnp.eye(N_STATES, dtype=a.dtype), e[:N_STATES, N_STATES], e[
        :N_STATES, N_STATES + 1
    ]


def contact_record(
    params: ServoParams,
    dt,
    n: int,
    sequence: SequenceInputs,
    stop_high,
    stop_low,
    stiffness,
    damping_ratio,
    *,
    block=1,
    max_block: int = 1,
    duration=None,
    substeps: int = SUBSTEPS,
    whole_holds: bool = True,
):
    """Noise-free U_out [V] of the loop with compliant stops at v = `stop_high` and
    v = `stop_low` [V] (stop_low < stop_high; far away for none: a stop on one side only
    is the other at ±1e6 V), each a unilateral spring-damper of stiffness `stiffness` × the
    loop's static stiffness and damping ratio `damping_ratio` (module docstring): at the
    samples (m = 1) or as the means of n blocks of `block` = m samples (m may be traced;
    `max_block`, static, the largest it may take, as in `sequence.linear_record`).
    Arguments otherwise as `sequence.linear_record`; `substeps` (static) the parts of a
    sample step in or near a contact; `whole_holds` (static): a sample step, or a block,
    that starts in a contact and stays in it is taken as one exact step of that contact's
    flow (False: part by part, as any step near a contact; the same record to round-off,
    a fit that presses on its stops ~4× slower). jit/vmap/grad-safe; float64."""
    (first_level, gain, moment, rate, dv, dw, change_index, change_step, change_shift) = sequence[
        :9
    ]
    m = block
    if isinstance(m, int) and m > max_block:
        max_block = m
    duration = dt * (n * m - 1) if duration is None else duration
    a, a_contact, f, b, c, spring, damper = contact_system(
        params, duration, stiffness, damping_ratio
    )
    dtype = a.dtype
    jumps = _moment_jumps(sequence, dtype)
    offset, fraction = _change_split(change_shift)
    interval = change_index + offset - 1
    active = (change_step != 0) | (jumps != 0)
    h = dt / substeps
    # A change acts for `fraction`·Δ at the end of its sample step: it falls in part
    # `part` of the step, with `rest`·Δ of that part after it.
    when = (1 - fraction) * substeps
    part = jnp.clip(jnp.floor(when).astype(jnp.int32), 0, substeps - 1)
    rest = (part + 1 - when) * h
    zero_f = jnp.zeros_like(f)

    def both(time):  # the flow maps of the free and the contact regime over `time`
        return _flow_maps(a, b, zero_f, time), _flow_maps(a_contact, b, f, time)

    whole_free = _flow_maps(a, b, zero_f, dt)
    phi_c, gamma_c, gamma_fc = _flow_maps(a_contact, b, f, dt)  # a whole step in contact
    partial_free = jax.vmap(lambda s: _flow_maps(a, b, zero_f, s))(fraction * dt)
    part_maps = both(h)
    before_maps = jax.vmap(both)(h - rest)
    after_maps = jax.vmap(both)(rest)
    start = initial_state(params, gain * first_level, moment, rate, dv, dw, sequence.lag_states)

    def force(x, side):
        # The contact force (in the spring's units) of the upper (side +1) or lower (−1)
        # stop, and the penetration; in contact while both are positive.
        stop = jnp.where(side > 0, stop_high, stop_low)
        depth = side * (x[0] - stop)
        return depth, side * (spring * (x[0] - stop) + damper * x[1])

    def switching(x, side):
        depth, push = force(x, side)
        return jnp.minimum(depth, push)

    def regime(x):
        return jnp.where(switching(x, 1.0) > 0, 1, jnp.where(switching(x, -1.0) > 0, -1, 0))

    def _affine_flow(r, x, drive, span):
        # Regime r's flow (0 free, ±1 a contact) over `span` [s] from x: a fourth-order
        # Taylor expansion (span ≤ one part: ‖A span‖ ≲ 0.2 up to κ = 3000 at 0.5 MHz).
        contact = r != 0
        stop = jnp.where(r > 0, stop_high, stop_low)
        matrix = jnp.where(contact, a_contact, a)
        velocity = matrix @ x + b * drive + jnp.where(contact, f * stop, 0.0)
        return _taylor_flow(matrix, x, velocity, span)

    def sample_step(k, carry):
        x, total = carry
        before = (k > interval) & active
        level_k = first_level + jnp.sum(jnp.where(before, change_step, 0.0))
        hit = (k == interval) & active
        change = jnp.any(hit)
        j = jnp.argmax(hit)
        step_k = jnp.where(change, change_step[j], 0.0)
        jump_k = jnp.where(change, jumps[j], 0.0)
        drive_old = gain * level_k
        drive_step = gain * step_k
        total = total + c @ x
        phi, gamma, _ = whole_free
        x_free = (
            phi @ x
            + gamma * drive_old
            + partial_free[1][j] * drive_step
            + partial_free[0][j][:, 4] * jump_k
        )
        r_start = regime(x)
        near = (r_start != 0) | (regime(x_free) != 0)

        def advance(x, drive, span, maps):
            # Over `span` [s] under a constant drive: the exact flow of the regime in force
            # at the start and, where the regime at the end differs, the switch found by
            # regula falsi on the switching function along that flow.
            r = regime(x)
            contact = r != 0
            stop = jnp.where(r > 0, stop_high, stop_low)
            phi, gamma, gamma_f = [jnp.where(contact, cm, fm) for fm, cm in zip(*maps)]
            x_end = phi @ x + gamma * drive + jnp.where(contact, gamma_f * stop, 0.0)
            r_end = regime(x_end)

            def switched(_):
                side = jnp.where(r != 0, r, r_end).astype(dtype)
                low, high = jnp.zeros((), dtype), jnp.ones((), dtype)
                s_low, s_high = switching(x, side), switching(x_end, side)

                def falsi(_, bracket):
                    low, high, s_low, s_high, _ = bracket
                    width = jnp.where(s_low == s_high, 1.0, s_low - s_high)
                    alpha = jnp.clip(low + (high - low) * s_low / width, 0.0, 1.0)
                    s_mid = switching(_affine_flow(r, x, drive, alpha * span), side)
                    same = jnp.sign(s_mid) == jnp.sign(s_low)
                    low, s_low = jnp.where(same, alpha, low), jnp.where(same, s_mid, s_low)
                    high, s_high = jnp.where(same, high, alpha), jnp.where(same, s_high, s_mid)
                    return low, high, s_low, s_high, alpha

                bracket = (low, high, s_low, s_high, low)
                alpha = jax.lax.fori_loop(0, SWITCH_ITERATIONS, falsi, bracket)[-1]
                middle = _affine_flow(r, x, drive, alpha * span)
                return _affine_flow(r_end, middle, drive, (1 - alpha) * span)

            return jax.lax.cond(r_end != r, switched, lambda _: x_end, None)

        def substepped(x):
            def part_step(i, x):
                here = change & (i == part[j])
                after = change & (i > part[j])

                # The part whole, or, where the change falls in it, the part before the
                # change and then the jump and the part after it: one `advance` in the
                # program for every piece (a smaller program to compile).
                def piece(k, x):
                    second = k == 1

                    def pick(early, late, whole):  # this piece's map of one kind
                        return jnp.where(second, late[j], jnp.where(here, early[j], whole))

                    maps = jax.tree.map(pick, before_maps, after_maps, part_maps)
                    span = jnp.where(second, rest[j], jnp.where(here, h - rest[j], h))
                    drive = drive_old + jnp.where(second | after, drive_step, 0.0)
                    x = jnp.where(second, x.at[4].add(jump_k), x)
                    return advance(x, drive, span, maps)

                return jax.lax.fori_loop(0, 1 + here.astype(jnp.int32), piece, x)

            return jax.lax.fori_loop(0, substeps, part_step, x)

        def in_contact(x):
            # A step that starts in a contact, holds no change and whose exact flow of that
            # contact ends in it: one exact step too (a pendulum resting on its stop).
            stop_start = jnp.where(r_start > 0, stop_high, stop_low)
            x_held = phi_c @ x + gamma_c * drive_old + gamma_fc * stop_start
            held = whole_holds & (r_start != 0) & ~change & (regime(x_held) == r_start)
            return jax.lax.cond(held, lambda x: x_held, substepped, x)

        x_next = jax.lax.cond(near, in_contact, lambda x: x_free, x)
        return x_next, total

    # A free block without a change whole (`sequence.whole_blocks`): the sample loop takes
    # a free step exactly when neither end is in contact.
    phi, gamma, _ = whole_free

    try_block = whole_blocks(
        phi, gamma, c, gain, first_level, change_step, interval, active, m, max_block
    )

    def free_of_contact(states):
        return jax.vmap(regime)(states) == 0

    # A block without a change that starts in contact and stays in that contact at every
    # sample: one product of the contact flow's powers (a pendulum resting on its stop).
    try_held = whole_blocks(
        phi_c, gamma_c, c, gain, first_level, change_step, interval, active, m, max_block,
        held_forcing=gamma_fc,
    )

    def block_step(x, index):
        def sample_loop(x):
            zero = jnp.zeros((), x.dtype)
            return jax.lax.fori_loop(index * m, index * m + m, sample_step, (x, zero))

        side = regime(x)

        def held_block(x):
            def in_contact(states):
                return jax.vmap(regime)(states) == side

            stop = jnp.where(side > 0, stop_high, stop_low)
            return try_held(x, index * m, in_contact, stop)

        def not_free(x):  # a block that starts in a contact may stay in it throughout
            # (The sample loop once in the program, after both tries: it is its largest
            # part: with a second copy the contact fit compiled in 14.1 s instead of 11.2 s).
            held = whole_holds & (side != 0)
            taken, x_held, total_held = jax.lax.cond(held, held_block, not_tried, x)
            return jax.lax.cond(taken, lambda _: (x_held, total_held), sample_loop, x)

        taken, x_fast, total_fast = try_block(x, index * m, free_of_contact)
        x, total = jax.lax.cond(taken, lambda _: (x_fast, total_fast), not_free, x)
        return x, total / m

    _, ys = jax.lax.scan(block_step, start, jnp.arange(n))
    return ys
