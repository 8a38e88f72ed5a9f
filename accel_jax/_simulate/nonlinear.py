"""`simulate_nonlinear`: the loop with the mechanical stops |l θ| ≤ h_max, solved with
diffrax."""

from __future__ import annotations

import diffrax
import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, PRNGKeyArray

from .._params import ServoParams
from .._servo import time_constant
from .loop import _add_noise, _drive_before, _grid_step, _Loop, _prepare
from .state_space import (
    _SampleInput,
    _Samples,
    _SampleTimes,
    _StateLike,
    _States,
    equilibrium_state,
)

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
    def t0(self):  # pyright: ignore[reportIncompatibleVariableOverride]  # diffrax's AbstractVar
        return self.ts[0]

    @property
    def t1(self):  # pyright: ignore[reportIncompatibleVariableOverride]  # diffrax's AbstractVar
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
