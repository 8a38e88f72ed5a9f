"""Closed forms of docs/models.md §1 against independent references."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import central_difference

import accel_jax as aj

REF = aj.REFERENCE_VALUES


def test_reference_values_match_spec():
    # docs/models.md §1: T ≈ 2.90e-4 s (549 Hz), ξ ≈ 0.52, K_test ≈ 0.996, γ ≈ 0.7493;
    # aperiodic ξ ≈ 2.07.
    p = aj.ServoParams.reference()
    assert float(aj.time_constant(p)) == pytest.approx(2.90e-4, rel=2e-3)
    assert float(1 / (2 * np.pi * aj.time_constant(p))) == pytest.approx(549, rel=2e-3)
    assert float(aj.damping_ratio(p)) == pytest.approx(0.52, abs=5e-3)
    assert float(aj.closed_loop_test_gain(p)) == pytest.approx(0.996, abs=5e-4)
    assert float(aj.shape_factor(p)) == pytest.approx(0.7493, abs=1e-4)
    assert float(aj.damping_ratio(aj.ServoParams.reference_aperiodic())) == pytest.approx(
        2.07, abs=5e-3
    )


def test_closed_forms_by_hand():
    # Evaluate eqs. (2), (4)-(7) directly in NumPy from the raw numbers.
    m, l, J, mu, c = (
        REF[k]
        for k in ("pendulum_mass", "pendulum_length", "moment_of_inertia", "damping", "stiffness")
    )
    kdp, ky, kdm = REF["pickoff_gain"], REF["amplifier_gain"], REF["torquer_gain"]
    k = kdm * l * kdp * ky
    p = aj.ServoParams.reference()
    np.testing.assert_allclose(aj.scale_factor(p), m * l**2 * kdp * ky / (c + k), rtol=1e-14)
    np.testing.assert_allclose(aj.time_constant(p), np.sqrt(J / (c + k)), rtol=1e-14)
    np.testing.assert_allclose(aj.damping_ratio(p), mu / 2 / np.sqrt(J * (c + k)), rtol=1e-14)
    np.testing.assert_allclose(aj.closed_loop_test_gain(p), k / (c + k), rtol=1e-14)
    # Eq. (7) is exact with γ = m l²/J (the paper rounds γ to 3/4).
    kahat = aj.scale_factor_from_time_constant(aj.time_constant(p), kdp * ky, aj.shape_factor(p))
    np.testing.assert_allclose(kahat, aj.scale_factor(p), rtol=1e-14)
    rounded = aj.scale_factor_from_time_constant(aj.time_constant(p), kdp * ky, aj.PAPER_GAMMA)
    # The γ rounding alone: (3/4 − 0.74927)/0.75 ≈ 0.097 % (docs/models.md: "≈ 0.10 %").
    assert float(aj.relative_error_percent(rounded, aj.scale_factor(p))) == pytest.approx(
        0.0971, abs=5e-4
    )


def test_transfer_function_dc_gain_and_poles():
    p = aj.ServoParams.reference()
    num, den = aj.transfer_function(p)
    # DC gain of eq. (1) is K_a.
    np.testing.assert_allclose(num[-1] / den[-1], aj.scale_factor(p), rtol=1e-14)
    # Expanding the product by NumPy polynomial multiplication gives the same denominator.
    pend = np.array([REF["moment_of_inertia"], REF["damping"], REF["stiffness"]])
    lag = np.array([REF["torquer_time_constant"], 1.0])
    expected = np.polymul(pend, lag)
    expected[-1] += float(aj.feedback_stiffness(p))
    np.testing.assert_allclose(den, expected, rtol=1e-14)
    # With T_dm = 0 the poles are those of T²p² + 2ξTp + 1.
    p0 = aj.ServoParams.reference(torquer_time_constant=0.0)
    _, den0 = aj.transfer_function(p0)
    T, xi = float(aj.time_constant(p0)), float(aj.damping_ratio(p0))
    np.testing.assert_allclose(
        np.sort_complex(np.roots(np.asarray(den0[1:]))),
        np.sort_complex(np.roots([T**2, 2 * xi * T, 1.0])),
        rtol=1e-12,
    )
    num_t, den_t = aj.transfer_function_test_signal(p)
    np.testing.assert_allclose(num_t[0] / den_t[-1], aj.closed_loop_test_gain(p), rtol=1e-14)


def test_aperiodic_time_constants():
    p = aj.ServoParams.reference_aperiodic()
    t1, t2, t3, t4 = (float(x) for x in aj.aperiodic_time_constants(p))
    assert t1 == pytest.approx(t3 + t4, rel=1e-14)  # (14)
    assert t2 == pytest.approx(np.sqrt(t3 * t4), rel=1e-12)  # (15)
    assert t1 > 2 * t2
    # T3, T4 are minus the reciprocals of the poles of T2²p² + T1p + 1.
    poles = np.roots([t2**2, t1, 1.0])
    np.testing.assert_allclose(np.sort(-1 / poles.real), [t4, t3], rtol=1e-12)
    with pytest.raises(ValueError, match="oscillatory"):
        aj.aperiodic_time_constants(aj.ServoParams.reference())
    with pytest.raises(Exception, match="oscillatory"):
        jax.jit(aj.aperiodic_time_constants)(aj.ServoParams.reference())


@pytest.mark.parametrize(
    "field", ["damping", "torquer_gain", "moment_of_inertia", "stiffness", "pendulum_length"]
)
def test_gradients_against_finite_differences(field):
    p = aj.ServoParams.reference()

    def functionals(value):
        q = eqx.tree_at(lambda s: getattr(s, field), p, value)
        return jnp.stack([aj.scale_factor(q), aj.time_constant(q), aj.damping_ratio(q)])

    x0 = getattr(p, field)
    jac = jax.jacfwd(functionals)(x0)
    fd = central_difference(functionals, x0)
    np.testing.assert_allclose(jac, fd, rtol=1e-6, atol=1e-12 * float(jnp.max(jnp.abs(fd))))


def test_vmap_over_params():
    dampings = jnp.linspace(1e-5, 2e-4, 7)
    batch = eqx.filter_vmap(lambda mu: aj.ServoParams.reference(damping=mu))(dampings)
    xi = jax.vmap(aj.damping_ratio)(batch)
    one_by_one = [
        float(aj.damping_ratio(aj.ServoParams.reference(damping=float(m)))) for m in dampings
    ]
    np.testing.assert_allclose(xi, one_by_one, rtol=1e-14)


@pytest.mark.parametrize(
    ("field", "value", "match"),
    [
        ("moment_of_inertia", -7e-9, "moment_of_inertia must be positive"),
        ("torquer_gain", 0.0, "torquer_gain must be positive"),
        ("damping", -1.0, "damping must be non-negative"),
        ("torquer_time_constant", -1e-5, "torquer_time_constant must be non-negative"),
        ("external_moment", float("nan"), "external_moment must be finite"),
        ("noise_std", float("inf"), "noise_std must be finite"),
    ],
)
def test_invalid_parameters_raise(field, value, match):
    with pytest.raises(ValueError, match=match):
        aj.ServoParams.reference(**{field: value})


def test_unknown_override_raises():
    with pytest.raises(ValueError, match="Unknown ServoParams field"):
        aj.ServoParams.reference(inertia=1.0)


def test_construction_does_not_enable_x64_or_change_config():
    # The library must not flip global settings; conftest enabled x64 for the tests only.
    before = jax.config.read("jax_enable_x64")
    aj.ServoParams.reference()
    assert jax.config.read("jax_enable_x64") == before


@pytest.mark.parametrize("ratio", [0.3, 1.0, 2.5])
def test_damping_for_ratio_inverts_damping_ratio(ratio):
    params = aj.ServoParams.reference()
    mu = aj.damping_for_ratio(params, ratio)
    twin = eqx.tree_at(lambda p: p.damping, params, mu)
    assert float(aj.damping_ratio(twin)) == pytest.approx(ratio, rel=1e-12)


def test_dominant_pole_scale_factor_against_the_state_space_eigenvalues():
    """Without a torquer lag the dominant pair is the loop's only pair: K̂_a = K_a with the
    exact γ. With one, |s|² of the pair from the transfer function's roots equals that of
    the oscillatory eigenvalue pair of the state-space matrix (an independent route)."""
    ideal = aj.ServoParams.reference(torquer_time_constant=0.0, filter_time_constant=0.0)
    gain = float(ideal.pickoff_gain * ideal.amplifier_gain)
    gamma = float(aj.shape_factor(ideal))
    estimate = aj.dominant_pole_scale_factor(ideal, gamma, gain)
    assert estimate == pytest.approx(float(aj.scale_factor(ideal)), rel=1e-12)
    lagged = aj.ServoParams.reference(torquer_time_constant=1e-5)
    a, *_ = aj.state_space(lagged)
    eigenvalues = np.linalg.eigvals(np.asarray(a))
    pair = eigenvalues[np.argmax(np.abs(eigenvalues.imag))]
    expected = gamma * gain / abs(pair) ** 2
    assert aj.dominant_pole_scale_factor(lagged, gamma, gain) == pytest.approx(expected, rel=1e-9)


def test_damping_for_ratio_and_dominant_pole_refuse_impossible_input():
    with pytest.raises(ValueError, match="ratio must be finite and ≥ 0"):
        aj.damping_for_ratio(aj.ServoParams.reference(), -0.5)
    aperiodic = aj.ServoParams.reference_aperiodic()
    with pytest.raises(ValueError, match="no oscillatory pole pair"):
        aj.dominant_pole_scale_factor(aperiodic, 0.75, 2e6)
