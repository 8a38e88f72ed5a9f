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
