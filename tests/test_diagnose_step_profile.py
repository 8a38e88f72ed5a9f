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


def test_a_cliff_is_bisected_not_crawled_to():
    # Quadratic (σ = 1) up to a cliff at 0.6, where the model leaves the data (a loop that
    # runs away): Δχ² never reaches the level within 10 %, so the side is not found, but
    # its end lies at the cliff. The secant through the near probe (0.1, 0.01) and the
    # cliff (1.0, 1e6) would move 1/1000 of the way a refit and end near 0.1.
    def delta(v):
        return v**2 if abs(v) < 0.6 else 1e6

    found = interval(delta, 0.0, 1.0)
    assert not found.found
    assert 0.55 <= found.upper <= 0.7 and -0.7 <= found.lower <= -0.55
    # A steep profile that is no cliff keeps the secant: (x + x³)², found as before.
    skewed = interval(lambda x: (x + x**3) ** 2, 0.0, 5.0)
    assert skewed.found and skewed.upper == pytest.approx(0.6823, rel=0.05)


def test_profile_refits_are_capped_in_evaluations():
    from accel_jax.diagnose.step import profile

    calls = []

    class Fit:
        cost, status, x = 0.0, 1, np.zeros(3)

    def solve(fun, jac, x0, args, **options):
        calls.append(options)
        return Fit()

    def residuals(params, args):
        return np.zeros(2)

    # A flat profile (every refit's cost 0): each side spends its refits, every one capped.
    profile.column_intervals(
        solve, residuals, None, np.zeros(3), (np.eye(2), np.ones(2), 0.0), 1, 2, [1.0, 1.0], 1.0
    )
    assert calls and all(c["max_evaluations"] == profile.MAX_EVALUATIONS for c in calls)


def test_each_profile_refit_continues_from_the_nearest_converged_one_on_its_side():
    # A coefficient c (estimate 0.5, the optimum's other parameter 0) held at v: the
    # other parameter's profile optimum is 10 (v − 0.5), Δχ² = ((v − 0.5)/0.2)². The fake
    # solver records where each refit starts; each refit must start from the converged
    # refit of the nearest value held so far on the same side of the estimate whose Δχ² is
    # below CLIFF² times the level (else from the optimum), never from a refit on the
    # other side, from one that failed, or from one far beyond the level (a false minimum
    # converges too).
    from accel_jax.diagnose.step import profile

    starts = []

    class Fit:
        def __init__(self, x, cost, status):
            self.x, self.cost, self.status = x, cost, status

    def solve(fun, jac, x0, args, **options):
        v = float(np.asarray(args[3])[0])
        starts.append((v, float(x0[0])))
        fails = v > 0.5 + 0.25  # far above: no convergence (status 0), a large cost
        return Fit(np.array([10 * (v - 0.5), 0.0]), 0.5 * ((v - 0.5) / 0.2) ** 2, 0 if fails else 2)

    def residuals(params, args):
        return np.zeros(1)

    params = np.array([0.0, 0.5])  # the other parameter, then the coefficient
    found = profile.column_intervals(
        solve, residuals, None, params, (np.eye(1), np.ones(1), 0.0), 1, 1, [1.0], 1.0
    )[0]
    assert found.lower == pytest.approx(0.3, rel=0.06)
    converged = []  # (value held, its refit's other parameter)
    for v, x0 in starts:
        side = [(at, x) for at, x in converged if (at > 0.5) == (v > 0.5)]
        expected = min(side, key=lambda item: abs(item[0] - v))[1] if side else 0.0
        if side and abs(0.5 - v) < min(abs(at - v) for at, _ in side):
            expected = 0.0  # the optimum is nearer
        assert x0 == pytest.approx(expected), (v, x0, starts)
        if not v > 0.75 and ((v - 0.5) / 0.2) ** 2 < profile.CLIFF**2:  # converged, near
            converged.append((v, 10 * (v - 0.5)))


def test_a_failed_refit_gives_a_finite_end_not_called_found():
    # Beyond 2σ above the estimate the refit fails (NaN): that side is not found, and its
    # end stays finite (the last bracket), never NaN in the report.
    def delta(v):
        return float("nan") if v > 2.0 else v**2

    found = interval(delta, 0.0, 30.0)
    assert not found.found
    assert math.isfinite(found.upper) and math.isfinite(found.sigma)
    assert found.lower == pytest.approx(-1.0, rel=0.06)


def test_profile_refits_at_their_tolerance_give_the_tight_refits_intervals(monkeypatch):
    # MINPACK's refits stopped at `profile.FTOL` against the same refits run to 1e-12, on a
    # nonlinear fit (two exponentials sharing a rate, refitted with each coefficient held):
    # from a cold start the refit's χ² is within FTOL·χ² of the minimum, and so each
    # interval end within FTOL·χ²·σ/2 of the tight one's (Δχ² ≈ 2(x − end)/σ there);
    # `profile`'s claim, checked with a factor 2 to spare. The sides searched on threads
    # (several CPUs) give the same intervals, to the bit, as one after the other (one CPU).
    from functools import partial

    import jax
    import jax.numpy as jnp

    from accel_jax import _runtime
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
        for cpus in (1, 3):
            monkeypatch.setattr(_runtime, "usable_cpus", lambda cpus=cpus: list(range(cpus)))
            assert run(solve) == loose
    for a, b in zip(loose, tight, strict=True):
        assert a.found and b.found
        bound = profile.FTOL * chi2 * b.sigma  # twice FTOL·χ²·σ/2
        assert abs(a.lower - b.lower) < bound and abs(a.upper - b.upper) < bound
