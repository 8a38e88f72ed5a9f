"""The servo loop's state-space model (docs/models.md §1): `state_space` (with the ideal-lag
limits T_dm = 0, T_f = 0), its exact zero-order-hold discretisation `discretise`, and
the settled state `equilibrium_state`."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .._params import ServoParams
from .._servo import feedback_stiffness, loop_stiffness

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

    Its transfer functions are docs/models.md eq. (1) (`transfer_function`) and
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

    The state [θ, θ', M_dm, U_f] in [rad, rad/s, N·m, V], shape (4,).
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
