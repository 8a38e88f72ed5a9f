"""Sensing-element ODE (docs/models.md §2, eq. 1): diffrax solutions checked against closed forms,
the paper's approximate solution (11), and the solver's convergence order."""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from accel_jax._pendulum import (
    SensingElement,
    amplitude_frequency,
    cubic_approximation,
    initial_state,
    linear_solution,
    record_mask,
    sample_sensing_element,
    sample_times,
    solve_sensing_element,
)

OMEGA0 = 2 * np.pi  # rad/s
TS = sample_times(0.02, 256)  # 5.12 s, 5.12 periods


def test_linear_matches_closed_form():
    element = SensingElement(OMEGA0, 0.05)
    amplitude, phase = 0.02, 0.7
    angle0, rate0 = initial_state(element, amplitude, phase)
    solution = solve_sensing_element(element, angle0, rate0, TS, restoring="linear")
    exact = linear_solution(element, amplitude, phase, TS)
    # Dopri8 at rtol 1e-12 over 5 periods: ~1e-10 of the amplitude.
    assert np.max(np.abs(solution.angle - exact)) < 1e-11
    rate_exact = jax.vmap(jax.grad(lambda t: linear_solution(element, amplitude, phase, t)))(TS)
    assert np.max(np.abs(solution.rate - rate_exact)) < 1e-10 * OMEGA0
    assert solution.result == diffrax.RESULTS.successful


@pytest.mark.parametrize("phase", [0.0, 1.1])
def test_cubic_matches_paper_solution_11_to_its_order(phase):
    # (11) is the O(A³) Lindstedt solution: its frequency error is O(A⁴ ω0), so over a
    # fixed time the error relative to A scales as A⁴ — halving A divides it by 16.
    element = SensingElement(OMEGA0, 0.0)
    errors = []
    for amplitude in (0.08, 0.04):
        angle0, rate0 = initial_state(element, amplitude, phase, form="lindstedt")
        solution = solve_sensing_element(element, angle0, rate0, TS, restoring="cubic")
        approx = cubic_approximation(element, amplitude, phase, TS)
        errors.append(float(np.max(np.abs(solution.angle - approx))) / amplitude)
    assert errors[0] < 3e-6  # A⁴ ω0 t ≈ 4e-5 × 32 / (a few hundred): small but visible
    assert 12 < errors[0] / errors[1] < 20
    # Without the A²/16 frequency shift the error would be O(A²), much larger.
    amplitude = 0.08
    angle0, rate0 = initial_state(element, amplitude, phase, form="lindstedt")
    solution = solve_sensing_element(element, angle0, rate0, TS, restoring="cubic")
    unshifted = amplitude * np.sin(OMEGA0 * np.asarray(TS) + phase)
    assert np.max(np.abs(solution.angle - unshifted)) / amplitude > 100 * errors[0]


def test_sine_and_cubic_agree_to_fifth_order():
    # sin α − (α − α³/6) = α⁵/120: the two motions differ at O(A⁵) per unit time.
    element = SensingElement(OMEGA0, 0.0)
    differences = []
    for amplitude in (0.1, 0.05):
        angle0, rate0 = initial_state(element, amplitude, 0.4, form="lindstedt")
        sine = solve_sensing_element(element, angle0, rate0, TS, restoring="sine").angle
        cubic = solve_sensing_element(element, angle0, rate0, TS, restoring="cubic").angle
        differences.append(float(np.max(np.abs(sine - cubic))))
    assert 24 < differences[0] / differences[1] < 40  # 2⁵ = 32


def test_fixed_step_convergence_order():
    # Tsit5 is 5th order: halving the fixed step divides the global error by ~32.
    element = SensingElement(OMEGA0, 0.1)
    ts = sample_times(0.05, 40)
    angle0, rate0 = initial_state(element, 0.02, 0.3)
    exact = linear_solution(element, 0.02, 0.3, ts)
    errors = []
    for dt in (0.05, 0.025):
        solution = solve_sensing_element(
            element,
            angle0,
            rate0,
            ts,
            restoring="linear",
            solver=diffrax.Tsit5(),
            dt0=dt,
            stepsize_controller=diffrax.ConstantStepSize(),
        )
        errors.append(float(np.max(np.abs(solution.angle - exact))))
    order = np.log2(errors[0] / errors[1])
    assert 4.5 < order < 5.6, errors


def test_adaptive_error_decreases_with_tolerance():
    element = SensingElement(OMEGA0, 0.05)
    angle0, rate0 = initial_state(element, 0.02, 0.3)
    exact = linear_solution(element, 0.02, 0.3, TS)
    errors = [
        float(
            np.max(
                np.abs(
                    solve_sensing_element(
                        element, angle0, rate0, TS, restoring="linear", rtol=tol, atol=tol * 1e-3
                    ).angle
                    - exact
                )
            )
        )
        for tol in (1e-6, 1e-9, 1e-12)
    ]
    assert errors[0] > errors[1] > errors[2]
    assert errors[0] > 30 * errors[2]


def test_vmap_over_amplitude_phase_decay_frequency_and_interval():
    n = 6
    rng = np.random.default_rng(3)
    amplitude = rng.uniform(0.005, 0.03, n)
    phase = rng.uniform(0, 2 * np.pi, n)
    omega0 = rng.uniform(3.0, 9.0, n)
    xi = rng.uniform(0.0, 0.2, n)
    delta = rng.uniform(0.01, 0.03, n)

    def one(a, p, w, x, d):
        element = SensingElement(w, x)
        ts, alpha = sample_sensing_element(
            element, a, p, sample_interval=d, n_samples=64, restoring="linear", form="linear"
        )
        return alpha - linear_solution(element, a, p, ts)

    errors = eqx.filter_jit(jax.vmap(one))(amplitude, phase, omega0, xi, delta)
    assert errors.shape == (n, 64)
    assert np.max(np.abs(errors)) < 1e-11


def test_constant_angle_and_record_mask():
    element = SensingElement(OMEGA0, 0.0)
    ts, alpha = sample_sensing_element(
        element, 0.01, 0.0, sample_interval=0.1, n_samples=5, constant_angle=0.2
    )
    np.testing.assert_allclose(ts, 0.1 * np.arange(1, 6))
    # Lindstedt initial state: α(0) = A sin φ + (A³/192) sin 3φ = 0 at φ = 0.
    angle0, _ = initial_state(element, 0.01, 0.0, form="lindstedt")
    assert float(angle0) == 0.0
    assert np.all(np.abs(alpha - 0.2) <= 0.0101)
    mask = jax.vmap(lambda k: record_mask(8, k))(jnp.array([3, 8]))
    np.testing.assert_array_equal(mask.sum(axis=1), [3, 8])
    assert float(amplitude_frequency(element, 0.4)) == pytest.approx(OMEGA0 * 0.99)


def test_gradient_with_respect_to_frequency_matches_closed_form():
    amplitude, phase = 0.02, 0.5
    t_end = TS[-10:]

    def solved(omega0):
        element = SensingElement(omega0, 0.05)
        angle0, rate0 = initial_state(element, amplitude, phase)
        return jnp.sum(
            solve_sensing_element(element, angle0, rate0, t_end, restoring="linear").angle
        )

    def closed(omega0):
        return jnp.sum(linear_solution(SensingElement(omega0, 0.05), amplitude, phase, t_end))

    assert float(jax.grad(solved)(OMEGA0)) == pytest.approx(
        float(jax.grad(closed)(OMEGA0)), rel=1e-7
    )


def test_bad_input_raises():
    with pytest.raises(ValueError, match="natural_frequency"):
        SensingElement(-1.0, 0.0)
    with pytest.raises(ValueError, match="below natural_frequency"):
        SensingElement(1.0, 2.0)
    with pytest.raises(ValueError, match="decay_rate"):
        SensingElement(1.0, -0.1)
    element = SensingElement(OMEGA0, 0.0)
    with pytest.raises(ValueError, match="restoring"):
        solve_sensing_element(element, 0.0, 1.0, TS, restoring="tangent")
    with pytest.raises(ValueError, match="n_samples"):
        sample_times(0.01, 0)
    with pytest.raises(ValueError, match="sample_interval"):
        sample_times(-0.01, 10)
    with pytest.raises(ValueError, match="strictly increasing"):
        solve_sensing_element(element, 0.0, 1.0, jnp.array([0.1, 0.1, 0.2]))
    with pytest.raises(ValueError, match="initial_angle"):
        solve_sensing_element(element, jnp.nan, 1.0, TS)
    with pytest.raises(ValueError, match="form"):
        initial_state(element, 0.1, 0.0, form="quadratic")
    with pytest.raises(ValueError, match="record_length"):
        record_mask(8, 9)


def test_failed_solve_is_reported_not_silent():
    element = SensingElement(OMEGA0, 0.0)
    solution = solve_sensing_element(element, 0.0, 1.0, TS, max_steps=4, throw=False)
    assert solution.result != diffrax.RESULTS.successful
    assert np.all(np.isnan(solution.angle))
    with pytest.raises(Exception, match="max_steps"):
        solve_sensing_element(element, 0.0, 1.0, TS, max_steps=4)
