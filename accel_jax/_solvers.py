"""Solvers that end a fit early: optimistix's solvers, wrapped, ended as at their step
limit (`RESULTS.nonlinear_max_steps_reached`) once the accepted point's cost has stopped
falling or a traced step limit is reached, or (`MinimumEnding`) as converged once the
accepted point passes the caller's own convergence test; a fit that never meets the
wrapper's test takes exactly the steps and values it took before (the inner solver's state
is untouched).

- `StallEnding`: a Gauss–Newton-type least-squares solver (Levenberg–Marquardt), for the
  step diagnosis's fits whose steps are dear (a stop's or a compliant contact's
  sample-by-sample simulation) and whose step limit is high so that a far start can walk
  back to the optimum. A fit of an effect that cannot describe the record (a stop on a
  record with no stop, an out-of-library effect) creeps: on a pickoff-nonlinearity record
  of the independent simulator (6,001 samples), the compliant stop's five starts ran 100
  steps each, three of them from χ² = 3.70604e6 to 3.70603e6.
- `StallEndingMinimiser`: a minimiser (BFGS), for the static-noise selection's Whittle
  fits (`_noise.spectral`), where a parameter the record does not identify (an absent
  flicker's level, a β → 0) keeps the step test of the tolerance from firing after the
  likelihood has settled: 14 of 21 single-start fits of one record ran all 128 steps.
- `MinimumEnding`: a least-squares solver whose state holds the accepted point's residuals
  and Jacobian, for every fit of the step diagnosis: optimistix's tolerance (steps and cost
  changes below 1e-6) keeps a fit going long after a Gauss–Newton step from its point
  would lower the cost by less than the diagnosis needs. On the quick report's 18 step
  records, the linear candidates' kept starts took a median of 19.5 Levenberg–Marquardt
  steps (1,772 in all) without it, 5 (1,013) with it; a fit that never passes the test
  still runs to its limit.
- `StepLimited`: a least-squares solver ended as at its step limit after a traced number
  of steps, so that fits of different limits share one compiled program (the joint step
  fit's nominal, limited to 30 steps, and its lags, to 60: `diagnose.step.joint`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, Float, Int

STALL_WINDOW = 10
"""Accepted steps over which a fit's progress is judged."""

STALL_RELATIVE = 1e-6
STALL_ABSOLUTE = 1e-3
"""A fit has stalled when its cost Σr² (the accepted point's: in χ² units for the step
fits) fell by less than `STALL_RELATIVE` × cost + `STALL_ABSOLUTE` over its last
`STALL_WINDOW` accepted steps. What ending there can cost: were the fit to go on at that
rate to its limit L, ≤ (L/`STALL_WINDOW` − 1) × that much of χ² — for a record at its noise
floor (χ² ≈ samples ≈ 10⁴) ≤ 0.2 at L = 100, far below the evidence scale (2 ln B ≈ 6 for
odds of 20 : 1) — unless it would have sped up again. Rejected steps do not count: with
them, a compliant contact's fit on an independent simulator's stop record (24,001
samples) ended during a run of rejections, and the clamp was named where the fit to the
limit names the compliant contact (both of the stop's family)."""


class _State(eqx.Module):
    inner: Any
    # The cost after each of the last `window` + 1 accepted steps, oldest first (inf: none).
    costs: Float[Array, " window_plus_one"]

    @property
    def f_info(self):
        """The inner solver's linearisation at the accepted point (as its state has it)."""
        return self.inner.f_info


class StallEnding(optx.AbstractLeastSquaresSolver):
    """`inner` (a Gauss–Newton-type solver whose state holds `f_info`, e.g.
    `optx.LevenbergMarquardt`), ended as at its step limit when it stalls (module
    docstring). The solution's `state.f_info` is the inner solver's."""

    inner: optx.AbstractGaussNewton
    rtol: float
    atol: float
    norm: Callable
    window: int = eqx.field(static=True)
    relative: float
    absolute: float

    def __init__(
        self,
        inner: optx.AbstractGaussNewton,
        window: int = STALL_WINDOW,
        relative: float = STALL_RELATIVE,
        absolute: float = STALL_ABSOLUTE,
    ):
        self.inner = inner
        self.rtol, self.atol, self.norm = inner.rtol, inner.atol, inner.norm  # the inner's
        self.window, self.relative, self.absolute = window, relative, absolute

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        inner = self.inner.init(fn, y, args, options, f_struct, aux_struct, tags)
        dtype = jnp.result_type(*[s.dtype for s in _leaves(f_struct)])
        return _State(inner, jnp.full(self.window + 1, jnp.inf, dtype))

    def step(self, fn, y, args, options, state, tags):
        y, inner, aux = self.inner.step(fn, y, args, options, state.inner, tags)
        cost = sum(jnp.sum(r**2) for r in _leaves(inner.f_info.residual))
        return y, _State(inner, _pushed(state.costs, cost)), aux

    def terminate(self, fn, y, args, options, state, tags):
        done, result = self.inner.terminate(fn, y, args, options, state.inner, tags)
        return _ended(done, result, state.costs, self.relative, self.absolute)

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return self.inner.postprocess(fn, y, aux, args, options, state.inner, tags, result)


class _CountedState(eqx.Module):
    inner: Any
    steps: Int[Array, ""]  # steps taken: the linearisation is the accepted point's once ≥ 1

    @property
    def f_info(self):
        """The inner solver's linearisation at the accepted point (as its state has it)."""
        return self.inner.f_info


class _Counting(optx.AbstractLeastSquaresSolver):
    """A wrapper of the least-squares solver `inner` that counts its steps (`_CountedState`)
    and leaves its steps and results as they are; the subclass's `terminate` ends it."""

    inner: eqx.AbstractVar[optx.AbstractLeastSquaresSolver]

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        inner = self.inner.init(fn, y, args, options, f_struct, aux_struct, tags)
        return _CountedState(inner, jnp.array(0))

    def step(self, fn, y, args, options, state, tags):
        y, inner, aux = self.inner.step(fn, y, args, options, state.inner, tags)
        return y, _CountedState(inner, state.steps + 1), aux

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return self.inner.postprocess(fn, y, aux, args, options, state.inner, tags, result)


class MinimumEnding(_Counting):
    """`inner` (a least-squares solver whose state holds `f_info`, the residuals and
    Jacobian at the accepted point: `optx.LevenbergMarquardt` or a `StallEnding` of it),
    ended as converged (`RESULTS.successful`) once `at_minimum(J, r)` holds at the accepted
    point (J the Jacobian as a matrix, r the residuals): the test by which the caller would
    judge the result converged anyway, applied at every step instead of only at the end. A
    fit that never meets it takes exactly the steps and values it took before."""

    inner: optx.AbstractLeastSquaresSolver
    rtol: float
    atol: float
    norm: Callable
    at_minimum: Callable = eqx.field(static=True)

    def __init__(self, inner, at_minimum: Callable):
        self.inner, self.at_minimum = inner, at_minimum
        self.rtol, self.atol, self.norm = inner.rtol, inner.atol, inner.norm  # the inner's

    def terminate(self, fn, y, args, options, state, tags):
        done, result = self.inner.terminate(fn, y, args, options, state.inner, tags)
        info = state.inner.f_info
        met = (state.steps > 0) & self.at_minimum(info.jac.as_matrix(), info.residual)
        result = optx.RESULTS.where(met & ~done, optx.RESULTS.successful, result)
        return done | met, result


class StallEndingMinimiser(optx.AbstractMinimiser):
    """`inner` (a minimiser whose state holds `f_info` with the accepted point's `f`, e.g.
    `optx.BFGS`), ended as at its step limit when it stalls: its loss fell by less than
    `relative` × loss + `absolute` over its last `window` accepted steps (module
    docstring). The solution's `state.f_info` is the inner solver's."""

    inner: optx.AbstractMinimiser
    rtol: float
    atol: float
    norm: Callable
    window: int = eqx.field(static=True)
    relative: float
    absolute: float | Array  # (traced: a loss's scale)

    def __init__(
        self,
        inner: optx.AbstractMinimiser,
        window: int,
        relative: float,
        absolute: float | Array,
    ):
        self.inner = inner
        self.rtol, self.atol, self.norm = inner.rtol, inner.atol, inner.norm  # the inner's
        self.window, self.relative, self.absolute = window, relative, absolute

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        inner = self.inner.init(fn, y, args, options, f_struct, aux_struct, tags)
        return _State(inner, jnp.full(self.window + 1, jnp.inf, f_struct.dtype))

    def step(self, fn, y, args, options, state, tags):
        y, inner, aux = self.inner.step(fn, y, args, options, state.inner, tags)
        return y, _State(inner, _pushed(state.costs, inner.f_info.f)), aux

    def terminate(self, fn, y, args, options, state, tags):
        done, result = self.inner.terminate(fn, y, args, options, state.inner, tags)
        return _ended(done, result, state.costs, self.relative, self.absolute)

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return self.inner.postprocess(fn, y, aux, args, options, state.inner, tags, result)


def _pushed(costs, cost):
    """The window of accepted costs with `cost` added. Only an accepted step (one that
    lowered the cost: the inner solvers accept no other) enters it: a run of rejected steps
    while the damping grows, or the line search shortens the step, is the search for a
    step, not a stall."""
    accepted = ~(cost >= costs[-1])
    shifted = jnp.concatenate([costs[1:], jnp.reshape(cost, (1,))])
    return jnp.where(accepted, shifted, costs)


def _ended(done, result, costs, relative, absolute):
    """(terminate, result): the inner solver's, or ended as at the step limit when the
    cost fell by less than `relative` × cost + `absolute` over the window. `costs[0]` is
    the cost `window` accepted steps ago, `costs[-1]` now: finite once the fit has accepted
    `window` + 1 steps."""
    oldest, now = costs[0], costs[-1]
    stalled = ~done & jnp.isfinite(oldest) & (oldest - now < relative * jnp.abs(now) + absolute)
    result = optx.RESULTS.where(stalled, optx.RESULTS.nonlinear_max_steps_reached, result)
    return done | stalled, result


def _leaves(tree) -> list:
    return jax.tree_util.tree_leaves(tree)


class StepLimited(_Counting):
    """`inner` (a least-squares solver), ended as at its step limit
    (`RESULTS.nonlinear_max_steps_reached`) after `limit` steps, a traced integer: fits of
    different step limits then share one compiled program, run under the largest limit as
    optimistix's static `max_steps` (which must be a Python integer). A fit ended here
    takes exactly the steps and values it would take under `max_steps=limit`, and reports
    the same result and step count."""

    inner: optx.AbstractLeastSquaresSolver
    rtol: float
    atol: float
    norm: Callable
    limit: Int[Array, ""]

    def __init__(self, inner, limit):
        self.inner, self.limit = inner, jnp.asarray(limit)
        self.rtol, self.atol, self.norm = inner.rtol, inner.atol, inner.norm  # the inner's

    def terminate(self, fn, y, args, options, state, tags):
        done, result = self.inner.terminate(fn, y, args, options, state.inner, tags)
        spent = ~done & (state.steps >= self.limit)
        return done | spent, optx.RESULTS.where(
            spent, optx.RESULTS.nonlinear_max_steps_reached, result
        )
