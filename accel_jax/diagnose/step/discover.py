"""Discovery of a missing term (issue 45, step records): where no library effect explains a
record, which term of a library of candidate terms at named places in the loop does, and how
far it closes the held-out gap. A hypothesis, never a verdict: the verdict stays
`unexplained` and the result carries a `discovery` block.

**The term library** (`TERMS`). Each term is a signal s(x, U) of the loop's scaled states
(`_simulate.sequence`: v the deflection as the amplifier voltage, w = T v̇, the torquer
moment m, the output y) times a coefficient c, entering at one place:

- `pickoff`: the amplifier voltage v becomes v + c·s (feeds the torquer and the output);
- `moment` (spring, damping, torquer, forcing): a moment c·s [V of M/k_dm] on the pendulum;
- `output`: the output U_out becomes U_out + c·s.

Each is zero at c = 0, so the nominal model is nested exactly. The signals are normalised
by the training output's half range h and the loop's time constant T, so coefficients are
fractions (c = 0.05: 5 % of the signal's size at the range's half).

**Simulation** (`term_record`): the loop sample by sample (`lax.scan`) on the affine state
[x; g·U] of `_simulate.sequence.linear_record` — the nominal part exact (the sample map
e^{[[A, B], [0, 0]]Δ}, each change's sub-sample flow) — with the terms' input taken linear
over each sample step between its values at the two ends (ETD2, a second-order
exponential integrator with an Euler predictor). At c = 0 it equals `linear_record` to
round-off; the terms' part converges at second order in Δ (tests: halving Δ changes a
0.33 V pickoff effect by ~1e-5 V on the reference records, Δ/T ≈ 1/150).

**Screen, select, confirm** (`discover`):

1. Screen: the first-order effect of every coefficient on the block means, a `jax.jacfwd`
   through `term_record` at c = 0 on the nominal fit, whitened by the noise floor and
   regressed jointly with the nominal fit's own parameters (the device's refit and the
   record's nuisances before the input's: a term that they absorb scores nothing).
2. Select: every subset of up to `MAX_TERMS` terms by the extended BIC (Chen & Chen 2008:
   BIC + 2γ ln C(P, k), γ = 1, which accounts for the library's size P), its held-out
   χ² predicted from the training fit.
3. Confirm: the best `CONFIRM` subsets refitted in full — the simulation with the terms,
   the device and the record's nuisances together (MINPACK's Levenberg–Marquardt through
   SciPy on the compiled residual and Jacobian) — their
   held-out gap, evidence (2 ln B ≈ Δχ² − k ln n, BIC) and coefficients ± σ.
4. Stability: the linearised selection repeated on `BOOTSTRAP` block-bootstrap resamples
   of the training part's constant-input segments; the fraction whose pick contains every
   term of the subset.

Rating: **credible** (held-out gap at the noise floor as `assess` judges a library effect,
stable in ≥ 80 % of resamples, evidence ≥ 10), **tentative** (evidence ≥ 10 but not all of
that), **nothing found**.

What this slice does not yet do (issue 45): the network reference of what is achievable,
the vibration-table and noise-record term libraries, the designer's consequence (δK_a,
vibration error) and the exciting experiment, the held-out change times refitted with a
term (they stay at the nominal fit's: a term's held-out gain is understated, not inflated).
Float64.
"""

from __future__ import annotations

import itertools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from scipy.optimize import least_squares

from ..._data import NominalDevice
from ..._simulate.matrix import expm_minus_identity
from ..._simulate.sequence import N_STATES, SequenceInputs, _change_split, initial_state, loop_system
from ..._servo import time_constant
from .. import openworld
from .layout import W
from .model import moment_jumps, unpack
from .state import StepFit, StepRecord


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

MAX_TERMS = 2
CONFIRM = 3
BOOTSTRAP = 200
STABLE = 0.8
CREDIBLE_EVIDENCE = 10.0
TIE_BAND = 6.0
"""Subsets within this much extended BIC of the best are a tie (`cannot tell which term`)."""

CONFIRM_MAX_EVALUATIONS = 200


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


def _signals(x, drive, xdot, c_out, t, ideal_torquer, scales: Scales):
    """Every coefficient's signal at one sample: (moment (N_COEFFICIENTS,), pickoff (…),
    output (…)), each zero where the term does not enter there."""
    h, period = scales.half, scales.period
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


def term_record(params, dt, n: int, m: int, sequence: SequenceInputs, coefficients, scales):
    """U_out [V] of the loop with the terms' `coefficients` (N_COEFFICIENTS,): the means of
    `n` blocks of `m` samples (static). At zero coefficients, `linear_record`'s record."""
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
    coefficients = jnp.asarray(coefficients, dtype)
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
        xdot = a @ x + b * drive
        s_moment, s_pickoff, s_output = _signals(x, drive, xdot, c_out, time, ideal_torquer, scales)
        torque_now = torque(z)
        moment_force = (
            lead @ s_moment + (lagged_torque - torque_now)
            + lead_torquer * (torque_now - torque_before)
        )
        output = c_out @ x + feed * (lead @ s_pickoff) + lead @ s_output
        return jnp.stack([moment_force, lead @ s_pickoff]), output

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
    _, samples = jax.lax.scan(step, carry, (jnp.arange(total, dtype=dtype), entering))
    return samples.reshape(n, m).mean(axis=1)


# ----------------------------------------------------------------------------------------
# The record's model with terms, at the nominal fit
# ----------------------------------------------------------------------------------------


def _model(rec: StepRecord, nominal: NominalDevice, w: np.ndarray, free: np.ndarray, effects):
    """(prediction(θ, coefficients, scales) [V] of the record's blocks, penalties(θ)) with
    θ = [w's `free` entries, an output offset in units of `ctx.scale`]; w's other entries
    stay as given. The output offset is a nuisance of its own here (standard normal prior):
    with the nominal loop it is the external moment's double, with a nonlinear term it is
    not (a term acts on the deflection, not on the ADC's zero)."""
    ctx = rec.ctx
    n, m = len(rec.u_out), int(rec.block)
    base, prior_sigma = nominal.params, jnp.asarray(rec.prior_sigma)
    w_fixed = jnp.asarray(w)
    index = jnp.asarray(np.flatnonzero(free))

    def unpacked(theta):
        return unpack(w_fixed.at[index].set(theta[:-1]), 0, effects, base, prior_sigma, ctx)

    def prediction(theta, coefficients, scales):
        model = unpacked(theta)
        sequence = SequenceInputs(
            ctx.first_level, model.gain, model.moment, model.rate, model.dv, model.dw,
            ctx.change_index, model.step, model.shift, moment_jumps(model.params, ctx),
        )
        blocks = term_record(model.params, ctx.dt, n, m, sequence, coefficients, scales)
        return blocks + model.output_offset + ctx.scale * theta[-1]

    def penalties(theta):
        return jnp.concatenate([unpacked(theta).penalties, theta[-1:]])

    return prediction, penalties


PAD = 16
"""Zero-padding of the periodogram that finds the sinusoid's starting frequency."""


def _peak_frequency(residual: np.ndarray, block_dt: float) -> float:
    """ω [rad/s] of the largest line of the nominal residual's periodogram (block means,
    Hann taper, zero-padded `PAD`×), the lowest bins (the record's length) excluded."""
    r = residual - residual.mean()
    size = PAD * r.size
    spectrum = np.abs(np.fft.rfft(r * np.hanning(r.size), size)) ** 2
    spectrum[: 3 * PAD] = 0.0
    k = int(np.argmax(spectrum))
    return 2 * np.pi * k / (size * block_dt)


def _subsets():
    for k in range(1, MAX_TERMS + 1):
        yield from itertools.combinations(range(len(TERMS)), k)


MAX_COLUMNS = 2 * MAX_TERMS
"""Coefficient columns of a confirmed subset at most (a sinusoid has two)."""

_SINUSOID = next(i for i, t in enumerate(TERMS) if t.name == "forcing_sinusoid")


def _select(seg_gram, seg_rhs, pen_gram, pen_rhs, weights, n_free, n_train):
    """Every subset of ≤ `MAX_TERMS` terms scored on the linearised problem (normal
    equations summed over the training segments with `weights`, plus the priors'), best
    first: (extended BIC relative to the nominal fit, subset, Δχ², coefficients)."""
    gram = np.tensordot(weights, seg_gram, 1) + pen_gram
    rhs = np.tensordot(weights, seg_rhs, 1) + pen_rhs
    scale = np.sqrt(np.maximum(np.diag(gram), 1e-300))
    gram, rhs = gram / scale[:, None] / scale[None, :], rhs / scale

    def gain(cols):
        keep = list(range(n_free)) + [n_free + c for c in cols]
        try:
            theta = np.linalg.solve(gram[np.ix_(keep, keep)], rhs[keep])
        except np.linalg.LinAlgError:
            return None, None
        return float(rhs[keep] @ theta), theta[n_free:] / scale[[n_free + c for c in cols]]

    base, _ = gain([])
    if base is None:  # the nominal fit's own problem is singular: nothing to score against
        return []
    scored = []
    for subset in _subsets():
        cols = columns(subset)
        value, coef = gain(cols)
        if value is None:
            continue
        k = len(cols)
        ebic = -(value - base) + k * math.log(n_train) + 2 * math.log(
            math.comb(len(TERMS), len(subset))
        )
        scored.append((ebic, subset, value - base, coef))
    scored.sort(key=lambda item: item[0])
    return scored


def _least_squares(fun, jac, x0, args):
    """MINPACK's Levenberg–Marquardt (SciPy) on a compiled residual and Jacobian: its
    scaling by the Jacobian's column norms converges in tens of evaluations where the
    terms' coefficients and the nominal parameters differ in scale by 10⁴ (optimistix's
    unscaled Levenberg–Marquardt needed hundreds of steps here)."""
    return least_squares(
        lambda p: np.asarray(fun(jnp.asarray(p), args)),
        np.asarray(x0, dtype=np.float64),
        jac=lambda p: np.asarray(jac(jnp.asarray(p), args)),  # pyright: ignore[reportArgumentType]  # SciPy's stubs take a callable too
        method="lm",
        xtol=1e-10,
        ftol=1e-10,
        max_nfev=CONFIRM_MAX_EVALUATIONS,
    )


def discover(rec: StepRecord, nominal: NominalDevice, fit: StepFit, effects) -> dict:
    """The `discovery` block of an unexplained step record (see the module docstring), from
    its nominal fit `fit` (a `StepFit`, the nominal model's)."""
    n = len(rec.u_out)
    train = np.asarray(rec.ctx.train)[:n] > 0
    test = np.asarray(rec.ctx.test)[:n] > 0
    sigma = float(rec.sigma)
    w = np.asarray(fit.w, dtype=np.float64)
    omega = _peak_frequency(np.asarray(fit.error)[: rec.n], float(rec.dt))
    scales = Scales(
        half=jnp.asarray(float(rec.host.half)), period=jnp.asarray(float(rec.period)),
        duration=rec.ctx.duration, omega=jnp.asarray(omega),
    )
    zero = jnp.zeros(N_COEFFICIENTS)
    u_out = jnp.asarray(rec.u_out)

    # 1. Screen: the first-order effect of every parameter of w and of every coefficient.
    all_free = np.ones(w.size, bool)
    prediction_all, penalties_all = _model(rec, nominal, w, all_free, effects)
    theta_w = jnp.concatenate([jnp.asarray(w), jnp.zeros(1)])

    @jax.jit
    def linearised(theta):
        pred = prediction_all(theta, zero, scales)
        j_theta = jax.jacfwd(prediction_all, argnums=0)(theta, zero, scales)
        j_coef = jax.jacfwd(prediction_all, argnums=1)(theta, zero, scales)
        return pred, j_theta, j_coef, penalties_all(theta), jax.jacfwd(penalties_all)(theta)

    pred0, j_theta, j_coef, p0, j_pen = (np.asarray(v) for v in linearised(theta_w))
    # Free: every entry of w but the effect slot and those only the held-out part sees (its
    # segments' change times), and the output offset (the last of θ).
    # (An entry that neither part sees is free too: a change time the nominal fit pushed to
    # its clip has no derivative there, and only its prior brings it back.)
    seen_train = np.any(j_theta[train, :-1] != 0, axis=0)
    held_only = np.flatnonzero(np.any(j_theta[test, :-1] != 0, axis=0) & ~seen_train)
    free = np.ones(w.size, bool)
    free[held_only] = False
    free[W.EFFECT] = False
    keep = np.append(free, True)
    j_free, j_pen = j_theta[:, keep], j_pen[:, keep]
    n_free = j_free.shape[1]
    r0 = (np.asarray(rec.u_out) - pred0) / sigma
    x_all = np.concatenate([j_free, j_coef], axis=1) / sigma
    pen_x = np.concatenate([j_pen, np.zeros((j_pen.shape[0], N_COEFFICIENTS))], axis=1)

    # Per constant-input segment of the training part: its normal equations (the block
    # bootstrap reweights them).
    edges = np.unique(np.clip(np.r_[0, np.asarray(rec.change_block, dtype=int), rec.n], 0, rec.n))
    seg_gram, seg_rhs = [], []
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        rows = np.arange(lo, hi)
        rows = rows[train[rows]]
        if rows.size:
            seg_gram.append(x_all[rows].T @ x_all[rows])
            seg_rhs.append(x_all[rows].T @ r0[rows])
    seg_gram, seg_rhs = np.stack(seg_gram), np.stack(seg_rhs)
    pen_gram, pen_rhs = pen_x.T @ pen_x, -pen_x.T @ p0
    n_train = int(train.sum())

    # 2. Select.
    def select(weights):
        return _select(seg_gram, seg_rhs, pen_gram, pen_rhs, weights, n_free, n_train)

    ranked = select(np.ones(len(seg_gram)))
    rng = np.random.default_rng(0)
    picks = []
    for _ in range(BOOTSTRAP):
        counts = np.bincount(rng.integers(0, len(seg_gram), len(seg_gram)), minlength=len(seg_gram))
        best = select(counts.astype(np.float64))
        picks.append(best[0][1] if best and best[0][0] < 0 else ())

    # 3. Confirm: one compiled refit for every subset (its columns chosen by `pick`, a
    # (MAX_COLUMNS, N_COEFFICIENTS) selection; unused columns pinned at 0), the sinusoid's
    # frequency free in units of the record's frequency resolution.
    prediction, penalties = _model(rec, nominal, w, free, effects)
    train_j = jnp.asarray(train.astype(np.float64))
    resolution = 2 * jnp.pi / scales.duration

    def residuals(params, args):
        pick, used, tone = args
        theta, c, shift = params[:n_free], params[n_free:-1], params[-1]
        tuned = scales._replace(omega=scales.omega + resolution * shift)
        e = (u_out - prediction(theta, c @ pick, tuned)) * train_j / sigma
        pinned = jnp.concatenate([c * (1 - used), shift * (1 - tone)[None]])
        return jnp.concatenate([e, penalties(theta), pinned])

    residuals_at = jax.jit(residuals)
    jacobian_at = jax.jit(jax.jacfwd(residuals))

    @jax.jit
    def error_at(params, pick):
        tuned = scales._replace(omega=scales.omega + resolution * params[-1])
        return u_out - prediction(params[:n_free], params[n_free:-1] @ pick, tuned)

    # The held-out part's own nuisances (w's entries the training part does not see: the
    # change times of the held-out segments) refitted there with the terms, as the
    # diagnosis refits them for every library effect.
    held_index = jnp.asarray(held_only)
    test_j = jnp.asarray(test.astype(np.float64))

    def held_residuals(x, args):
        theta, coefficients, tuned = args
        w_full = jnp.asarray(w).at[jnp.asarray(np.flatnonzero(free))].set(theta[:-1])
        w_full = w_full.at[held_index].set(x)
        full = jnp.concatenate([w_full, theta[-1:]])
        e = (u_out - prediction_all(full, coefficients, tuned)) * test_j / sigma
        return jnp.concatenate([e, penalties_all(full)])

    held_at = jax.jit(held_residuals)
    held_jacobian_at = jax.jit(jax.jacfwd(held_residuals))

    def held_out_error(theta, coefficients, tuned):
        x = np.asarray(w)[held_only]
        args = (theta, coefficients, tuned)
        if held_only.size:
            x = _least_squares(held_at, held_jacobian_at, x, args).x
        w_full = jnp.asarray(w).at[jnp.asarray(np.flatnonzero(free))].set(theta[:-1])
        full = jnp.concatenate([w_full.at[held_index].set(jnp.asarray(x)), theta[-1:]])
        return u_out - prediction_all(full, coefficients, tuned)

    cost0 = float(np.sum(r0[train] ** 2) + np.sum(p0**2))
    test_rows = np.flatnonzero(test)
    gap_before = openworld.excess(float(np.mean((r0[test_rows] * sigma) ** 2)), sigma**2)
    confirmed = []
    chosen = [item for item in ranked[:CONFIRM] if item[0] < 0]
    # The single terms of a chosen pair are confirmed too: a pair can win the linearised
    # screen only because one term's start (a sinusoid's frequency) is off.
    singles = {item[1] for item in ranked if len(item[1]) == 1}
    wanted = {item[1] for item in chosen}
    for item in list(chosen):
        for i in item[1]:
            if (i,) not in wanted and (i,) in singles:
                wanted.add((i,))
                chosen.append(next(r for r in ranked if r[1] == (i,)))
    for ebic, subset, _, coef in chosen:
        cols = columns(subset)
        pick = np.zeros((MAX_COLUMNS, N_COEFFICIENTS))
        pick[np.arange(len(cols)), cols] = 1.0
        used = (np.arange(MAX_COLUMNS) < len(cols)).astype(np.float64)
        tone = np.asarray(float(_SINUSOID in subset))
        start = np.concatenate([np.asarray(theta_w)[keep], np.pad(coef, (0, MAX_COLUMNS - len(cols))), [0.0]])
        args = (jnp.asarray(pick), jnp.asarray(used), jnp.asarray(tone))
        # From the linearised estimate and from the nominal fit itself (the terms at 0):
        # the linearised estimate of a strong term can start in another basin.
        at_nominal = start.copy()
        at_nominal[n_free:] = 0.0
        solution = min(
            (_least_squares(residuals_at, jacobian_at, x0, args) for x0 in (start, at_nominal)),
            key=lambda sol: sol.cost,
        )
        params = solution.x
        r = residuals_at(jnp.asarray(params), args)
        jac = np.asarray(jacobian_at(jnp.asarray(params), args))
        error = np.asarray(error_at(jnp.asarray(params), args[0]))
        converged = solution.status > 0
        active = np.r_[np.ones(n_free, bool), used > 0, tone > 0]
        jac = jac[:, active]
        delta = cost0 - float(np.sum(np.asarray(r) ** 2))
        k = len(cols) + int(tone)
        chi2_train = float(np.sum((error[train] / sigma) ** 2))
        dof = max(n_train - jac.shape[1], 1)
        try:
            cov = np.linalg.inv(jac.T @ jac) * max(chi2_train / dof, 1.0)
        except np.linalg.LinAlgError:
            cov = np.full((jac.shape[1],) * 2, np.nan)
        std = np.sqrt(np.maximum(np.diag(cov)[n_free : n_free + len(cols)], 0.0))
        tuned = scales._replace(omega=scales.omega + resolution * params[-1])
        held_error = np.asarray(
            held_out_error(
                jnp.asarray(params[:n_free]), jnp.asarray(params[n_free:-1] @ pick), tuned
            )
        )
        gap_after = openworld.excess(float(np.mean(held_error[test_rows] ** 2)), sigma**2)
        names = [
            (TERMS[i], f" ({part})" if TERMS[i].width > 1 else "")
            for i in subset
            for part in (("sin", "cos") if TERMS[i].width > 1 else ("",))
        ]
        entry = {
            "terms": [TERMS[i].name for i in subset],
            "columns": [
                {
                    "term": term.name + part,
                    "place": term.place,
                    "family": term.family,
                    "formula": term.formula,
                    "coefficient": float(value),
                    "sigma": float(spread),
                }
                for (term, part), value, spread in zip(
                    names, params[n_free : n_free + len(cols)], std, strict=True
                )
            ],
            "evidence": float(delta - k * math.log(n_train)),
            "criterion": float(
                -delta + k * math.log(n_train) + 2 * math.log(math.comb(len(TERMS), len(subset)))
            ),
            "delta_chi2_train": float(delta),
            "ebic_linearised": float(ebic),
            "held_out_gap_before_V": gap_before,
            "held_out_gap_after_V": gap_after,
            "explained_fraction": openworld.explained_fraction(gap_before, gap_after),
            "held_out_at_floor": gap_after <= openworld.FLOOR_FACTOR * sigma,
            "stability": float(np.mean([set(subset) <= set(p) for p in picks])),
            "converged": bool(converged),
        }
        if tone > 0:
            entry["frequency_Hz"] = float((omega + float(resolution) * params[-1]) / (2 * np.pi))
        confirmed.append(entry)
    confirmed.sort(key=lambda d: d["criterion"])
    result = {
        "method": (
            f"{len(TERMS)} terms ({N_COEFFICIENTS} coefficients), subsets of ≤ {MAX_TERMS} by "
            f"the extended BIC (γ = 1) on the linearised fit; the best {CONFIRM} refitted in "
            "full (device, the record's nuisances, an output offset, the terms); evidence "
            f"2 ln B ≈ Δχ² − k ln n (BIC); stability over {BOOTSTRAP} block-bootstrap "
            "resamples of the training segments; the held-out change times as the nominal "
            "fit's"
        ),
        "sinusoid_start_Hz": omega / (2 * np.pi),
        "scales": {"half_V": float(rec.host.half), "period_s": float(rec.period)},
        "candidates": confirmed,
        "best": None,
        "tie": None,
        "rating": "nothing found",
    }
    if not confirmed:
        return result
    best = confirmed[0]
    credible = (
        best["evidence"] >= CREDIBLE_EVIDENCE
        and best["stability"] >= STABLE
        and best["held_out_at_floor"]
    )
    if best["evidence"] >= CREDIBLE_EVIDENCE:
        result["rating"] = "credible" if credible else "tentative"
        result["best"] = best
        ties = [d for d in confirmed[1:] if d["criterion"] - best["criterion"] < TIE_BAND]
        result["tie"] = ties[0] if ties else None
    return result
