"""What the step diagnosis's fits take from the solver (accel_jax/diagnose/step/fit.py):
`dense_jacobian` differentiates as the function does, and an optimistix
Levenberg–Marquardt solution's state holds the residuals and Jacobian at the returned
value (the fits read the cost, the Newton decrement and the polishing step from it instead
of simulating again). Checked on a small nonlinear least-squares problem, converged and
stopped early."""

import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
import pytest

from accel_jax.diagnose.step.fit import _gauss_newton_step, _newton_step, dense_jacobian

T = jnp.linspace(0.0, 3.0, 40)


def _residuals(w, scale):
    # A damped oscillation's amplitude, rate and frequency against data, plus a prior row.
    y = 1.3 * jnp.exp(-0.7 * T) * jnp.cos(2.1 * T)
    model = w[0] * jnp.exp(-w[1] * T) * jnp.cos(w[2] * T)
    return jnp.concatenate([scale * (model - y), 0.1 * w[:1]])


def test_dense_jacobian_differentiates_as_the_function_does():
    with jax.enable_x64(True):
        w = jnp.array([1.0, 0.5, 2.0])
        dense = dense_jacobian(_residuals)
        np.testing.assert_allclose(dense(w, 2.0), _residuals(w, 2.0), rtol=0, atol=0)
        expected = jax.jacfwd(_residuals)(w, 2.0)
        np.testing.assert_allclose(jax.jacfwd(dense)(w, 2.0), expected, rtol=1e-14)
        tangent = jnp.array([0.3, -1.0, 0.2])
        _, out = jax.jvp(lambda v: dense(v, 2.0), (w,), (tangent,))
        np.testing.assert_allclose(out, expected @ tangent, rtol=1e-14)


@pytest.mark.parametrize("max_steps", [3, 100])
def test_the_solvers_state_holds_the_residuals_and_jacobian_at_its_value(max_steps):
    with jax.enable_x64(True):
        solver = optx.LevenbergMarquardt(
            rtol=1e-10, atol=1e-10, linear_solver=lx.Normal(lx.Cholesky())
        )

        @jax.jit
        def fit(w0):
            solution = optx.least_squares(
                dense_jacobian(_residuals), solver, w0, args=2.0, max_steps=max_steps, throw=False
            )
            info = solution.state.f_info
            return solution.value, info.residual, info.jac.as_matrix(), solution.result

        value, r, jac, result = fit(jnp.array([1.0, 0.5, 2.0]))
        assert (result == optx.RESULTS.successful) == (max_steps == 100)
        np.testing.assert_allclose(r, _residuals(value, 2.0), rtol=0, atol=1e-14)
        np.testing.assert_allclose(jac, jax.jacfwd(_residuals)(value, 2.0), rtol=1e-13)
        # The Newton step from the state is the one from a fresh evaluation.
        from_state = _newton_step(jac, r, value)
        fresh = _gauss_newton_step(lambda v: _residuals(v, 2.0), value)
        for a, b in zip(from_state, fresh, strict=True):
            np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-14)


def _fit_steps(solver, w0, scale):
    @jax.jit
    def fit(w0):
        solution = optx.least_squares(
            dense_jacobian(_residuals), solver, w0, args=scale, max_steps=200, throw=False
        )
        return solution.value, solution.result, solution.stats["num_steps"]

    return fit(w0)


def test_a_fit_ends_once_it_would_count_as_converged():
    # `MinimumEnding` ends a fit at the first accepted point where the test that `fit_one`
    # applies to its result holds (`_at_minimum`), instead of at the solver's own tolerance.
    from accel_jax.diagnose.step.fit import CONVERGED_DECREMENT, _at_minimum
    from accel_jax.diagnose.step.solver import MinimumEnding

    with jax.enable_x64(True):
        plain = optx.LevenbergMarquardt(
            rtol=1e-14, atol=1e-14, linear_solver=lx.Normal(lx.Cholesky())
        )
        w0, scale = jnp.array([1.0, 0.5, 2.0]), 30.0  # the cost ½Σr² from 165 to ~1e-2
        full, full_result, full_steps = _fit_steps(plain, w0, scale)
        ended, result, steps = _fit_steps(MinimumEnding(plain, _at_minimum), w0, scale)
        assert full_result == optx.RESULTS.successful and result == optx.RESULTS.successful
        assert int(steps) < int(full_steps), (steps, full_steps)

        def cost(w):
            return 0.5 * float(jnp.sum(_residuals(w, scale) ** 2))

        jac = jax.jacfwd(_residuals)(ended, scale)
        assert bool(_at_minimum(jac, _residuals(ended, scale)))
        # What ending there costs: within the decrement's bound of the minimum (the
        # quadratic model's remaining decrease is half the decrement).
        assert 0.0 <= cost(ended) - cost(full) <= 0.5 * CONVERGED_DECREMENT + 1e-12
        # A test that never holds leaves the solver's steps and values as they were.
        never, never_result, never_steps = _fit_steps(
            MinimumEnding(plain, lambda jac, r: jnp.array(False)), w0, scale
        )
        assert int(never_steps) == int(full_steps) and never_result == full_result
        np.testing.assert_array_equal(never, full)
        # From the minimum itself it ends at once: the first step's linearisation.
        _, again_result, again_steps = _fit_steps(MinimumEnding(plain, _at_minimum), full, scale)
        assert again_result == optx.RESULTS.successful and int(again_steps) <= 1


def test_a_traced_step_limit_is_the_static_one():
    # `StepLimited` (the joint fit's nominal and lags in one compiled program): a fit under
    # a traced limit k, run with a larger static `max_steps`, takes exactly the steps and
    # values of `max_steps=k`, and reports the same result and step count; one program
    # serves every limit.
    from accel_jax._solvers import StepLimited

    with jax.enable_x64(True):
        plain = optx.LevenbergMarquardt(
            rtol=1e-14, atol=1e-14, linear_solver=lx.Normal(lx.Cholesky())
        )
        w0 = jnp.array([1.0, 0.5, 2.0])

        @jax.jit
        def limited(limit):
            solution = optx.least_squares(
                dense_jacobian(_residuals), StepLimited(plain, limit), w0, args=30.0,
                max_steps=200, throw=False,
            )
            return solution.value, solution.result, solution.stats["num_steps"]

        def static(limit):
            @jax.jit
            def fit(w):
                solution = optx.least_squares(
                    dense_jacobian(_residuals), plain, w, args=30.0, max_steps=limit,
                    throw=False,
                )
                return solution.value, solution.result, solution.stats["num_steps"]

            return fit(w0)

        _, _, converged_at = static(200)
        for limit in (0, 1, 3, int(converged_at) - 1, int(converged_at), 150):
            value, result, steps = limited(jnp.asarray(limit))
            expected, expected_result, expected_steps = static(limit)
            np.testing.assert_array_equal(value, expected)
            assert result == expected_result and int(steps) == int(expected_steps), limit
        assert limited._cache_size() == 1
