"""Time-domain simulation of the closed-loop servo accelerometer (SPEC.md §1).

Two simulators of the same loop (`ServoParams` gives the equations):

- `simulate_linear`: the linear loop (no mechanical stops), discretised exactly for
  zero-order-held inputs (matrix exponential) and run with `jax.lax.scan`;
- `simulate_nonlinear`: the loop with the mechanical stops |l θ| ≤ h_max, solved with diffrax.

Both take the inputs as sequences on a uniform time grid, each sample held until the next
(zero-order hold), and return the sampled output voltage U_out(t_i). Both are jit-, vmap-
and grad-safe over the parameters and the inputs, including across T_dm = 0 and T_f = 0.

The ideal lags (T_dm = 0, T_f = 0) are singular limits of the lagged model: there the lag
states become dummies and the algebraic values are used instead. To make the derivative
with respect to T_dm (T_f) at exactly 0 the one-sided derivative of the lagged model, the
ideal branch keeps the first-order singular-perturbation terms in T_dm (T_f); they are
zero in value at T = 0 and only carry the derivative.
"""

from __future__ import annotations

import math
from typing import Literal

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray

from ._checks import check_uniform_grid
from ._params import ServoParams, _concrete, _shown
from ._servo import feedback_stiffness, loop_stiffness, time_constant

_STATE_NAMES = ("θ [rad]", "θ' [rad/s]", "M_dm [N·m]", "U_f [V]")

# Shapes (n samples, 4 states, 3 inputs), named once here for the signatures below.
_Samples = Float[Array, " n"]
_SampleTimes = Float[ArrayLike, " n"]
_SampleInput = Float[ArrayLike, " n"] | float
_State = Float[Array, " 4"]
_StateLike = Float[ArrayLike, " 4"]
_States = Float[Array, "n 4"]
_StateMatrix = Float[Array, "4 4"]
_InputMatrix = Float[Array, "4 3"]
_OutputMatrix = Float[Array, "1 4"]
_FeedthroughMatrix = Float[Array, "1 3"]


# --------------------------------------------------------------------------------------
# Linear model
# --------------------------------------------------------------------------------------


def _is_zero_and_reciprocal(value):
    # The "double where": the reciprocal is computed from a value that is never 0, so that
    # neither the primal nor the gradient of the unselected branch is inf/NaN at value = 0.
    is_zero = value == 0
    safe = jnp.where(is_zero, jnp.ones_like(value), value)
    return is_zero, jnp.where(is_zero, jnp.zeros_like(value), 1 / safe)


def _pickoff_amplifier_per_radian(params: ServoParams):
    """k_dp·k_y·l [V/rad]: U_amp per radian of deflection."""
    return params.pickoff_gain * params.amplifier_gain * params.pendulum_length


def state_space(
    params: ServoParams,
) -> tuple[_StateMatrix, _InputMatrix, _OutputMatrix, _FeedthroughMatrix]:
    """The closed loop as a continuous-time linear state-space system (no mechanical stops).

        x' = A x + B u,     U_out = C x + D u   (noise-free)

    with state x = [θ, θ', M_dm, U_f] and input u = [U_test, a, M_ext], from

        J θ'' + μ θ' + c θ = m l a + M_ext + M_dm
        T_dm M_dm' = k_dm (U_test − U_amp) − M_dm,    U_amp = k_dp k_y l θ
        T_f U_f' = U_amp − U_f,                       U_out = U_f.

    Its transfer functions are SPEC.md eq. (1) (`transfer_function`) and
    `transfer_function_test_signal`, each followed by 1/(T_f p + 1).

    The ideal lags are handled without branching on values (so that the matrices are
    vmappable and differentiable across them):

    - T_dm = 0: M_dm = k_dm (U_test − U_amp) algebraically. The row of M_dm is zero (the
      state is a dummy) and the algebraic moment enters the θ'' row. The second state is
      then θ' + T_dm k_dm U_test / J (equal to θ' in value), and the first-order terms in
      T_dm of the reduced (singularly perturbed) loop are kept; they vanish at T_dm = 0 but
      make the derivative with respect to T_dm there the one-sided derivative of the lagged
      loop.
    - T_f = 0: U_out = U_amp. The row of U_f is zero (a dummy state) and C reads
      U_amp − T_f dU_amp/dt (again the first-order term only carries the derivative).

    **Arguments:**

    - `params`: the device, a `ServoParams` (SI units).

    **Returns:**

    `(A, B, C, D)` with shapes (4, 4), (4, 3), (1, 4), (1, 3), in SI units: states in
    rad, rad/s, N·m, V; inputs in V, m/s², N·m; output in V.
    """
    p = params
    inertia = p.moment_of_inertia
    gain = _pickoff_amplifier_per_radian(p)
    torquer = p.torquer_gain
    feedback = feedback_stiffness(p)
    tdm = p.torquer_time_constant
    tf = p.filter_time_constant
    ideal_torquer, inv_tdm = _is_zero_and_reciprocal(tdm)
    no_filter, inv_tf = _is_zero_and_reciprocal(tf)
    zero = jnp.zeros_like(inertia * gain * tdm * tf)
    one = zero + 1

    def matrix(rows):
        return jnp.stack([jnp.stack([zero + entry for entry in row]) for row in rows])

    pendulosity = p.pendulum_mass * p.pendulum_length
    # Lagged torquer: M_dm is a state.
    a_lagged = matrix(
        [
            [zero, one, zero, zero],
            [-p.stiffness / inertia, -p.damping / inertia, 1 / inertia, zero],
            [-feedback * inv_tdm, zero, -inv_tdm, zero],
            [zero, zero, zero, zero],
        ]
    )
    b_lagged = matrix(
        [
            [zero, zero, zero],
            [zero, pendulosity / inertia, 1 / inertia],
            [torquer * inv_tdm, zero, zero],
            [zero, zero, zero],
        ]
    )
    # Ideal torquer. Reduced loop to first order in T_dm (slow manifold of the lag):
    # M_dm = k_dm (U_test − U_amp) + T_dm k_dm k_dp k_y l θ'; and a step ΔU_test at a
    # sample time costs the momentum T_dm k_dm ΔU_test (the lag's initial layer), which
    # the variable ω̃ = θ' + T_dm k_dm U_test / J absorbs, so ω̃ stays continuous.
    shift = tdm * torquer / inertia  # θ' = ω̃ − shift·U_test
    velocity_coefficient = (-p.damping + tdm * feedback) / inertia
    a_ideal = matrix(
        [
            [zero, one, zero, zero],
            [-loop_stiffness(p) / inertia, velocity_coefficient, zero, zero],
            [zero, zero, zero, zero],
            [zero, zero, zero, zero],
        ]
    )
    b_ideal = matrix(
        [
            [-shift, zero, zero],
            [torquer / inertia - velocity_coefficient * shift, pendulosity / inertia, 1 / inertia],
            [zero, zero, zero],
            [zero, zero, zero],
        ]
    )
    a_matrix = jnp.where(ideal_torquer, a_ideal, a_lagged)
    b_matrix = jnp.where(ideal_torquer, b_ideal, b_lagged)

    # Output filter. Lagged: U_f is a state; ideal: U_out = U_amp − T_f dU_amp/dt.
    filter_row = matrix([[gain * inv_tf, zero, zero, -inv_tf]])[0]
    a_matrix = a_matrix.at[3].set(jnp.where(no_filter, zero, filter_row))
    velocity_shift = jnp.where(ideal_torquer, shift, zero)
    c_ideal = matrix([[gain, -tf * gain, zero, zero]])
    d_ideal = matrix([[tf * gain * velocity_shift, zero, zero]])
    c_matrix = jnp.where(no_filter, c_ideal, matrix([[zero, zero, zero, one]]))
    d_matrix = jnp.where(no_filter, d_ideal, matrix([[zero, zero, zero]]))
    return a_matrix, b_matrix, c_matrix, d_matrix


def discretise(a_matrix: Array, b_matrix: Array, dt: ArrayLike) -> tuple[Array, Array]:
    """Exact zero-order-hold discretisation of x' = A x + B u.

    With u held constant over each step of length dt, x_{k+1} = A_d x_k + B_d u_k where
    A_d = e^{A dt} and B_d = ∫_0^dt e^{A s} ds B, both read off the exponential of the
    augmented matrix [[A, B], [0, 0]]·dt (Van Loan).

    **Arguments:**

    - `a_matrix`: A, shape (n, n) [1/s].
    - `b_matrix`: B, shape (n, m) [state units/(input units·s)].
    - `dt`: the step [s].

    **Returns:**

    `(A_d, B_d)`, shapes (n, n) and (n, m).
    """
    n_states, n_inputs = b_matrix.shape
    augmented = jnp.concatenate(
        [
            jnp.concatenate([a_matrix, b_matrix], axis=1),
            jnp.zeros((n_inputs, n_states + n_inputs), dtype=b_matrix.dtype),
        ],
        axis=0,
    )
    # Lags far shorter than dt (T_dm → 0) make ‖A dt‖ huge: allow the squarings they need
    # (the default 16 returns NaN beyond ‖A dt‖ ≈ 3.5e5).
    exponential = jax.scipy.linalg.expm(augmented * dt, max_squarings=64)
    return exponential[:n_states, :n_states], exponential[:n_states, n_states:]


# --------------------------------------------------------------------------------------
# Equilibrium
# --------------------------------------------------------------------------------------


def _stop_angle(params: ServoParams):
    """θ_max = h_max / l [rad]."""
    return params.stop_displacement / params.pendulum_length


def equilibrium_state(
    params: ServoParams,
    test_voltage: ArrayLike = 0.0,
    acceleration: ArrayLike = 0.0,
    external_moment: ArrayLike | None = None,
    *,
    stops: bool = False,
    stop_stiffness_ratio: ArrayLike = 1e4,
) -> _State:
    """The state at rest under constant inputs.

    (c + k_dm l k_dp k_y) θ = k_dm U_test + m l a + M_ext, θ' = 0,
    M_dm = k_dm (U_test − U_amp), U_f = U_amp = k_dp k_y l θ. With `stops=True` and θ beyond
    a stop, the stop's contact stiffness K_s (see `simulate_nonlinear`) balances the excess:
    θ = (K θ_free ± K_s θ_max)/(K + K_s), K = c + k_dm l k_dp k_y.

    **Arguments:**

    - `params`: the device, a `ServoParams`.
    - `test_voltage`: U_test [V].
    - `acceleration`: a [m/s²].
    - `external_moment`: M_ext [N·m]; `None` means `params.external_moment`.
    - `stops`: whether to include the mechanical stops (as in `simulate_nonlinear`).
    - `stop_stiffness_ratio`: K_s / (c + k_dm l k_dp k_y), as in `simulate_nonlinear`.

    **Returns:**

    The state [θ, θ', M_dm, U_f] [rad, rad/s, N·m, V], shape (4,).
    """
    if external_moment is None:
        external_moment = params.external_moment
    stiffness = loop_stiffness(params)
    drive = (
        params.torquer_gain * test_voltage
        + params.pendulum_mass * params.pendulum_length * acceleration
        + external_moment
    )
    theta = drive / stiffness
    if stops:
        theta_max = _stop_angle(params)
        contact = stop_stiffness_ratio * stiffness
        above = (stiffness * theta + contact * theta_max) / (stiffness + contact)
        below = (stiffness * theta - contact * theta_max) / (stiffness + contact)
        theta = jnp.where(theta > theta_max, above, jnp.where(theta < -theta_max, below, theta))
    theta = jnp.asarray(theta)
    gain = _pickoff_amplifier_per_radian(params)
    amplifier = gain * theta
    moment = params.torquer_gain * (test_voltage - amplifier)
    return jnp.stack(jnp.broadcast_arrays(theta, jnp.zeros_like(theta), moment, amplifier))


# --------------------------------------------------------------------------------------
# Shared input handling
# --------------------------------------------------------------------------------------


def _common_dtype(params: ServoParams, *values):
    leaves = [leaf for leaf in jax.tree_util.tree_leaves(params) if eqx.is_array_like(leaf)]
    # `float` is weakly typed: it only promotes integers (to JAX's default float).
    return jnp.result_type(float, *leaves, *[v for v in values if v is not None])


def _prepare(params, ts, test_voltage, acceleration, external_moment, initial_state):
    """Validates shapes and returns the arrays in one floating dtype."""
    if not isinstance(params, ServoParams):
        raise ValueError(f"params must be a ServoParams, got {type(params).__name__}.")
    if external_moment is None:
        external_moment = params.external_moment
    ts = jnp.asarray(ts)
    if ts.ndim != 1 or ts.shape[0] < 2:
        raise ValueError(
            f"ts must be a 1-D time grid with at least 2 samples; got shape {ts.shape}."
        )
    n = ts.shape[0]
    dtype = _common_dtype(params, ts, test_voltage, acceleration, external_moment)
    ts = ts.astype(dtype)
    check_uniform_grid(
        ts,
        "the simulators (each input sample is held for one step)",
        "Resample the inputs onto a uniform grid.",
    )

    def sequence(value, name, unit):
        concrete = _concrete(value)  # None under jit/vmap: nothing to check there
        if concrete is not None and not np.all(np.isfinite(concrete)):
            bad = np.flatnonzero(~np.isfinite(concrete.ravel()))[0]
            where = "" if concrete.ndim == 0 else f" (sample {bad})"
            raise ValueError(
                f"{name} must be finite, got {_shown(concrete.ravel()[bad])} {unit}{where}."
            )
        value = jnp.asarray(value, dtype=dtype)
        if value.ndim == 0:
            return jnp.broadcast_to(value, (n,))
        if value.shape != (n,):
            raise ValueError(
                f"{name} must be a scalar or have the shape of ts ({n},); got shape "
                f"{value.shape}. Give one sample [{unit}] per time in ts."
            )
        return value

    inputs = jnp.stack(
        [
            sequence(test_voltage, "test_voltage", "V"),
            sequence(acceleration, "acceleration", "m/s²"),
            sequence(external_moment, "external_moment", "N·m"),
        ],
        axis=1,
    )
    if initial_state is not None:
        initial_state = jnp.asarray(initial_state, dtype=dtype)
        if initial_state.shape != (4,):
            raise ValueError(
                f"initial_state must have shape (4,) for {list(_STATE_NAMES)}; got shape "
                f"{initial_state.shape}."
            )
    return ts, inputs, initial_state, dtype


class _Scaling(eqx.Module):
    """Internal O(1) units: θ in θ_max, θ' in θ_max/T, M in K·θ_max, U in volts; inputs
    U_test in volts, a in K·θ_max/(m l), M_ext in K·θ_max (K the loop stiffness)."""

    state: Array
    inputs: Array

    def __init__(self, params: ServoParams):
        theta_max = _stop_angle(params)
        stiffness = loop_stiffness(params)
        moment = stiffness * theta_max
        one = jnp.ones_like(moment)
        self.state = jnp.stack([theta_max, theta_max / time_constant(params), moment, one])
        pendulosity = params.pendulum_mass * params.pendulum_length
        self.inputs = jnp.stack([one, moment / pendulosity, moment])


class _Loop(eqx.Module):
    """The linear loop in internal units, and the maps to and from the physical state."""

    a_matrix: Array  # scaled A [1/s]
    b_matrix: Array  # scaled B [1/s]
    scaling: _Scaling
    ideal_torquer: Array
    ideal_filter: Array
    torquer_time_constant: Array
    filter_time_constant: Array
    torquer_gain: Array
    inertia: Array
    gain: Array
    feedback: Array

    def __init__(self, params: ServoParams):
        a_matrix, b_matrix, _, _ = state_space(params)
        self.scaling = scaling = _Scaling(params)
        self.a_matrix = a_matrix * scaling.state[None, :] / scaling.state[:, None]
        self.b_matrix = b_matrix * scaling.inputs[None, :] / scaling.state[:, None]
        self.torquer_time_constant = params.torquer_time_constant
        self.filter_time_constant = params.filter_time_constant
        self.ideal_torquer = params.torquer_time_constant == 0
        self.ideal_filter = params.filter_time_constant == 0
        self.torquer_gain = params.torquer_gain
        self.inertia = params.moment_of_inertia
        self.gain = _pickoff_amplifier_per_radian(params)
        self.feedback = feedback_stiffness(params)

    def velocity_shift(self, torquer_drive):
        """ω̃ − θ' [rad/s] of the ideal-torquer branch, for a torquer drive k_dm U_test."""
        shift = self.torquer_time_constant * torquer_drive / self.inertia
        return jnp.where(self.ideal_torquer, shift, jnp.zeros_like(shift))

    def scaled_inputs(self, inputs):
        return inputs / self.scaling.inputs

    def to_internal(self, state):
        """Physical initial state → internal scaled state. With an ideal torquer the
        initial M_dm is read as the moment just before t_0, k_dm U_test(t_0⁻) − k_dm U_amp:
        the drive before t_0 sets the initial-layer momentum (zero at equilibrium)."""
        theta, velocity, moment, filtered = state
        drive_before = moment + self.feedback * theta
        internal = jnp.stack(
            [theta, velocity + self.velocity_shift(drive_before), moment, filtered]
        )
        return internal / self.scaling.state

    def to_physical(self, internal, drive_before):
        """Internal scaled states (n, 4) at t_i → physical states, taken just before the
        sample u_i acts (the left limits; that is what the lagged model tends to).

        `drive_before`: k_dm U_test(t_i⁻) [N·m], shape (n,)."""
        theta, omega_tilde, moment, filtered = (internal * self.scaling.state).T
        velocity = omega_tilde - self.velocity_shift(drive_before)
        algebraic_moment = (
            drive_before
            - self.feedback * theta
            + self.torquer_time_constant * self.feedback * velocity
        )
        moment = jnp.where(self.ideal_torquer, algebraic_moment, moment)
        amplifier = self.gain * (theta - self.filter_time_constant * velocity)
        filtered = jnp.where(self.ideal_filter, amplifier, filtered)
        return jnp.stack([theta, velocity, moment, filtered], axis=1)


def _drive_before(loop: _Loop, inputs, initial_state):
    """k_dm U_test(t_i⁻): the previous test-voltage sample; before t_0, from the state."""
    theta0, _, moment0, _ = initial_state
    first = moment0 + loop.feedback * theta0
    return jnp.concatenate([first[None], loop.torquer_gain * inputs[:-1, 0]])


def _grid_step(ts):
    # The mean spacing: equal to ts[1] − ts[0] on a uniform grid, and the better estimate
    # when the grid times carry rounding (float32).
    return (ts[-1] - ts[0]) / (ts.shape[0] - 1)


def _add_noise(params, outputs, key):
    if key is None:
        return outputs
    noise = jax.random.normal(key, outputs.shape, dtype=outputs.dtype)
    return outputs + params.noise_std * noise


# --------------------------------------------------------------------------------------
# Linear simulator
# --------------------------------------------------------------------------------------


@eqx.filter_jit
def _simulate_linear(params, ts, inputs, initial_state):
    loop = _Loop(params)
    ad, bd = discretise(loop.a_matrix, loop.b_matrix, _grid_step(ts))
    forcing = loop.scaled_inputs(inputs) @ bd.T

    def step(state, force):
        return ad @ state + force, state

    _, internal = jax.lax.scan(step, loop.to_internal(initial_state), forcing)
    return loop.to_physical(internal, _drive_before(loop, inputs, initial_state))


def simulate_linear(
    params: ServoParams,
    ts: _SampleTimes,
    test_voltage: _SampleInput,
    acceleration: _SampleInput = 0.0,
    external_moment: _SampleInput | None = None,
    *,
    key: PRNGKeyArray | None = None,
    initial_state: _StateLike | None = None,
    return_states: bool = False,
) -> _Samples | tuple[_Samples, _States]:
    """Sampled output of the linear closed loop (no mechanical stops), exactly discretised.

    Solves the loop of `state_space` for inputs held constant between samples (zero-order
    hold: sample i acts on [t_i, t_{i+1})) by the exact discretisation `discretise` and
    `jax.lax.scan`: the only errors are rounding. The output is

        U_out(t_i) = U_f(t_i) + ε w_i,   w_i ~ N(0, 1) i.i.d. (only when `key` is given).

    **Arguments:**

    - `params`: the device, a `ServoParams` (SI units).
    - `ts`: uniform sample times [s], shape (n,), n ≥ 2. Checked to be uniform when
        concrete (`ValueError` otherwise); under jit it is assumed uniform, with step
        (ts[-1] − ts[0])/(n − 1).
    - `test_voltage`: U_test [V], shape (n,) or a scalar (constant).
    - `acceleration`: a [m/s²], shape (n,) or a scalar. Default 0.
    - `external_moment`: M_ext [N·m], shape (n,) or a scalar; `None` (default) means the
        constant `params.external_moment`.
    - `key`: a JAX PRNG key for the output noise ε = `params.noise_std`; `None` for none.
    - `initial_state`: [θ, θ', M_dm, U_f] [rad, rad/s, N·m, V] at t_0 (before U_test(t_0)
        acts). `None` (default): the settled device, `equilibrium_state` with zero test
        voltage and the first samples of acceleration and external moment. With
        T_dm = 0 (T_f = 0) the M_dm (U_f) entry is the value just before t_0.
    - `return_states`: also return the states.

    **Returns:**

    U_out at ts [V], shape (n,); with `return_states=True`, `(U_out, states)` with states
    [θ, θ', M_dm, U_f] at ts, shape (n, 4) (at a sample time, the value just before that
    input sample acts; with T_dm = 0, M_dm is the algebraic torquer moment, with T_f = 0,
    U_f = U_amp).
    """
    ts, inputs, initial_state, _ = _prepare(
        params, ts, test_voltage, acceleration, external_moment, initial_state
    )
    if initial_state is None:
        initial_state = equilibrium_state(params, 0.0, inputs[0, 1], inputs[0, 2])
    states = _simulate_linear(params, ts, inputs, initial_state.astype(inputs.dtype))
    outputs = _add_noise(params, states[:, 3], key)
    return (outputs, states) if return_states else outputs


# --------------------------------------------------------------------------------------
# Nonlinear simulator (mechanical stops)
# --------------------------------------------------------------------------------------


def _default_max_steps(n_samples: int) -> int:
    # One step per sample interval at least (the inputs jump at every sample); the lag and
    # the stiff stop contact need a few more per sample while they are excited; and a
    # margin for the rejected steps that locate each stop contact.
    return 16 * n_samples + 4096


class _HeldInputPath(diffrax.AbstractPath):
    """X(t) = ∫_{t_0}^t u(s) ds for the zero-order-held samples u_i (held on [t_i, t_{i+1})).

    Driving the loop through dX rather than through u(t) makes the input independent of the
    stage times of the solver (some implicit Runge–Kutta methods, e.g. Kvaerno5, evaluate
    stages beyond the end of the step, which would read the next sample).
    """

    ts: Array
    samples: Array  # (n, m)

    @property
    def t0(self):
        return self.ts[0]

    @property
    def t1(self):
        return self.ts[-1]

    def _index(self, t):
        # The last sample never acts inside [t_0, t_{n-1}].
        return jnp.clip(jnp.searchsorted(self.ts, t, side="right") - 1, 0, self.ts.shape[0] - 2)

    def evaluate(self, t0, t1=None, left=True):
        del left
        if t1 is None:
            index = self._index(t0)
            step = self.ts[1:] - self.ts[:-1]
            cumulative = jnp.concatenate(
                [jnp.zeros_like(self.samples[:1]), jnp.cumsum(self.samples[:-1] * step[:, None], 0)]
            )
            return cumulative[index] + self.samples[index] * (t0 - self.ts[index])
        # The controller never lets a step straddle a sample time (jump_ts=ts), so one
        # sample acts over the whole step; it is the one at the step's midpoint. Computing
        # u_i·(t1 − t0) directly avoids the cancellation of X(t1) − X(t0).
        index = self._index(t0 + 0.5 * (t1 - t0))
        return self.samples[index] * (t1 - t0)

    def derivative(self, t, left=True):
        del left
        return self.samples[self._index(t)]


def _stop_moment(y, contact_rate, contact_damping):
    """M_stop/J in internal units, with the velocity term on ω̃ (see `_input_matrix`)."""
    # In units of θ_max and θ_max/T the stops are at ±1, and M_stop/J becomes
    # −(K_s T/J)(θ − 1)_+ − (D_s/J) θ' while in contact (and symmetrically).
    theta = y[0]
    above = theta - 1
    below = -1 - theta
    in_contact = (above > 0) | (below > 0)
    spring = contact_rate * (jnp.maximum(above, 0) - jnp.maximum(below, 0))
    dashpot = jnp.where(in_contact, contact_damping * y[1], 0)
    return -spring - dashpot, in_contact


@eqx.filter_jit
def _simulate_nonlinear(
    params,
    ts,
    inputs,
    initial_state,
    stop_stiffness_ratio,
    rtol,
    atol,
    *,
    stops,
    max_steps,
    solver,
    throw,
    constant_inputs=False,
):
    loop = _Loop(params)
    period = time_constant(params)
    # K_s = r·K, so K_s T/J = r/T; critical damping D_s = 2 sqrt(K_s J): D_s/J = 2 sqrt(r)/T.
    contact_rate = stop_stiffness_ratio / period
    contact_damping = 2 * jnp.sqrt(stop_stiffness_ratio) / period
    # With an ideal torquer the second state is ω̃ = θ' + shift·U_test: the dashpot acts
    # on θ', so its −D_s·shift·U_test part enters with the input.
    shift_per_input = (
        loop.velocity_shift(params.torquer_gain * loop.scaling.inputs[0]) / loop.scaling.state[1]
    )
    args = (loop.a_matrix, loop.b_matrix, contact_rate, contact_damping, shift_per_input)

    def drift(t, y, args):
        a_matrix, _, contact_rate, contact_damping, _ = args
        dy = a_matrix @ y
        if stops:
            moment, _ = _stop_moment(y, contact_rate, contact_damping)
            dy = dy.at[1].add(moment)
        return dy

    def input_matrix(t, y, args):
        _, b_matrix, contact_rate, contact_damping, shift_per_input = args
        if stops:
            _, in_contact = _stop_moment(y, contact_rate, contact_damping)
            correction = jnp.where(in_contact, contact_damping * shift_per_input, 0)
            b_matrix = b_matrix.at[1, 0].add(correction)
        return b_matrix

    if constant_inputs:
        # Inputs constant over the record: one smooth vector field, so the steps need not
        # stop at every sample; the solver's dense output gives the samples (as solve_ivp's
        # t_eval does). Same ODE as the held path below, far fewer steps where it is smooth.
        held = loop.scaled_inputs(inputs)[0]

        def vector_field(t, y, args):
            return drift(t, y, args) + input_matrix(t, y, args) @ held

        terms = diffrax.ODETerm(vector_field)
        controller = diffrax.PIDController(rtol=rtol, atol=atol)
    else:
        terms = diffrax.MultiTerm(
            diffrax.ODETerm(drift),
            diffrax.ControlTerm(input_matrix, _HeldInputPath(ts, loop.scaled_inputs(inputs))),
        )
        controller = diffrax.ClipStepSizeController(
            diffrax.PIDController(rtol=rtol, atol=atol), jump_ts=ts
        )
    solution = diffrax.diffeqsolve(
        terms,
        solver,
        t0=ts[0],
        t1=ts[-1],
        dt0=_grid_step(ts),
        y0=loop.to_internal(initial_state),
        args=args,
        saveat=diffrax.SaveAt(ts=ts),
        stepsize_controller=controller,
        max_steps=max_steps,
        throw=throw,
    )
    states = loop.to_physical(solution.ys, _drive_before(loop, inputs, initial_state))
    failed = solution.result != diffrax.RESULTS.successful
    states = jnp.where(failed, jnp.nan, states)
    return states, solution.stats["num_steps"]


def simulate_nonlinear(
    params: ServoParams,
    ts: _SampleTimes,
    test_voltage: _SampleInput,
    acceleration: _SampleInput = 0.0,
    external_moment: _SampleInput | None = None,
    *,
    key: PRNGKeyArray | None = None,
    initial_state: _StateLike | None = None,
    stops: bool = True,
    stop_stiffness_ratio: ArrayLike = 1e4,
    rtol: float = 1e-10,
    atol: float = 1e-10,
    max_steps: int | None = None,
    solver: diffrax.AbstractSolver | None = None,
    throw: bool = True,
    return_states: bool = False,
) -> _Samples | tuple[_Samples, _States]:
    """Sampled output of the closed loop with mechanical stops, solved with diffrax.

    The loop of `state_space` plus the stops |l θ| ≤ h_max, θ_max = h_max / l, modelled
    as a stiff one-sided inelastic (spring–dashpot) contact in the moment balance:

        J θ'' + μ θ' + c θ = m l a + M_ext + M_dm + M_stop(θ, θ'),
        M_stop = −K_s (θ − θ_max)_+ − D_s θ' [θ > θ_max]
                 + K_s (−θ_max − θ)_+ − D_s θ' [θ < −θ_max],

    K_s = r (c + k_dm l k_dp k_y) (r = `stop_stiffness_ratio`), D_s = 2 sqrt(K_s J)
    (critically damped: the pendulum does not rebound). A loop pushing with the free
    deflection θ_free beyond the stop rests at θ = θ_max + (θ_free − θ_max)/(1 + r): with
    r = 1e4 on the reference device at ±5 V test voltage the penetration is ≈ 2.6e-5 of
    h_max, so the stopped output is k_dp k_y h_max to that accuracy.

    The inputs are piecewise constant (sample i held on [t_i, t_{i+1})): the solver steps
    onto every sample time (`ClipStepSizeController(jump_ts=ts)`) and saves at ts. When every
    input is a scalar (constant over the record, e.g. a test-voltage step from rest), the
    vector field is smooth between contacts and the steps are left to the error control;
    the samples come from the solver's dense output (about 6x fewer right-hand-side
    evaluations on a stop record, at the same tolerance). The state
    is solved in O(1) units (θ in θ_max, θ' in θ_max/T with T = sqrt(J/(c + k_dm l k_dp k_y)),
    M_dm in (c + k_dm l k_dp k_y)·θ_max, U_f in volts), so `rtol` and `atol` are relative
    to the stop angle. With `stops=False`, or when the stops are not reached, it solves the
    same linear loop as `simulate_linear` (they agree to ~1e-13 relative in float64 on the
    per-sample path, to ~1e-10 — the default tolerance — on the adaptive path).

    Gradients: exact (to the solver tolerance) for records that do not reach the stops,
    and for the output settled on a stop. Across the impact itself they are not: the
    dashpot switches on discontinuously, and differentiating the discretised solve
    misses the resulting jump of the sensitivities (errors of a few % for a functional
    spanning the impact).

    **Arguments:**

    - `params`, `ts`, `test_voltage`, `acceleration`, `external_moment`, `key`,
        `return_states`: as in `simulate_linear`.
    - `initial_state`: as in `simulate_linear`; `None` (default) is the equilibrium with
        zero test voltage, including the stops when `stops=True`.
    - `stops`: include the mechanical stops (a Python bool).
    - `stop_stiffness_ratio`: r = K_s / (c + k_dm l k_dp k_y), dimensionless.
    - `rtol`, `atol`: tolerances of the adaptive step-size controller (on the scaled state).
    - `max_steps`: maximum number of solver steps (a Python int); `None` (default) allows
        16 per sample plus 4096 (a 5 ms record at 1 MHz hitting the stops takes ≈ 5200).
    - `solver`: a diffrax solver; `None` (default) is `diffrax.Tsit5()`. The contact
        (eigenvalues ≈ sqrt(r)/T) and lags T_dm, T_f down to ~1e-7 s cost it a few
        steps per µs at most. Lags far shorter than the sample period are stiff: use
        T = 0 (exact), or an implicit solver such as `diffrax.Kvaerno5()` (fine for tiny
        T_dm without contact; its Newton iteration does not converge across the
        dashpot's switch-on, so avoid it when the stops are hit).
    - `throw`: if the solve fails (e.g. `max_steps` reached), raise diffrax's error (an
        `EqxRuntimeError` naming the cause). With `throw=False` a failed record is
        returned as NaN instead (for batch sweeps: mask per element).

    **Returns:**

    As `simulate_linear`: U_out at ts [V], shape (n,); with `return_states=True`,
    `(U_out, states)`, states shape (n, 4).
    """
    ts, inputs, initial_state, dtype = _prepare(
        params, ts, test_voltage, acceleration, external_moment, initial_state
    )
    if not isinstance(stops, bool):
        raise ValueError(f"stops must be a Python bool, got {stops!r}.")
    n = ts.shape[0]
    if max_steps is None:
        max_steps = _default_max_steps(n)
    elif not (isinstance(max_steps, int) and max_steps > 0):
        raise ValueError(f"max_steps must be a positive int or None, got {max_steps!r}.")
    if solver is None:
        solver = diffrax.Tsit5()
    if initial_state is None:
        initial_state = equilibrium_state(
            params,
            0.0,
            inputs[0, 1],
            inputs[0, 2],
            stops=stops,
            stop_stiffness_ratio=stop_stiffness_ratio,
        )
    # Scalar inputs (static shapes, so also under jit/vmap) are constant over the record.
    constant = all(
        jnp.ndim(x) == 0 for x in (test_voltage, acceleration, external_moment) if x is not None
    )
    states, _ = _simulate_nonlinear(
        params,
        ts,
        inputs,
        initial_state.astype(dtype),
        jnp.asarray(stop_stiffness_ratio, dtype=dtype),
        rtol,
        atol,
        stops=stops,
        max_steps=max_steps,
        solver=solver,
        throw=throw,
        constant_inputs=constant,
    )
    outputs = _add_noise(params, states[:, 3], key)
    return (outputs, states) if return_states else outputs


# --------------------------------------------------------------------------------------
# Step response
# --------------------------------------------------------------------------------------


def step_response(
    params: ServoParams,
    duration: float,
    sample_rate: float,
    test_voltage: ArrayLike = 1.0,
    *,
    method: Literal["linear", "nonlinear"] = "linear",
    key: PRNGKeyArray | None = None,
    **kwargs,
) -> tuple[_Samples, _Samples]:
    """Response of the output to a constant test voltage switched on at t_0 = 0.

    The device starts settled (the default initial state: equilibrium with zero test
    voltage, under `params.external_moment` and zero acceleration), and U_test is applied
    from t_0 on: the record of SPEC.md §1's identification (step 1).

    **Arguments:**

    - `params`: the device, a `ServoParams`.
    - `duration`: record length [s], a positive Python number.
    - `sample_rate`: [Hz], a positive Python number; n = round(duration·sample_rate) + 1
        samples at ts = arange(n)/sample_rate.
    - `test_voltage`: the constant U_test [V].
    - `method`: `"linear"` (`simulate_linear`) or `"nonlinear"` (`simulate_nonlinear`,
        with the stops).
    - `key`: PRNG key for the output noise, or `None`.
    - `**kwargs`: passed on to the simulator (e.g. `acceleration`, `external_moment`,
        `stops`, `rtol`).

    **Returns:**

    `(ts, u_out)`: sample times [s] and output [V], both shape (n,).
    """
    for name, value in (("duration", duration), ("sample_rate", sample_rate)):
        if (
            isinstance(value, bool)
            or not isinstance(value, (int, float, np.integer, np.floating))
            or not math.isfinite(value)
            or value <= 0
        ):
            raise ValueError(
                f"{name} must be a positive finite Python number, got {value!r}"
                f"{' s' if name == 'duration' else ' Hz'}."
            )
    if method not in ("linear", "nonlinear"):
        raise ValueError(f"method must be 'linear' or 'nonlinear', got {method!r}.")
    n = int(round(duration * sample_rate)) + 1
    if n < 2:
        raise ValueError(
            f"duration·sample_rate = {duration * sample_rate!r} gives fewer than 2 samples; "
            "increase the duration or the sample rate."
        )
    dtype = _common_dtype(params, test_voltage)
    ts = jnp.arange(n, dtype=dtype) / jnp.asarray(sample_rate, dtype=dtype)
    simulate = simulate_linear if method == "linear" else simulate_nonlinear
    return ts, simulate(params, ts, test_voltage, key=key, **kwargs)
