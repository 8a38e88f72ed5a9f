"""Static transfer function (1) and basic error (2), docs/models.md §3, checked against
independent NumPy evaluation and hand sums of the paper's Table 4 coefficients."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import central_difference

from accel_jax._static import (
    COEFFICIENTS,
    PPM,
    StaticTransferFunction,
    basic_error,
    g_to_si,
    indicated_acceleration,
    si_to_g,
    to_ppm,
)

RNG = np.random.default_rng(2)


def _random_tf():
    values = RNG.normal(size=len(COEFFICIENTS)) * np.array(
        [1e-3, 2e-5, 1e-5, 5e-6, 5e-6, 1e-6, 1e-7, 1e-5, 1e-5, 5e-6, 5e-6]
    )
    return StaticTransferFunction(**dict(zip(COEFFICIENTS, values, strict=True))), values


def _numpy_af(c, a3, a1, a2):
    a0, A1, d, k2, k3, k4, k5, m1, m2, m31, m32 = c
    return (
        a0
        + (1 + 0.5 * A1 * np.sign(a3) + d) * a3
        + sum(k * a3**n for k, n in zip((k2, k3, k4, k5), (2, 3, 4, 5), strict=True))
        + m1 * a1
        + m2 * a2
        + m31 * a3 * a1
        + m32 * a3 * a2
    )


def test_indicated_acceleration_matches_numpy_polynomial():
    tf, c = _random_tf()
    a3 = np.linspace(-5, 5, 41)
    a1 = RNG.normal(size=41)
    a2 = RNG.normal(size=41)
    ours = np.asarray(indicated_acceleration(tf, a3, a1, a2))
    np.testing.assert_allclose(ours, _numpy_af(c, a3, a1, a2), rtol=0, atol=1e-14)


def test_basic_error_is_eq2():
    tf, c = _random_tf()
    a3 = np.array([-3.0, -0.5, 0.7, 2.0])
    a1 = np.array([0.3, -1.0, 0.2, 0.0])
    expected = _numpy_af(c, a3, a1, 0.0) - (1 + c[2]) * a3
    np.testing.assert_allclose(basic_error(tf, a3, a1), expected, atol=1e-15)
    np.testing.assert_allclose(
        basic_error(tf, a3, a1, include_bias=False), expected - c[0], atol=1e-15
    )


def test_presets_table4_and_basic_error_at_1g():
    aks, al = StaticTransferFunction.aks05(), StaticTransferFunction.al1m()
    assert aks.as_ppm() == pytest.approx(
        {
            "bias_mg": 0.5,
            "asymmetry": 15,
            "scale_factor_error": 0,
            "k2": 2,
            "k3": 7,
            "k4": 0.02,
            "k5": 0.3,
            "m1": 0,
            "m2": 0,
            "m31": 0,
            "m32": 0,
        }
    )
    assert float(al.k2) == pytest.approx(105 * PPM)
    # Hand sums: ½A1 + k2 + k3 + k4 + k5 at 1 g (docs/models.md: 16.8 and 215.4 ppm; Table 5 step 1→2).
    assert float(to_ppm(basic_error(aks, 1.0, include_bias=False))) == pytest.approx(
        16.82, abs=1e-6
    )
    assert float(to_ppm(basic_error(al, 1.0, include_bias=False))) == pytest.approx(215.4, abs=1e-6)
    # Negative input: asymmetry and even terms keep their sign, odd terms flip.
    expected = 1e-3 * 0.5 + (7.5 + 2 - 7 + 0.02 - 0.3) * PPM
    assert float(basic_error(aks, -1.0)) == pytest.approx(expected, abs=1e-15)


def test_grad_jit_vmap():
    tf, _ = _random_tf()
    f = eqx.filter_jit(lambda a: indicated_acceleration(tf, a, 0.4, -0.2))
    for a in (-2.3, 0.8, 4.0):
        assert float(jax.grad(f)(a)) == pytest.approx(float(central_difference(f, a)), rel=1e-8)
    # Sensitivity to the coefficients: ∂a_F/∂k3 = a3³, ∂a_F/∂m31 = a3 a1.
    g = jax.grad(lambda t: indicated_acceleration(t, 1.5, 0.4, 0.0))(tf)
    assert float(g.k3) == pytest.approx(1.5**3)
    assert float(g.m31) == pytest.approx(1.5 * 0.4)
    assert float(g.asymmetry) == pytest.approx(0.75)
    batched = jax.vmap(indicated_acceleration, in_axes=(None, 0))(tf, jnp.arange(3.0))
    np.testing.assert_allclose(batched, indicated_acceleration(tf, jnp.arange(3.0)))


def test_units_in_one_place():
    assert float(si_to_g(g_to_si(2.5))) == pytest.approx(2.5)
    assert float(g_to_si(1.0)) == 9.80665


def test_bad_input_raises():
    with pytest.raises(ValueError, match="k3 must be finite"):
        StaticTransferFunction(k3=np.nan)
    with pytest.raises(ValueError, match="Unknown coefficient"):
        StaticTransferFunction.from_ppm(k6=1.0)
