"""Input handling and the internal (scaled) form of the loop shared by the simulators:
`_prepare` validates and promotes the inputs, `_Loop` holds the scaled matrices and maps
between physical and internal states."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._checks import check_uniform_grid
from .._params import ServoParams, _concrete, _shown
from .._servo import feedback_stiffness, loop_stiffness, time_constant
from .state_space import _STATE_NAMES, _pickoff_amplifier_per_radian, _stop_angle, state_space

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
