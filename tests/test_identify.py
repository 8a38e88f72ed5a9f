"""Tests of accel_jax._identify: the paper's identification methods (docs/models.md §1, eqs.
(7)-(16)) and the least-squares fit.

Records are made here from closed forms (the second-order step response, the two-exponential
aperiodic response, partial fractions of the third-order loop), independently of the
library's simulator and of its own model functions. The tests run in float64 (conftest).
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.signal
from helpers import central_difference

from accel_jax._identify import (
    IdentificationResult,
    fit_step_response,
    identify_aperiodic,
    identify_oscillatory,
    inflection_time_ratio,
    pickoff_gain_from_stops,
    scale_factor_from_fit,
)
from accel_jax._simulate.modal import _third_order_step, second_order_step

R = IdentificationResult
# The reference device (docs/models.md §1): T ≈ 2.90e-4 s, ξ ≈ 0.52; aperiodic ξ ≈ 2.07.
T_REF = 2.9e-4
XI_OSC = 0.52
XI_AP = 2.07
PICKOFF_AMPLIFIER_GAIN = 2.5e5 * 8.5  # k_dp k_y [V/m]
GAMMA = 2.9e-4 * 4.28e-3**2 / 7.09e-9  # m l²/J
GAINS = dict(pickoff_amplifier_gain=PICKOFF_AMPLIFIER_GAIN, shape_factor=GAMMA)
OSC_DURATION = 20e-3  # 9 periods; envelope e^{-ξ t/T} ≈ 3e-13 at the tail start
AP_DURATION = 30e-3  # slow mode e^{-t/T3} ≈ 6e-10 at the tail start


def oscillatory_record(ts, time_constant, damping_ratio, amplitude=1.0, initial=0.0, step=0.0):
    """Closed-form step response of amplitude/(T²p² + 2ξTp + 1), ξ < 1, step at `step`."""
    x = np.maximum(ts - step, 0.0) / time_constant
    beta = np.sqrt(1 - damping_ratio**2)
    response = 1 - np.exp(-damping_ratio * x) * (
        np.cos(beta * x) + damping_ratio / beta * np.sin(beta * x)
    )
    return initial + amplitude * response


def aperiodic_constants(time_constant, damping_ratio):
    """(T1, T3, T4) of T²p² + 2ξTp + 1 = (T3 p + 1)(T4 p + 1), ξ ≥ 1."""
    t1 = 2 * damping_ratio * time_constant
    root = np.sqrt(t1**2 / 4 - time_constant**2)
    return t1, t1 / 2 + root, t1 / 2 - root


def aperiodic_record(ts, t3, t4, amplitude=1.0, initial=0.0, delay=0.0):
    """Two-exponential step response of amplitude/((T3 p + 1)(T4 p + 1)), delayed."""
    tau = np.maximum(ts - delay, 0.0)
    response = 1 - (t3 * np.exp(-tau / t3) - t4 * np.exp(-tau / t4)) / (t3 - t4)
    return initial + amplitude * response


def grid(sample_rate, duration):
    return np.arange(int(round(duration * sample_rate))) / sample_rate


def relative_error(estimate, truth):
    return np.abs(np.asarray(estimate) / truth - 1)


# ---------------------------------------------------------------------------------------
# Oscillatory method


def test_oscillatory_recovery_and_convergence():
    # Linear interpolation of a crossing errs by at most dt²|U''|/(8|U'|); at a zero of a
    # damped sinusoid |U''/U'| = 2ξ/T, so δt ≤ dt² ξ/(4T): 4.5e-10 s at 1 MHz, i.e. 2e-7
    # of the period per crossing. The sampled extrema err by ≈ (ω dt)²/8 relative, mostly
    # cancelling in A1/A2. Both are O(dt²). The error depends on where the crossings fall
    # between samples, so each rate is run with 8 step times spread over one sample.
    rates = np.array([1e6, 3e6, 1e7])
    worst_t, worst_xi = [], []
    for rate in rates:
        ts = grid(rate, OSC_DURATION)
        steps = (np.arange(8) + 0.5) / 8 / rate
        estimates = [
            identify_oscillatory(
                ts, oscillatory_record(ts, T_REF, XI_OSC, step=step), step_time=step, **GAINS
            )
            for step in steps
        ]
        estimate = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *estimates)
        worst_t.append(np.max(relative_error(estimate.time_constant, T_REF)))
        worst_xi.append(np.max(relative_error(estimate.damping_ratio, XI_OSC)))
        # eq. (7): K̂_a = γ T̂² k_dp k_y exactly.
        np.testing.assert_allclose(
            estimate.scale_factor,
            GAMMA * estimate.time_constant**2 * PICKOFF_AMPLIFIER_GAIN,
            rtol=1e-14,
        )
        truth_k = GAMMA * T_REF**2 * PICKOFF_AMPLIFIER_GAIN
        assert np.max(relative_error(estimate.scale_factor, truth_k)) < 2.5 * worst_t[-1]
    worst_t, worst_xi = np.array(worst_t), np.array(worst_xi)
    # Measured (worst of 8): T 5.7e-7 (1 MHz) … 4.7e-9 (10 MHz), ξ 4.8e-7 … 1.8e-9.
    # Tolerances: the O(dt²) bound above (2 crossings + 0.37 × the ξ error, since
    # dT/T = −ξ²/(1−ξ²) dξ/ξ), rounded up.
    assert worst_t[0] < 2e-6 and worst_xi[0] < 2e-6
    assert worst_t[-1] < 2e-8 and worst_xi[-1] < 2e-8
    order = -np.polyfit(np.log(rates), np.log(worst_t), 1)[0]
    assert 1.7 < order < 2.4, (order, worst_t)


def test_oscillatory_variants_and_step_direction():
    ts = grid(1e6, OSC_DURATION)
    u = oscillatory_record(ts, T_REF, XI_OSC)
    linear = identify_oscillatory(ts, u, **GAINS)
    nearest = identify_oscillatory(ts, u, crossing="nearest", **GAINS)
    parabolic = identify_oscillatory(ts, u, extremum="parabolic", **GAINS)
    # Nearest-sample crossings err by up to dt/2 each (O(dt)), linear ones by O(dt²).
    assert relative_error(nearest.time_constant, T_REF) > 20 * relative_error(
        linear.time_constant, T_REF
    )
    assert relative_error(nearest.period, linear.period) < 1e-6 / linear.period
    # The parabolic vertex removes the O(dt²) bias of the largest sample.
    assert relative_error(parabolic.damping_ratio, XI_OSC) < 0.1 * relative_error(
        linear.damping_ratio, XI_OSC
    )
    # A step down from an offset gives the same estimate.
    down = identify_oscillatory(ts, 3.0 - 0.8 * u, **GAINS)
    np.testing.assert_allclose(down.time_constant, linear.time_constant, rtol=1e-9)
    np.testing.assert_allclose(down.damping_ratio, linear.damping_ratio, rtol=1e-9)
    np.testing.assert_allclose(down.steady_state, 2.2, rtol=1e-12)
    # A1 ≈ e^{-πξ/√(1−ξ²)}, A2 ≈ A1² for a unit step.
    overshoot = np.exp(-np.pi * XI_OSC / np.sqrt(1 - XI_OSC**2))
    np.testing.assert_allclose(parabolic.overshoot, overshoot, rtol=1e-8)
    np.testing.assert_allclose(parabolic.undershoot, overshoot**2, rtol=1e-8)


def test_oscillatory_ignores_noise_chatter():
    ts = grid(1e6, OSC_DURATION)
    clean = oscillatory_record(ts, T_REF, XI_OSC)
    sigma = 1e-4  # V, on a 1 V step
    noisy = clean + sigma * np.random.default_rng(0).standard_normal(ts.size)
    # The raw deviation changes sign thousands of times (noise around the settled level).
    raw_crossings = np.sum(np.diff(np.sign(noisy - clean[-1])) != 0)
    assert raw_crossings > 1000
    estimate = identify_oscillatory(ts, noisy, **GAINS)
    assert estimate.result == R.successful
    # Crossing jitter σ/|U'| ≈ 2e-7 s; ξ from noisy A1/A2 (σ/A2 ≈ 5e-3): errors of a few
    # 1e-3 are expected, an extra crossing would give errors of order 1.
    assert relative_error(estimate.time_constant, T_REF) < 5e-3
    assert relative_error(estimate.damping_ratio, XI_OSC) < 2e-2
    assert relative_error(estimate.period, 2 * np.pi * T_REF / np.sqrt(1 - XI_OSC**2)) < 1e-3


def test_oscillatory_high_damping_with_noise():
    # ξ = 0.8: the overshoot after t2 is 3.5e-6 of the step, below the noise σ = 1e-5, so
    # the hysteresis rule for t2 must not require it; and t2 itself is shallow, so the
    # half-period variant (two steep crossings) is far less noisy than t2 − t1.
    xi = 0.8
    ts = grid(1e6, 20e-3)
    clean = oscillatory_record(ts, T_REF, xi)
    period = 2 * np.pi * T_REF / np.sqrt(1 - xi**2)
    for variant in ("full", "half"):
        estimate = identify_oscillatory(ts, clean, period=variant, **GAINS)
        assert relative_error(estimate.period, period) < 1e-6
        assert relative_error(estimate.time_constant, T_REF) < 1e-6
    keys = jax.random.split(jax.random.key(5), 32)
    noisy = clean + 1e-5 * jax.vmap(lambda k: jax.random.normal(k, ts.shape))(keys)
    errors = {}
    for variant in ("full", "half"):
        estimate = jax.vmap(
            lambda u, v=variant: identify_oscillatory(ts, u, period=v, throw=False, **GAINS)
        )(noisy)
        assert bool(jnp.all(estimate.result == R.successful))
        errors[variant] = np.asarray(estimate.period) / period - 1
    assert np.std(errors["half"]) < np.std(errors["full"]) / 5
    assert abs(np.mean(errors["half"])) < 2e-3
    with pytest.raises(ValueError, match="'full' or 'half'"):
        identify_oscillatory(ts, clean, period="quarter", **GAINS)


def test_oscillatory_gradient_matches_finite_differences():
    # Records with the reference damped frequency, T(ξ) = T_REF √((1 − ξ²)/(1 − XI²)), so
    # dT/dξ = −Tξ/(1 − ξ²) is O(T) and a relative tolerance means something. The estimate
    # is piecewise smooth in ξ: kinks where a sample crosses the steady-state line (the
    # interpolating pair changes) or a new sample becomes the largest; a step of 1e-6 in ξ
    # moves a crossing by ~1e-9 s, far less than the 1e-6 s between samples.
    ts = jnp.asarray(grid(1e6, OSC_DURATION))

    def time_constant(xi):
        return T_REF * jnp.sqrt((1 - xi**2) / (1 - XI_OSC**2))

    def record(xi, times=ts):
        x = times / time_constant(xi)
        beta = jnp.sqrt(1 - xi**2)
        return 1 - jnp.exp(-xi * x) * (jnp.cos(beta * x) + xi / beta * jnp.sin(beta * x))

    def estimates(extremum):
        def estimate(xi):
            return identify_oscillatory(ts, record(xi), extremum=extremum, **GAINS)

        return [
            jax.jit(lambda xi: estimate(xi).time_constant),
            jax.jit(lambda xi: estimate(xi).damping_ratio),
        ]

    def check(functions, xi, step):
        for function in functions:
            expected = (function(xi + step) - function(xi - step)) / (2 * step)
            np.testing.assert_allclose(jax.grad(function)(xi), expected, rtol=1e-4)

    parabolic, sample = estimates("parabolic"), estimates("sample")
    for xi in (0.4, XI_OSC, 0.6):
        check(parabolic, xi, 1e-6)
    check(sample, XI_OSC, 1e-6)
    # dT̂/dξ is the true dT/dξ up to the O(dt²) discretisation error.
    np.testing.assert_allclose(
        jax.grad(parabolic[0])(XI_OSC), -T_REF * XI_OSC / (1 - XI_OSC**2), rtol=1e-3
    )

    # A sample next to the first crossing, inside the noise band (1e-6 of the step here):
    # the crossing time is still the interpolation between the bracketing pair, so moving
    # the sample across the band edge changes nothing discretely. (A least-squares line
    # through all in-band samples jumped there by O(dt² U''/U') ≈ 1e-9 s.)
    sample_index = 722  # t1 = 0.719 ms at ξ = 0.52, 0.727 ms at 0.54

    def deviation(xi):  # of that sample from the steady state, in the record's units
        return float(record(xi, jnp.asarray(ts[sample_index]))) - 1.0

    def solve(target, low=0.52, high=0.54):
        # t1 grows with ξ, so the deviation at a fixed time falls through zero (bisection).
        for _ in range(60):
            middle = 0.5 * (low + high)
            low, high = (middle, high) if deviation(middle) > target else (low, middle)
        return 0.5 * (low + high)

    on_line = solve(0.0)
    band_edge = solve(1e-6)
    assert abs(band_edge - on_line) > 1e-7
    check(parabolic, band_edge, 0.5 * abs(band_edge - on_line))


# ---------------------------------------------------------------------------------------
# Aperiodic method


def test_aperiodic_recovery_and_refinement():
    t1, t3, t4 = aperiodic_constants(T_REF, XI_AP)
    errors = {}
    for rate in (1e6, 4e6):
        ts = grid(rate, AP_DURATION)
        estimate = identify_aperiodic(ts, aperiodic_record(ts, t3, t4), **GAINS)
        assert estimate.result == R.successful
        errors[rate] = (
            relative_error(estimate.t1, t1),
            relative_error(estimate.t2, T_REF),
            relative_error(estimate.t2_initial, T_REF),
        )
        # Step 8 is solved: the closed-form inflection time at (T1, T2) is T0.
        residual = inflection_time_ratio(2 * estimate.t2 / estimate.t1) * estimate.t1
        assert abs(float(residual - estimate.inflection_time)) < 1e-12 * t1
        assert abs(float(estimate.root_residual)) < 1e-12 * t1
        np.testing.assert_allclose(estimate.t3 + estimate.t4, estimate.t1, rtol=1e-12)
        np.testing.assert_allclose(estimate.t3 * estimate.t4, estimate.t2**2, rtol=1e-12)
        np.testing.assert_allclose(estimate.damping_ratio, XI_AP, rtol=1e-3)
        np.testing.assert_allclose(
            estimate.scale_factor, GAMMA * estimate.t2**2 * PICKOFF_AMPLIFIER_GAIN, rtol=1e-14
        )
    # T0 = T3 T4 ln(T3/T4)/(T3 − T4) at 1 MHz to O(dt²).
    t0 = t3 * t4 * np.log(t3 / t4) / (t3 - t4)
    np.testing.assert_allclose(estimate.inflection_time, t0, rtol=1e-5)
    # Measured at 1 MHz: T1 2.0e-6, refined T2 1.4e-5, tangent T2 (15) 0.154; all O(dt²):
    # T1 = (U_ss − U0)/tg α is exact for this model, and the errors come from locating the
    # derivative peak (parabolic vertex, O(dt²)) and the central difference (O(dt²/T4²)).
    t1_error, t2_error, t2_initial_error = errors[1e6]
    assert t1_error < 1e-5
    assert t2_error < 5e-5
    assert t2_initial_error > 0.1  # the tangent construction (15) alone is 15 % off
    assert t2_error < 1e-3 * t2_initial_error  # the refinement helps by > 1000×
    for before, after in zip(errors[1e6][:2], errors[4e6][:2], strict=True):
        assert after < before / 10  # 16× for O(dt²)


def test_aperiodic_lag_correction_and_direction():
    t1, t3, t4 = aperiodic_constants(T_REF, XI_AP)
    ts = grid(1e6, AP_DURATION)
    lag = 2e-5  # T_f + T_dm of the reference device
    delayed = aperiodic_record(ts, t3, t4, delay=lag)
    corrected = identify_aperiodic(ts, delayed, lag_correction=lag, **GAINS)
    uncorrected = identify_aperiodic(ts, delayed, **GAINS)
    assert relative_error(corrected.t2, T_REF) < 5e-5
    assert relative_error(uncorrected.t2, T_REF) > 100 * relative_error(corrected.t2, T_REF)
    np.testing.assert_allclose(
        corrected.inflection_time_measured - corrected.inflection_time, lag, rtol=1e-12
    )
    # A step down from an offset (and a step time inside the record) gives the same T2.
    start = 1e-3
    down = 5.0 - 2.0 * aperiodic_record(ts, t3, t4, delay=start)
    estimate = identify_aperiodic(ts, down, step_time=start, **GAINS)
    assert relative_error(estimate.t2, T_REF) < 5e-5
    assert float(estimate.max_slope) < 0


def test_aperiodic_critical_damping():
    # ξ = 1: T1 = 2 T2 and T0 = T2 (the paper's special case); U = 1 − (1 + t/T) e^{−t/T}.
    ts = grid(1e6, AP_DURATION)
    x = ts / T_REF
    estimate = identify_aperiodic(ts, 1 - (1 + x) * np.exp(-x), **GAINS)
    assert estimate.result == R.successful
    assert relative_error(estimate.t2, T_REF) < 1e-4
    assert relative_error(estimate.t1, 2 * T_REF) < 1e-5


def test_savgol_weights_match_scipy():
    from accel_jax._identify import _savgol_kernels

    for window in (5, 9, 31):
        value_w, slope_w = _savgol_kernels(window)
        # scipy's coefficients are convolution weights (reversed); ours are per offset.
        np.testing.assert_allclose(
            value_w, scipy.signal.savgol_coeffs(window, 3, use="dot"), atol=1e-13
        )
        np.testing.assert_allclose(
            slope_w, scipy.signal.savgol_coeffs(window, 3, deriv=1, use="dot"), atol=1e-13
        )


def test_aperiodic_savgol_exact_and_noisy():
    t1, t3, t4 = aperiodic_constants(T_REF, XI_AP)
    ts = grid(1e6, AP_DURATION)
    clean = aperiodic_record(ts, t3, t4)
    central = identify_aperiodic(ts, clean, **GAINS)
    savgol = identify_aperiodic(ts, clean, derivative="savgol", smoothing_window=31, **GAINS)
    averaged = identify_aperiodic(ts, clean, smoothing_window=31, **GAINS)
    # Noise-free: the local cubic leaves the slope peak (a quadratic in t) unbiased, while a
    # moving average of the same width flattens it.
    assert relative_error(savgol.t2, T_REF) < 1e-4
    assert relative_error(savgol.t2, T_REF) < 3 * relative_error(central.t2, T_REF) + 1e-6
    assert relative_error(averaged.t2, T_REF) > 10 * relative_error(savgol.t2, T_REF)
    # With noise (σ = 1e-5 of a unit step): the local cubic scatters far less than the raw
    # central difference.
    keys = jax.random.split(jax.random.key(3), 32)
    noisy = clean + 1e-5 * jax.vmap(lambda k: jax.random.normal(k, ts.shape))(keys)

    def t2_of(record, **kw):
        return identify_aperiodic(ts, record, **GAINS, **kw).t2

    raw = jax.vmap(t2_of)(noisy) / T_REF - 1
    fitted = jax.vmap(lambda r: t2_of(r, derivative="savgol", smoothing_window=61))(noisy)
    fitted = fitted / T_REF - 1
    assert float(jnp.std(fitted)) < float(jnp.std(raw)) / 4
    assert abs(float(jnp.mean(fitted))) < 3 * float(jnp.std(fitted)) / np.sqrt(32) + 1e-4


def test_aperiodic_savgol_bad_input():
    t1, t3, t4 = aperiodic_constants(T_REF, XI_AP)
    ts = grid(1e6, AP_DURATION)
    record = aperiodic_record(ts, t3, t4)
    with pytest.raises(ValueError, match="at least 5 samples"):
        identify_aperiodic(ts, record, derivative="savgol", smoothing_window=3, **GAINS)
    with pytest.raises(ValueError, match="'central' or 'savgol'"):
        identify_aperiodic(ts, record, derivative="spline", **GAINS)
    warped = np.asarray(ts) + 0.3e-6 * np.sin(np.arange(ts.shape[0]))
    with pytest.raises(ValueError, match="uniform time grid"):
        identify_aperiodic(warped, record, derivative="savgol", smoothing_window=9, **GAINS)


def test_inflection_time_ratio():
    # Against T3 T4 ln(T3/T4)/(T3 − T4) / T1 computed directly.
    ratio = np.array([1e-3, 0.1, 0.5, 0.9, 0.999999, 1.0])
    t1 = 1.0
    t3 = t1 / 2 * (1 + np.sqrt(1 - ratio**2))
    t4 = t1 / 2 * (1 - np.sqrt(1 - ratio**2))
    with np.errstate(divide="ignore", invalid="ignore"):
        direct = t3 * t4 * np.log(t3 / t4) / (t3 - t4)
    direct[-1] = 0.5  # the ξ = 1 limit t_inflection = T2 = T1/2
    ratio_fn = jax.jit(inflection_time_ratio)
    np.testing.assert_allclose(ratio_fn(jnp.asarray(ratio)), direct, rtol=1e-9)
    assert np.all(np.diff(np.asarray(ratio_fn(jnp.linspace(0, 1, 1001)))) > 0)


# ---------------------------------------------------------------------------------------
# Stops, eq. (11)


def test_pickoff_gain_from_stops():
    gain, h = PICKOFF_AMPLIFIER_GAIN, 1.9e-6
    offset = 0.013
    # Symmetric stops: the offset cancels exactly.
    estimate = pickoff_gain_from_stops(gain * h + offset, -gain * h + offset, h, h)
    np.testing.assert_allclose(estimate, gain, rtol=1e-14)
    # Asymmetric stops, no offset: exact.
    estimate = pickoff_gain_from_stops(gain * 2e-6, -gain * 1.5e-6, 2e-6, 1.5e-6)
    np.testing.assert_allclose(estimate, gain, rtol=1e-14)
    with pytest.raises(ValueError, match="h_minus"):
        pickoff_gain_from_stops(4.0, -4.0, h, -h)
    with pytest.raises(ValueError, match="u_minus"):
        pickoff_gain_from_stops(4.0, 4.0, h, h)
    with pytest.raises(ValueError, match="u_plus"):
        pickoff_gain_from_stops(-4.0, -5.0, h, h)
    # Traced values are not checked and pass through.
    traced = jax.jit(pickoff_gain_from_stops)(4.0, -4.0, h, h)
    np.testing.assert_allclose(traced, 4.0 / h, rtol=1e-14)


# ---------------------------------------------------------------------------------------
# Least-squares fit


def test_second_order_step_is_smooth_through_critical_damping():
    tau = jnp.asarray(grid(1e6, 3e-3))
    x = np.asarray(tau) / T_REF
    step = jax.jit(second_order_step)
    for xi in (0.3, XI_OSC, 0.9999):
        np.testing.assert_allclose(
            step(tau, T_REF, xi), oscillatory_record(np.asarray(tau), T_REF, xi), atol=1e-13
        )
    np.testing.assert_allclose(step(tau, T_REF, 1.0), 1 - (1 + x) * np.exp(-x), atol=1e-13)
    for xi in (1.0001, 1.5, XI_AP, 10.0):
        _, t3, t4 = aperiodic_constants(T_REF, xi)
        np.testing.assert_allclose(
            step(tau, T_REF, xi), aperiodic_record(np.asarray(tau), t3, t4), atol=1e-12
        )

    @jax.jit
    def total(xi):
        return jnp.sum(second_order_step(tau, T_REF, xi))

    grad = jax.jit(jax.grad(total))
    for xi in (1 - 1e-7, 1.0, 1 + 1e-7, 0.99, 1.01):
        assert np.isfinite(grad(xi))
        np.testing.assert_allclose(grad(xi), central_difference(total, xi, 1e-5), rtol=1e-6)
    # The derivative is continuous across ξ = 1.
    np.testing.assert_allclose(grad(1 - 1e-7), grad(1 + 1e-7), rtol=1e-6)


def third_order_record(ts, time_constant, damping_ratio, torquer, feedback, step=0.0):
    """Step response of K/[(T²p² + 2ξTp + 1 − K)(T_dm p + 1) + K] by partial fractions."""
    denominator = np.polymul(
        [time_constant**2, 2 * damping_ratio * time_constant, 1 - feedback], [torquer, 1.0]
    )
    denominator = np.polyadd(denominator, [feedback])
    poles = np.roots(denominator)
    slope = np.polyder(denominator)
    tau = np.maximum(ts - step, 0.0)
    # Y(s) = K/(s D(s)), D(0) = 1: residue K at 0, K/(p D'(p)) at each pole p.
    response = feedback + sum(
        feedback / (p * np.polyval(slope, p)) * np.exp(p * tau) for p in poles
    )
    return np.where(ts > step, response.real, 0.0)


def test_third_order_model_matches_partial_fractions():
    ts = jnp.asarray(grid(1e6, 3e-3))
    step = 2.5e-7 + 1e-4  # between samples
    model = jax.jit(_third_order_step)(ts, step, T_REF, XI_OSC, 1e-5, 0.996)
    expected = third_order_record(np.asarray(ts), T_REF, XI_OSC, 1e-5, 0.996, step)
    # The library's response is normalised to unit DC gain.
    np.testing.assert_allclose(0.996 * model, expected, atol=1e-12)


def test_fit_second_order_uncertainty_is_calibrated():
    ts = grid(1e6, 5e-3)
    step = 1e-4
    sigma = 2e-3
    clean = oscillatory_record(ts, T_REF, XI_OSC, amplitude=0.996, initial=0.01, step=step)
    noise = np.random.default_rng(1).standard_normal((20, ts.size))
    records = jnp.asarray(clean + sigma * noise)
    fit = jax.vmap(lambda u: fit_step_response(ts, u, step_time=step))(records)
    assert np.all(fit.result == R.successful)
    z_t = (fit.time_constant - T_REF) / fit.time_constant_std
    z_xi = (fit.damping_ratio - XI_OSC) / fit.damping_ratio_std
    assert abs(float(z_t[0])) < 3 and abs(float(z_xi[0])) < 3
    # The covariance σ̂²(JᵀJ)⁻¹ predicts the scatter over seeds.
    assert 0.5 < np.std(z_t) < 1.6 and 0.5 < np.std(z_xi) < 1.6
    np.testing.assert_allclose(fit.residual_rms, sigma, rtol=0.05)
    np.testing.assert_allclose(fit.gain, 0.996, rtol=1e-3)
    np.testing.assert_allclose(fit.offset, 0.01, atol=1e-3)
    np.testing.assert_allclose(fit.torquer_time_constant, 0.0)
    assert fit.covariance.shape == (20, 4, 4)
    # K̂_a = γ T² k_dp k_y with relative std 2 σ_T/T.
    k, k_std = scale_factor_from_fit(fit, PICKOFF_AMPLIFIER_GAIN, GAMMA)
    np.testing.assert_allclose(k_std / k, 2 * fit.time_constant_std / fit.time_constant)
    truth = GAMMA * T_REF**2 * PICKOFF_AMPLIFIER_GAIN
    assert 0.5 < np.std((k - truth) / k_std) < 1.6


def test_fit_second_order_aperiodic_and_third_order_lag():
    # The batched order-2 fit (compiled once for 20 records of 5000 samples) serves both.
    ts = grid(1e6, 5e-3)
    step = 1e-4
    sigma = 1e-4
    rng = np.random.default_rng(2)

    def fit_batch(times, records):
        return jax.vmap(lambda u: fit_step_response(times, u, step_time=step))(jnp.asarray(records))

    # One closed form covers ξ > 1: aperiodic records are fitted like oscillatory ones.
    _, t3, t4 = aperiodic_constants(T_REF, XI_AP)
    ts_ap = grid(2.5e5, 20e-3)  # 5000 samples
    aperiodic = aperiodic_record(ts_ap, t3, t4, delay=step)
    fit = fit_batch(ts_ap, aperiodic + sigma * rng.standard_normal((20, ts.size)))
    assert np.all(fit.result == R.successful)
    z_t = (fit.time_constant - T_REF) / fit.time_constant_std
    z_xi = (fit.damping_ratio - XI_AP) / fit.damping_ratio_std
    assert abs(float(z_t[0])) < 3 and abs(float(z_xi[0])) < 3
    assert 0.5 < np.std(z_t) < 1.6 and 0.5 < np.std(z_xi) < 1.6

    # Order 3 recovers the torquer lag T_dm that the second-order model neglects.
    torquer, feedback = 1e-5, 0.996
    clean = third_order_record(ts, T_REF, XI_OSC, torquer, feedback, step)
    record = clean + sigma * rng.standard_normal(ts.size)
    fit3 = fit_step_response(ts, record, order=3, step_time=step, feedback_fraction=feedback)
    assert fit3.result == R.successful
    torquer_std = float(np.sqrt(fit3.covariance[2, 2]))
    assert abs(float(fit3.torquer_time_constant) - torquer) < 3 * torquer_std
    assert torquer_std < 0.2 * torquer
    assert abs(float((fit3.time_constant - T_REF) / fit3.time_constant_std)) < 3
    assert abs(float((fit3.damping_ratio - XI_OSC) / fit3.damping_ratio_std)) < 3
    np.testing.assert_allclose(fit3.gain, feedback, rtol=1e-3)
    # Without a lag the fit converges to the boundary T_dm ≈ 0 (within its uncertainty).
    no_lag = oscillatory_record(ts, T_REF, XI_OSC, amplitude=feedback, step=step)
    no_lag = no_lag + 10 * sigma * np.random.default_rng(5).standard_normal(ts.size)
    fit0 = fit_step_response(ts, no_lag, order=3, step_time=step, feedback_fraction=feedback)
    assert float(fit0.torquer_time_constant) < 3 * float(np.sqrt(fit0.covariance[2, 2]))
    assert abs(float((fit0.time_constant - T_REF) / fit0.time_constant_std)) < 3
    # Second-order fits of such records are biased by many standard deviations.
    fit2 = fit_batch(ts, clean + sigma * rng.standard_normal((20, ts.size)))
    assert np.all(np.abs((fit2.damping_ratio - XI_OSC) / fit2.damping_ratio_std) > 10)


def test_fit_third_order_with_known_output_filter():
    # Data from the library's closed-loop simulator (an independent model: the physical
    # state space with T_dm in the loop and T_f on the output), noise-free.
    import accel_jax as aj

    ref = aj.ServoParams.reference()
    ts = grid(1e6, 10e-3)
    record = aj.simulate_linear(ref, jnp.asarray(ts), 1.0)
    feedback = float(aj.closed_loop_test_gain(ref))
    gain, gamma = float(ref.pickoff_gain * ref.amplifier_gain), float(aj.shape_factor(ref))

    def error_percent(fit):
        estimate, _ = scale_factor_from_fit(fit, gain, gamma)
        return float(aj.relative_error_percent(estimate, aj.scale_factor(ref)))

    known = fit_step_response(
        ts,
        record,
        order=3,
        feedback_fraction=feedback,
        filter_time_constant=float(ref.filter_time_constant),
    )
    # The model is then exact: residuals at rounding level, T_dm and K_a recovered.
    assert float(known.residual_rms) < 1e-10
    np.testing.assert_allclose(known.torquer_time_constant, ref.torquer_time_constant, rtol=1e-6)
    assert abs(error_percent(known)) < 1e-5
    # Ignoring the filter, the fit folds T_f into T_dm and biases K_a by about −0.43 %.
    ignored = fit_step_response(ts, record, order=3, feedback_fraction=feedback)
    np.testing.assert_allclose(
        ignored.torquer_time_constant,
        ref.torquer_time_constant + ref.filter_time_constant,
        rtol=0.05,
    )
    assert error_percent(ignored) < -0.2
    with pytest.raises(ValueError, match="T_f >= 0"):
        fit_step_response(ts, record, order=3, filter_time_constant=-1e-5)
    with pytest.raises(ValueError, match="needs order=3"):
        fit_step_response(ts, record, order=2, filter_time_constant=1e-5)
    warped = ts + 0.3e-6 * np.sin(np.arange(ts.size))
    with pytest.raises(ValueError, match="order=3. needs a uniform time grid"):
        fit_step_response(warped, record, order=3)


# ---------------------------------------------------------------------------------------
# Transforms


def test_vmap_matches_loop_and_no_retrace():
    ts = grid(1e6, OSC_DURATION)
    records = np.stack([oscillatory_record(ts, T_REF, xi) for xi in (0.3, XI_OSC, 0.7)])
    batched = jax.vmap(lambda u: identify_oscillatory(ts, u, **GAINS))(jnp.asarray(records))
    for i, record in enumerate(records):
        single = identify_oscillatory(ts, record, **GAINS)
        for name in ("time_constant", "damping_ratio", "t1", "t2", "scale_factor"):
            np.testing.assert_allclose(getattr(batched, name)[i], getattr(single, name), rtol=1e-12)

    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def scale_factor(u, gain):
        return identify_oscillatory(
            ts, u, pickoff_amplifier_gain=gain, shape_factor=GAMMA
        ).scale_factor

    first = scale_factor(jnp.asarray(records[0]), jnp.asarray(1.0))
    second = scale_factor(jnp.asarray(records[1]), jnp.asarray(2.0))
    assert float(first) != float(second)


# ---------------------------------------------------------------------------------------
# Bad input


def test_bad_records_give_result_codes_and_clear_errors():
    ts = grid(1e6, OSC_DURATION)
    oscillatory = oscillatory_record(ts, T_REF, XI_OSC)

    def code(u, ts=ts, **kwargs):
        return identify_oscillatory(ts, u, throw=False, **GAINS, **kwargs)

    # Aperiodic data to the oscillatory method.
    _, t3, t4 = aperiodic_constants(T_REF, XI_AP)
    aperiodic = aperiodic_record(ts, t3, t4)
    estimate = code(aperiodic)
    assert estimate.result == R.not_oscillatory
    assert all(np.isfinite(leaf) for leaf in jax.tree_util.tree_leaves(estimate))
    with pytest.raises(Exception, match="use identify_aperiodic"):
        identify_oscillatory(ts, aperiodic, **GAINS)

    # Clipped (saturated) output: a flat top at the overshoot.
    clipped = np.minimum(oscillatory, 1.1)
    assert code(clipped).result == R.saturated
    noisy_clipped = clipped + 1e-5 * np.random.default_rng(3).standard_normal(ts.size)
    assert code(noisy_clipped, saturation_level=1.1).result == R.saturated

    # NaN: a clear error, or with throw=False a code and finite numbers.
    broken = oscillatory.copy()
    broken[100] = np.nan
    with pytest.raises(Exception, match="NaN"):
        identify_oscillatory(ts, broken, **GAINS)
    estimate = code(broken)
    assert estimate.result == R.non_finite
    assert all(np.isfinite(leaf) for leaf in jax.tree_util.tree_leaves(estimate))

    # A record that stops before settling.
    # A record that stops before settling (2 ms at 10 MHz: the same 20000 samples).
    short_ts = grid(1e7, 2e-3)
    assert code(oscillatory_record(short_ts, T_REF, XI_OSC), ts=short_ts).result == R.too_short

    # Structure errors at call time.
    with pytest.raises(ValueError, match="same length"):
        identify_oscillatory(ts, oscillatory[:-1], **GAINS)
    with pytest.raises(ValueError, match="same length"):
        identify_aperiodic(ts[:-1], oscillatory, **GAINS)
    with pytest.raises(ValueError, match="vmap"):
        identify_oscillatory(ts, np.stack([oscillatory, oscillatory]), **GAINS)
    with pytest.raises(ValueError, match="crossing"):
        identify_oscillatory(ts, oscillatory, crossing="cubic", **GAINS)
    with pytest.raises(ValueError, match="uniform"):
        fit_step_response(np.r_[ts[:10], ts[10:] * 1.01], oscillatory, order=3)


def test_aperiodic_method_rejects_oscillatory_and_rootless_records():
    ts = grid(1e6, AP_DURATION)
    oscillatory = oscillatory_record(ts, T_REF, XI_OSC)
    estimate = identify_aperiodic(ts, oscillatory, throw=False, **GAINS)
    assert estimate.result == R.not_aperiodic
    with pytest.raises(Exception, match="use identify_oscillatory"):
        identify_aperiodic(ts, oscillatory, **GAINS)
    # A lag correction larger than the inflection time leaves step 8 without a root.
    _, t3, t4 = aperiodic_constants(T_REF, XI_AP)
    estimate = identify_aperiodic(
        ts, aperiodic_record(ts, t3, t4), lag_correction=1e-3, throw=False, **GAINS
    )
    assert estimate.result == R.no_root
    assert all(np.isfinite(leaf) for leaf in jax.tree_util.tree_leaves(estimate))


def test_weighted_moments_match_plain_sums_and_differentiate():
    """The crossing fit's one-pass moment sums (a variadic reduction with a hand-written
    JVP): the values of five `jnp.sum`s, and derivatives that pass JAX's numerical
    gradient check in forward and reverse mode, batched too."""
    from jax.test_util import check_grads

    from accel_jax._identify import _weighted_moments

    rng = np.random.default_rng(3)
    w, x, y = (jnp.asarray(rng.uniform(0.1, 1.0, (3, 257))) for _ in range(3))
    x, y = x - 0.5, y - 0.4
    expected = jnp.stack(
        [
            jnp.sum(w, -1),
            jnp.sum(w * x, -1),
            jnp.sum(w * y, -1),
            jnp.sum(w * x * x, -1),
            jnp.sum(w * x * y, -1),
        ]
    )
    got = jnp.stack(jax.vmap(_weighted_moments)(w, x, y))
    np.testing.assert_allclose(got, expected, rtol=1e-13, atol=1e-13)
    check_grads(_weighted_moments, (w[0], x[0], y[0]), order=1, modes=["fwd", "rev"])
    check_grads(jax.vmap(_weighted_moments), (w, x, y), order=1, modes=["fwd", "rev"])


def test_index_searches_and_largest_between_match_their_definitions():
    """`_first`/`_last` (masked min/max over float indices) and `_largest_between` (a masked
    max) against NumPy's definitions: empty masks, an end sample, ties, no sample between."""
    from accel_jax._identify.oscillatory import _largest_between
    from accel_jax._identify.record import _first, _last

    rng = np.random.default_rng(2)
    masks = [rng.random(501) < p for p in (0.0, 0.002, 0.3, 1.0)]
    masks.append(np.zeros(501, bool))
    masks[-1][-1] = True
    for mask in masks:
        hits = np.flatnonzero(mask)
        for search, expected in ((_first, hits[:1]), (_last, hits[-1:])):
            k, found = jax.jit(search)(jnp.asarray(mask))
            assert bool(found) == bool(hits.size)
            assert int(k) == (int(expected[0]) if hits.size else 0)
            assert k.dtype == jnp.int32
    ts = jnp.arange(501) * 1e-3
    values = jnp.asarray(np.round(rng.normal(size=501), 1))  # rounded: ties
    for start, stop in ((0.1, 0.3), (-1.0, 1.0), (0.2005, 0.2009), (0.3, 0.1)):
        inside = (np.asarray(ts) > start) & (np.asarray(ts) < stop)
        expected = np.max(np.asarray(values)[inside]) if inside.any() else 0.0
        assert float(_largest_between(ts, values, start, stop, "sample")) == expected


@pytest.mark.parametrize("finite", [True, False])
def test_step_at_the_first_sample_given_statically_is_step_time_ts0(finite):
    """`step_time=None` in the record summary and the oscillatory estimate (the Monte Carlo
    kernel's records: the step at the first sample, known before tracing) gives what
    `step_time=ts[0]` gives, field for field, for a noisy oscillatory record and for a
    non-finite one (its placeholders)."""
    from accel_jax._identify.oscillatory import _oscillatory_estimate

    ts = jnp.arange(5001) * 2e-6  # 10 ms: settled
    u = second_order_step(ts, T_REF, 0.52) + 1e-4 * jax.random.normal(jax.random.key(4), ts.shape)
    if not finite:
        u = u.at[700].set(jnp.nan)
    args = (2.1e6, 0.75)
    rest = (None, jnp.inf, 1000, "linear", "sample", "full", 128)
    given, exact_given = _oscillatory_estimate(ts, u, *args, ts[0], *rest)
    static, exact_static = _oscillatory_estimate(ts, u, *args, None, *rest)
    assert bool(exact_given) == bool(exact_static)
    for name in ("steady_state", "t1", "t2", "overshoot", "undershoot", "scale_factor"):
        assert float(getattr(static, name)) == float(getattr(given, name)), name
    assert static.result == given.result
    assert (given.result == R.successful) == finite


def test_a_non_finite_sample_anywhere_is_flagged_under_vmap():
    """One NaN, +inf or −inf at any position — first, last, inside a vector lane's
    remainder — of any record in a vmapped batch of 16 (the Monte Carlo kernel's chunk)
    gives `non_finite` for that record only, with finite placeholders. (A max reduction
    does not propagate NaN on XLA:CPU: finiteness read from the largest |U| failed this.)"""
    from accel_jax._identify.oscillatory import _oscillatory_estimate

    ts = jnp.arange(5001) * 2e-6
    clean = second_order_step(ts, T_REF, 0.52)
    positions = [0, 1, 7, 15, 16, 2500, 4990, 4999, 5000]
    bad = [jnp.nan, jnp.inf, -jnp.inf]
    records = [clean]
    for i, position in enumerate(positions):
        records.append(clean.at[position].set(bad[i % 3]))
    records += [clean] * (16 - len(records))
    batch = jnp.stack(records[:16])
    rest = (None, None, jnp.inf, 1000, "linear", "sample", "full", 128)
    estimate, _ = jax.jit(jax.vmap(lambda u: _oscillatory_estimate(ts, u, 2.1e6, 0.75, *rest)))(
        batch
    )
    flagged = np.asarray(estimate.result == R.non_finite)
    successful = np.asarray(estimate.result == R.successful)
    expected = np.array([1 <= i <= len(positions) for i in range(16)])
    np.testing.assert_array_equal(flagged, expected)
    np.testing.assert_array_equal(successful, ~expected)
    for name in ("steady_state", "t1", "t2", "overshoot", "scale_factor"):
        assert bool(jnp.all(jnp.isfinite(getattr(estimate, name)))), name
