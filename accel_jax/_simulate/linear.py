"""`simulate_linear`: the linear loop (no mechanical stops), discretised exactly for
zero-order-held inputs (matrix exponential) and run with `jax.lax.scan`."""

from __future__ import annotations

import equinox as eqx
import jax
from jaxtyping import PRNGKeyArray

from .._params import ServoParams
from .loop import _add_noise, _drive_before, _grid_step, _Loop, _prepare
from .state_space import (
    _SampleInput,
    _Samples,
    _SampleTimes,
    _StateLike,
    _States,
    discretise,
    equilibrium_state,
)

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
    - `initial_state`: [θ, θ', M_dm, U_f] in [rad, rad/s, N·m, V] at t_0 (before U_test(t_0)
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
