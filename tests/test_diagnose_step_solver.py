"""The solvers that end a stalled fit (`accel_jax._solvers`): the step fits' least-squares
`StallEnding` and the noise fits' `StallEndingMinimiser`. A fit that stalls ends as at its
step limit, and one that makes progress or converges takes exactly the steps and values of
the plain solver."""

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import optimistix as optx
import pytest

from accel_jax.diagnose.step.solver import (
    STALL_ABSOLUTE,
    STALL_RELATIVE,
    STALL_WINDOW,
    StallEnding,
)


@pytest.fixture(autouse=True)
def _x64():
    with jax.enable_x64(True):
        yield


def _lm():
    return optx.LevenbergMarquardt(rtol=1e-6, atol=1e-6, linear_solver=lx.Normal(lx.Cholesky()))


def _solve(solver, fn, y0, max_steps=100):
    solution = optx.least_squares(fn, solver, y0, max_steps=max_steps, throw=False)
    cost = float(jnp.sum(solution.state.f_info.residual ** 2))
    return solution, cost, int(solution.stats["num_steps"])


def test_a_creeping_fit_ends_at_its_stall_as_at_its_limit():
    # A misfit far above its floor whose only free residual saturates: each step moves y a
    # long way for a vanishing decrease, so the plain solver's own test (small steps and
    # a small change of cost) never ends it and it runs to its limit.
    def creep(y, _):
        return jnp.stack([1e3 + 0 * y[0], 1 / (1 + y[0] ** 2)])

    y0 = jnp.array([10.0])
    plain, plain_cost, plain_steps = _solve(_lm(), creep, y0)
    ended, cost, steps = _solve(StallEnding(_lm()), creep, y0)
    assert plain_steps == 100 and plain.result == optx.RESULTS.nonlinear_max_steps_reached
    assert steps == STALL_WINDOW + 1  # the first time the window is full
    assert ended.result == optx.RESULTS.nonlinear_max_steps_reached  # judged as at the limit
    # What ending early lost is within the bound the module states.
    bound = (100 / STALL_WINDOW - 1) * (STALL_RELATIVE * cost + STALL_ABSOLUTE)
    assert 0 <= cost - plain_cost <= bound


@pytest.mark.parametrize("max_steps", [5, 100])
def test_a_fit_that_progresses_is_the_plain_solvers_step_for_step(max_steps):
    # An exponential fit converging in a few steps, and the same fit cut at 5 steps: the
    # values, step counts and results are the plain solver's, bit for bit.
    t = jnp.linspace(0, 1, 50)
    data = 2.0 * jnp.exp(-3.0 * t) + 0.01 * jnp.sin(40 * t)

    def residuals(y, _):
        return y[0] * jnp.exp(-y[1] * t) - data

    y0 = jnp.array([1.0, 1.0])
    plain, plain_cost, plain_steps = _solve(_lm(), residuals, y0, max_steps)
    ended, cost, steps = _solve(StallEnding(_lm()), residuals, y0, max_steps)
    assert steps == plain_steps and ended.result == plain.result and cost == plain_cost
    assert bool(jnp.all(ended.value == plain.value))
    assert (plain.result == optx.RESULTS.successful) == (max_steps == 100)


class _Info(eqx.Module):
    residual: jax.Array


class _ScriptState(eqx.Module):
    k: jax.Array
    f_info: _Info


class _Scripted(optx.AbstractLeastSquaresSolver):
    """A stand-in inner solver whose accepted cost after step k is `costs[k]` (a cost
    that does not fall is a rejected step); it ends, successful, after the last."""

    costs: jax.Array
    rtol: float = 1e-6
    atol: float = 1e-6
    norm: Callable = optx.max_norm

    def _state(self, k):
        return _ScriptState(k, _Info(jnp.sqrt(self.costs[k])[None]))

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        return self._state(jnp.array(0))

    def step(self, fn, y, args, options, state, tags):
        return y, self._state(state.k + 1), None

    def terminate(self, fn, y, args, options, state, tags):
        return state.k >= self.costs.shape[0] - 1, optx.RESULTS.successful

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return y, aux, {}


def _scripted(costs):
    solver = StallEnding(_Scripted(jnp.asarray(costs, float)))
    return optx.least_squares(
        lambda y, _: y, solver, jnp.zeros(1), max_steps=100, throw=False
    )


def test_the_window_counts_accepted_steps_only():
    # A slow fall (1e-4 a step at a cost of 1e3: below the rule's 1e-3 + 1e-6 × cost over
    # ten steps) ends once ten accepted steps span the window; a run of fifteen rejected
    # steps (the cost unchanged) between fast falls does not end the fit.
    slow = _scripted(1e3 - 1e-4 * jnp.arange(40))
    assert int(slow.stats["num_steps"]) == STALL_WINDOW + 1
    assert slow.result == optx.RESULTS.nonlinear_max_steps_reached
    script = [100.0, 99.0, 98.0, 97.0] + [97.0] * 15 + [50.0, 20.0, 10.0, 5.0, 1.0]
    rejections = _scripted(script)
    assert int(rejections.stats["num_steps"]) == len(script) - 1
    assert rejections.result == optx.RESULTS.successful


# The minimiser variant (`accel_jax._solvers.StallEndingMinimiser`, the static-noise
# selection's Whittle fits): the same window, on the loss itself.


def _bfgs():
    return optx.BFGS(rtol=1e-8, atol=1e-8)


def _minimise(solver, fn, y0, max_steps=128):
    solution = optx.minimise(fn, solver, y0, max_steps=max_steps, throw=False)
    return solution, float(fn(solution.value, None)), int(solution.stats["num_steps"])


def test_a_minimisation_whose_loss_has_settled_ends_at_its_stall():
    # One parameter identified (y0 → 1), one that the loss barely sees (a level that
    # goes to −∞, as an absent noise component's does): BFGS's own test (small steps and a
    # small change of the loss) never fires, so it runs to its limit, creeping.
    from accel_jax._solvers import StallEndingMinimiser

    def loss(y, _):
        return (y[0] - 1.0) ** 2 + 1e-3 * jnp.exp(y[1])

    y0 = jnp.array([3.0, 0.0])
    plain, plain_loss, plain_steps = _minimise(_bfgs(), loss, y0)
    absolute = 1e-6
    ended, ended_loss, steps = _minimise(
        StallEndingMinimiser(_bfgs(), STALL_WINDOW, 0.0, absolute), loss, y0
    )
    assert plain_steps == 128 and plain.result == optx.RESULTS.nonlinear_max_steps_reached
    assert steps < plain_steps // 2
    assert ended.result == optx.RESULTS.nonlinear_max_steps_reached  # judged as at the limit
    assert abs(float(ended.value[0]) - 1.0) < 1e-6  # the identified parameter is there
    # What ending early lost is within the bound the module states.
    assert 0 <= ended_loss - plain_loss <= (128 / STALL_WINDOW - 1) * absolute


def test_a_converging_minimisation_is_bfgs_step_for_step():
    from accel_jax._solvers import StallEndingMinimiser

    def loss(y, _):  # Rosenbrock's valley: converges, after many steps of progress
        return (1 - y[0]) ** 2 + 100 * (y[1] - y[0] ** 2) ** 2

    y0 = jnp.array([-1.2, 1.0])
    plain, plain_loss, plain_steps = _minimise(_bfgs(), loss, y0)
    ended, ended_loss, steps = _minimise(
        StallEndingMinimiser(_bfgs(), STALL_WINDOW, 0.0, 1e-12), loss, y0
    )
    assert plain.result == optx.RESULTS.successful and plain_steps > STALL_WINDOW
    assert steps == plain_steps and ended.result == plain.result and ended_loss == plain_loss
    assert bool(jnp.all(ended.value == plain.value))
