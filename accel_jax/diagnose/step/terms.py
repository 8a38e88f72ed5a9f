"""The term library of the discovery of a missing term (`discover`) and the loop simulated
with its terms (`term_record`).

Each term is a signal s(x, U) of the loop's scaled states (`_simulate.sequence`: v the
deflection as the amplifier voltage, w = T v̇, the torquer moment m, the output y) times a
coefficient c, entering at one place:

- `pickoff`: the amplifier voltage v becomes v + c·s (feeds the torquer and the output);
- `moment` (spring, damping, torquer, forcing): a moment c·s [V of M/k_dm] on the pendulum;
- `output`: the output U_out becomes U_out + c·s;

and two extra poles (in the feedback path, at the output), each an exact first-order lag of
time constant c·T for c > 0 (a state of its own) and a lead to first order for c < 0. Each
term is zero at c = 0, so the nominal model is nested exactly. The signals are normalised
by the training output's half range h and the loop's time constant T (`Scales`), so
coefficients are fractions (c = 0.05: 5 % of the signal's size at the range's half).

**Simulation** (`term_record`): the loop sample by sample (`lax.scan`) on the affine state
[x; g·U] of `_simulate.sequence.linear_record` — the nominal part exact (the sample map
e^{[[A, B], [0, 0]]Δ}, each change's sub-sample flow) — with the terms' input taken linear
over each sample step between its values at the two ends (ETD2, a second-order
exponential integrator with an Euler predictor). At c = 0 it equals `linear_record` to
round-off; the terms' part converges at second order in Δ (halving Δ changed a 0.33 V
pickoff effect by ~1e-6 V per sample on a reference record, Δ/T ≈ 1/150). Float64.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from ..._simulate.matrix import expm_minus_identity
from ..._simulate.sequence import N_STATES, SequenceInputs, _change_split, initial_state, loop_system


class Term(NamedTuple):
    """One candidate term: `name`; `place` where it enters (`pickoff`, `moment` or
    `output`); `family` what a designer calls it (pickoff, spring, damping, torquer,
    forcing, output); `formula` in words; `width` its number of coefficients."""

    name: str
    place: str
    family: str
    formula: str
    width: int = 1


TERMS = (
    Term("pickoff_square", "pickoff", "pickoff", "U_amp += c·v²/h"),
    Term("pickoff_cube", "pickoff", "pickoff", "U_amp += c·v³/h²"),
    Term("pickoff_abs", "pickoff", "pickoff", "U_amp += c·|v|v/h"),
    Term("spring_square", "moment", "spring", "M/k_dm += c·v²/h"),
    Term("spring_cube", "moment", "spring", "M/k_dm += c·v³/h²"),
    Term("damping_quadratic", "moment", "damping", "M/k_dm += c·w|w|/h (w = T v̇)"),
    Term("dry_friction", "moment", "damping", "M/k_dm += c·h·tanh(w/(ε h)), ε = 0.02"),
    Term("torquer_asymmetry", "moment", "torquer", "M_dm/k_dm += c·|m| (scale factor by direction)"),
    Term("torquer_square", "moment", "torquer", "M_dm/k_dm += c·m|m|/h"),
    Term("torquer_dead_zone", "moment", "torquer", "M_dm/k_dm += c·h·tanh(m/(ε h))"),
    Term(
        "torquer_pole", "moment", "torquer",
        "an extra pole of time constant c·T in the feedback path (c < 0: a lead, −c·T·ṁ)",
    ),
    Term("output_square", "output", "output", "U_out += c·y²/h"),
    Term(
        "output_pole", "output", "output",
        "an extra pole of time constant c·T at the output (c < 0: a lead, −c·T·ẏ)",
    ),
    Term("forcing_ramp", "moment", "forcing", "M/k_dm += c·h·t/t_rec"),
    Term("forcing_sinusoid", "moment", "forcing", "M/k_dm += h(c₁ sin ωt + c₂ cos ωt)", 2),
)
"""The step records' term library (see the module docstring)."""

EPSILON = 0.02
"""ε of the smoothed signs (dry friction, a dead zone), in units of h."""



def _offsets() -> tuple[int, ...]:
    out, k = [], 0
    for term in TERMS:
        out.append(k)
        k += term.width
    return tuple(out)


OFFSETS = _offsets()
N_COEFFICIENTS = OFFSETS[-1] + TERMS[-1].width
_TORQUER_POLE = OFFSETS[[t.name for t in TERMS].index("torquer_pole")]
_OUTPUT_POLE = OFFSETS[[t.name for t in TERMS].index("output_pole")]


def columns(indices) -> list[int]:
    """The coefficient columns of the terms `indices`."""
    return [OFFSETS[i] + j for i in indices for j in range(TERMS[i].width)]


class Scales(NamedTuple):
    """What the signals are normalised by: `half` h [V], `period` T [s], `duration` [s]
    of the record, `omega` [rad/s] the sinusoid's frequency."""

    half: jax.Array | float
    period: jax.Array | float
    duration: jax.Array | float
    omega: jax.Array | float


def _signals(x, drive, c_out, t, ideal_torquer, scales: Scales):
    """Every coefficient's signal at one sample: (moment (N_COEFFICIENTS,), pickoff (…),
    output (…)), each zero where the term does not enter there."""
    h = scales.half
    v, w = x[0], x[1]
    torque = jnp.where(ideal_torquer, drive - v, x[2])
    y = c_out @ x
    smooth = EPSILON * h
    zero = jnp.zeros((), x.dtype)
    values = {
        "pickoff_square": v * v / h,
        "pickoff_cube": v**3 / h**2,
        "pickoff_abs": jnp.abs(v) * v / h,
        "spring_square": v * v / h,
        "spring_cube": v**3 / h**2,
        "damping_quadratic": w * jnp.abs(w) / h,
        "dry_friction": h * jnp.tanh(w / smooth),
        "torquer_asymmetry": jnp.abs(torque),
        "torquer_square": torque * jnp.abs(torque) / h,
        "torquer_dead_zone": h * jnp.tanh(torque / smooth),
        "torquer_pole": zero,  # both poles are `term_record`'s own
        "output_square": y * y / h,
        "output_pole": zero,
        "forcing_ramp": h * t / scales.duration,
    }
    out = {"moment": [], "pickoff": [], "output": []}
    for term in TERMS:
        if term.name == "forcing_sinusoid":
            signal = [h * jnp.sin(scales.omega * t), h * jnp.cos(scales.omega * t)]
        else:
            signal = [values[term.name]]
        for place in out:
            out[place].extend(signal if place == term.place else [zero] * term.width)
    return tuple(jnp.stack(out[p]) for p in ("moment", "pickoff", "output"))


def term_record(
    params, dt, n: int, m: int, sequence: SequenceInputs, coefficients, scales, residual=None
):
    """U_out [V] of the loop with the terms' `coefficients` (N_COEFFICIENTS,): the means of
    `n` blocks of `m` samples (static). At zero coefficients, `linear_record`'s record.
    `coefficients` None: no terms (the same record as zeros, without computing the terms'
    signals: the network reference's fit, whose Jacobian would otherwise carry them
    sample by sample). `residual`: None, or a function (v, w, m, g·U) [V] → (moment,
    output) [V] added as the terms are (the network reference, `ceiling`)."""
    (first_level, gain, moment, rate, dv, dw, change_index, change_step, change_shift) = sequence[
        :9
    ]
    total = n * m
    a, b, c_out = loop_system(params, scales.duration)
    dtype = a.dtype
    size = N_STATES + 1
    augmented = jnp.zeros((size, size), dtype).at[:N_STATES, :N_STATES].set(a)
    augmented = augmented.at[:N_STATES, N_STATES].set(b)
    eye = jnp.eye(size, dtype=dtype)
    # The places' input columns: a moment enters as M̃ does; a pickoff error δv drives the
    # torquer as −δv of test voltage (before the winding's gain) and the output filter as
    # v does (with no filter, the output reads v: the feed-through c_out[0]).
    place_columns = jnp.stack([a[:, 4], -b + jnp.zeros_like(b).at[3].set(a[3, 0])], axis=1)
    # The terms' input u(s) over a sample step taken linear between the samples (ETD2, a
    # second-order exponential integrator): x(Δ) = e^{AΔ}x + Γ₁u_k + Γ₂(u_{k+1} − u_k),
    # Γ₁ = ∫₀^Δ e^{Aσ}dσ E and Γ₂ = ∫₀^Δ e^{Aσ}(Δ − σ)dσ E/Δ, both from one exponential
    # of [[A, E, 0], [0, 0, I], [0, 0, 0]]Δ (Van Loan).
    van_loan = jnp.zeros((N_STATES + 4, N_STATES + 4), dtype)
    van_loan = van_loan.at[:N_STATES, :N_STATES].set(a).at[:N_STATES, N_STATES:N_STATES + 2].set(
        place_columns
    )
    van_loan = van_loan.at[N_STATES : N_STATES + 2, N_STATES + 2 :].set(jnp.eye(2, dtype=dtype))
    exponential = expm_minus_identity(van_loan * dt)
    gamma_1 = exponential[:N_STATES, N_STATES : N_STATES + 2]
    gamma_2 = exponential[:N_STATES, N_STATES + 2 :] / dt
    offset, fraction = _change_split(change_shift)
    first = (change_index + offset).astype(jnp.int32)
    times = jnp.concatenate([jnp.asarray([dt], dtype), fraction * dt])
    flows = jax.vmap(lambda s: expm_minus_identity(augmented * s) + eye)(times)
    sample_map, to_first = flows[0], flows[1:]
    moments = (
        jnp.zeros_like(change_step) if sequence.change_moment is None else sequence.change_moment
    )
    jumps = jnp.zeros((change_step.shape[0], size), dtype)
    jumps = jumps.at[:, N_STATES].set(gain * change_step).at[:, 4].set(moments)
    zeta = jnp.einsum("jab,jb->ja", to_first, jumps)
    entering = jnp.zeros((total, size), dtype).at[first].add(zeta, mode="drop")
    start = initial_state(params, gain * first_level, moment, rate, dv, dw, sequence.lag_states)
    z0 = jnp.concatenate([start, jnp.asarray([gain * first_level], dtype)])
    ideal_torquer = params.torquer_time_constant == 0
    feed = c_out[0]  # the output's read of v (1 with no output filter, else 0)
    with_terms = coefficients is not None
    coefficients = (
        jnp.asarray(coefficients, dtype) if with_terms else jnp.zeros(N_COEFFICIENTS, dtype)
    )
    # The two extra poles, exact for c > 0 (a first-order lag of time constant c·T, a state
    # of its own); for c < 0 a lead to first order, −c·T times the backward difference of
    # the torquer moment or the output over the sample step: the pole's own first-order
    # effect, so that both sides of c = 0 meet with one derivative.
    c_torquer, c_output = coefficients[_TORQUER_POLE], coefficients[_OUTPUT_POLE]
    lead = coefficients.at[_TORQUER_POLE].set(jnp.where(c_torquer > 0, 0.0, c_torquer))
    lead = lead.at[_OUTPUT_POLE].set(jnp.where(c_output > 0, 0.0, c_output))
    tau_torquer = scales.period * jnp.where(c_torquer > 0, c_torquer, 0.0)
    tau_output = scales.period * jnp.where(c_output > 0, c_output, 0.0)

    def lag(previous_out, previous_in, new_in, tau):
        # τ s' = u − s over one sample step, u linear between the samples: exact, and the
        # identity (s = u) at τ = 0.
        positive = tau > 0
        decay = jnp.where(positive, jnp.exp(-dt / jnp.where(positive, tau, 1.0)), 0.0)
        slope = tau * (new_in - previous_in) / dt
        return new_in - slope + decay * (previous_out - previous_in + slope)

    def torque(z):
        return jnp.where(ideal_torquer, z[N_STATES] - z[0], z[2])

    lead_torquer = -scales.period * lead[_TORQUER_POLE] / dt
    lead_output = -scales.period * lead[_OUTPUT_POLE] / dt

    def forces(z, time, lagged_torque, torque_before):
        x, drive = z[:N_STATES], z[N_STATES]
        if with_terms:
            signals = _signals(x, drive, c_out, time, ideal_torquer, scales)
            on_moment, on_pickoff, on_output = (lead @ s for s in signals)
        else:
            on_moment = on_pickoff = on_output = jnp.zeros((), dtype)
        torque_now = torque(z)
        moment_force = (
            on_moment + (lagged_torque - torque_now)
            + lead_torquer * (torque_now - torque_before)
        )
        output = c_out @ x + feed * on_pickoff + on_output
        if residual is not None:
            extra_moment, extra_output = residual(x[0], x[1], torque_now, drive)
            moment_force, output = moment_force + extra_moment, output + extra_output
        return jnp.stack([moment_force, on_pickoff]), output

    def padded(v):
        return jnp.concatenate([v, jnp.zeros(1, dtype)])

    def step(carry, inputs):
        z, lagged_before, torque_before, filtered, previous = carry
        k, enter = inputs
        z = z + enter  # the changes that first reach this sample
        torque_k = torque(z)
        lagged_k = lag(lagged_before, torque_before, torque_k, tau_torquer)
        u_k, y = forces(z, k * dt, lagged_k, torque_before)
        ahead = sample_map @ z + padded(gamma_1 @ u_k)  # the predictor
        lagged_ahead = lag(lagged_k, torque_k, torque(ahead), tau_torquer)
        u_next, _ = forces(ahead, (k + 1) * dt, lagged_ahead, torque_k)
        z_next = ahead + padded(gamma_2 @ (u_next - u_k))
        filtered = lag(filtered, previous, y, tau_output)
        return (z_next, lagged_k, torque_k, filtered, y), filtered + lead_output * (y - previous)

    y0 = c_out @ z0[:N_STATES]
    carry = (z0, torque(z0), torque(z0), y0, y0)
    # Two samples per loop iteration (the same arithmetic per sample). In one process on the
    # 2-core CPU (a 6,400-sample discovery refit, 15 alternated calls each): the residuals
    # 28.8 → 17.7 ms (median), the Jacobian 81.6 → 82.4 ms (unchanged, equal to the bit);
    # 3 and 4 samples per iteration were no faster (docs/performance.md).
    _, samples = jax.lax.scan(
        step, carry, (jnp.arange(total, dtype=dtype), entering), unroll=2
    )
    return samples.reshape(n, m).mean(axis=1)
