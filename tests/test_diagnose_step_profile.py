"""`accel_jax.diagnose.step.profile.interval`: the profile-likelihood interval of a
coefficient, checked against closed forms (a quadratic profile, an ordinary least-squares
line, whose profile interval is its linearised one exactly) and on a profile that is far
from quadratic."""

import math

import numpy as np
import pytest

from accel_jax.diagnose.step.profile import MAX_REFITS, TOLERANCE, interval


@pytest.mark.parametrize("wrong_by", [15.0, 1.0, 1 / 20])
def test_a_quadratic_profile_gives_its_sigma_whatever_the_linearised_start(wrong_by):
    sigma, c = 0.006, 0.056
    found = interval(lambda v: ((v - c) / sigma) ** 2, c, sigma * wrong_by)
    assert found.found and found.refits <= 2 * MAX_REFITS
    # Within the tolerance on Δχ² (√(1 ± 0.1): about ±5 % on each side).
    assert found.sigma == pytest.approx(sigma, rel=0.06)
    assert c - found.lower == pytest.approx(sigma, rel=0.06)
    assert found.upper - c == pytest.approx(sigma, rel=0.06)


def test_an_ordinary_least_squares_slope_its_profile_is_its_linearised_sigma():
    # y = a + b t + e, e ~ N(0, 1): the profile of b (a refitted) is exactly quadratic with
    # curvature 1/σ_b², σ_b from (XᵀX)⁻¹; the level 4 gives the 2σ interval.
    rng = np.random.default_rng(0)
    t = np.linspace(0.0, 1.0, 200)
    y = 0.3 + 1.7 * t + rng.standard_normal(t.size)
    design = np.column_stack([np.ones_like(t), t])
    coef, *_ = np.linalg.lstsq(design, y, rcond=None)
    chi2_hat = float(np.sum((y - design @ coef) ** 2))
    sigma_b = math.sqrt(np.linalg.inv(design.T @ design)[1, 1])

    def delta(b):
        a = float(np.mean(y - b * t))  # a refitted with b held
        return float(np.sum((y - a - b * t) ** 2)) - chi2_hat

    found = interval(delta, float(coef[1]), 3 * sigma_b, level=4.0)
    assert found.found
    assert found.sigma == pytest.approx(2 * sigma_b, rel=0.06)


def test_a_skewed_profile_gets_two_sides():
    # Above the estimate Δχ² = (x + x³)² (far from quadratic: 1 at x ≈ 0.6823, the root of
    # x³ + x − 1), below it (x/3)² (1 at x = −3).
    def delta(x):
        return (x + x**3) ** 2 if x >= 0 else (x / 3) ** 2

    found = interval(delta, 0.0, 5.0)
    assert found.found
    assert delta(found.upper) == pytest.approx(1.0, abs=TOLERANCE)
    assert delta(found.lower) == pytest.approx(1.0, abs=TOLERANCE)
    assert found.upper == pytest.approx(0.6823, rel=0.05)
    assert found.lower == pytest.approx(-3.0, rel=0.05)


def test_a_flat_profile_is_not_called_found_and_bad_input_is_refused():
    flat = interval(lambda v: 1e-9 * v**2, 0.0, 1.0)
    assert not flat.found and flat.refits == 2 * MAX_REFITS
    with pytest.raises(ValueError, match="positive and finite"):
        interval(lambda v: v**2, 0.0, float("nan"))


def test_a_failed_refit_gives_a_finite_end_not_called_found():
    # Beyond 2σ above the estimate the refit fails (NaN): that side is not found, and its
    # end stays finite (the last bracket), never NaN in the report.
    def delta(v):
        return float("nan") if v > 2.0 else v**2

    found = interval(delta, 0.0, 30.0)
    assert not found.found
    assert math.isfinite(found.upper) and math.isfinite(found.sigma)
    assert found.lower == pytest.approx(-1.0, rel=0.06)


def test_profile_refits_at_their_tolerance_give_the_tight_refits_intervals():
    # MINPACK's refits stopped at `profile.FTOL` against the same refits run to 1e-12, on a
    # nonlinear fit (two exponentials sharing a rate, refitted with each coefficient held):
    # from a cold start the refit's χ² is within FTOL·χ² of the minimum, and so each
    # interval end within FTOL·χ²·σ/2 of the tight one's (Δχ² ≈ 2(x − end)/σ there);
    # `profile`'s claim, checked with a factor 2 to spare.
    from functools import partial

    import jax
    import jax.numpy as jnp

    from accel_jax.diagnose.step import profile
    from accel_jax.diagnose.step.minpack import solve

    with jax.enable_x64(True):
        t = jnp.linspace(0.0, 4.0, 400)
        rng = np.random.default_rng(3)
        noise = 0.05
        truth = 1.3 * jnp.exp(-0.8 * t) + 0.6 * jnp.exp(-1.6 * t) - 0.2 * jnp.sin(3.0 * t)
        y = truth + noise * jnp.asarray(rng.standard_normal(t.size))

        @jax.jit
        def residuals(params, args):
            pick, used, _, fixed = args
            c = params[2:] @ pick + fixed
            decay = jnp.exp(-params[1] * t)
            model = params[0] * decay + c[0] * decay**2 + c[1] * jnp.sin(3.0 * t)
            pins = 1e3 * (1.0 - used) * params[2:]  # a held coefficient's own slot at 0
            return jnp.concatenate([(y - model) / noise, pins])

        jacobian = jax.jit(jax.jacfwd(residuals))
        pick, used = np.eye(2), np.ones(2)
        args = tuple(jnp.asarray(a) for a in (pick, used, 0.0, np.zeros(2)))
        cold = np.array([1.0, 1.0, 0.0, 0.0])
        fit = solve(residuals, jacobian, cold, args, ftol=1e-12)
        chi2 = 2 * fit.cost
        stopped = 2 * solve(residuals, jacobian, cold, args, ftol=profile.FTOL).cost
        assert 0 <= stopped - chi2 < 2 * profile.FTOL * chi2
        jac = np.asarray(jacobian(jnp.asarray(fit.x), args))[:400]
        sigmas = np.sqrt(np.diag(np.linalg.inv(jac.T @ jac)))[2:]
        run = partial(profile.column_intervals, residuals_at=residuals, jacobian_at=jacobian,
                      params=fit.x, args=(pick, used, 0.0), n_free=2, n_cols=2,
                      sigmas=sigmas, level=1.0)  # fmt: skip
        loose, tight = run(solve), run(solve, ftol=1e-12)
    for a, b in zip(loose, tight, strict=True):
        assert a.found and b.found
        bound = profile.FTOL * chi2 * b.sigma  # twice FTOL·χ²·σ/2
        assert abs(a.lower - b.lower) < bound and abs(a.upper - b.upper) < bound
