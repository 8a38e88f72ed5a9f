"""Tests of accel_jax._simulate against closed forms, scipy, finite differences and each
other. Float64 (tests/conftest.py). Records are short (≤ 2 ms at 1 MHz) to keep this fast."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.signal

from accel_jax._params import ServoParams
from accel_jax._servo import (
    closed_loop_test_gain,
    damping_ratio,
    loop_stiffness,
    scale_factor,
    time_constant,
    transfer_function,
)
from accel_jax._simulate import (
    discretise,
    equilibrium_state,
    simulate_linear,
    simulate_nonlinear,
    state_space,
    step_response,
)

SAMPLE_RATE = 1e6  # Hz
TS = jnp.arange(1001) / SAMPLE_RATE  # 1 ms: the shared grid (one compilation per simulator)
T = np.asarray(TS)
# A time-varying external moment [N·m]: a 3 kHz ripple and a step, around the reference 1e-6.
MOMENT = 1e-6 + 5e-7 * np.sin(2 * np.pi * 3e3 * T) + 2e-7 * (T > 4e-4)


def _reference(**overrides):
    return ServoParams.reference(**overrides)


def _relative_max_error(x, y):
    x, y = np.asarray(x), np.asarray(y)
    return np.max(np.abs(x - y)) / np.max(np.abs(y))


def _pickoff_per_radian(params):
    return float(params.pickoff_gain * params.amplifier_gain * params.pendulum_length)


# ----------------------------------------------------------------------------------------
# Linear simulator against independent references
# ----------------------------------------------------------------------------------------


def test_linear_matches_analytic_second_order_step():
    # T_dm = T_f = 0: W_test = K_test/(T²p² + 2ξTp + 1), docs/models.md eq. (3). M_ext is constant
    # and the device starts at its equilibrium, so only the test step shows.
    params = _reference(torquer_time_constant=0.0, filter_time_constant=0.0)
    test_voltage = 1.3
    u_out = simulate_linear(params, TS, test_voltage)
    period, xi = float(time_constant(params)), float(damping_ratio(params))
    gain = float(closed_loop_test_gain(params))
    offset = _pickoff_per_radian(params) * float(params.external_moment / loop_stiffness(params))
    omega_d = math.sqrt(1 - xi**2) / period
    envelope = np.exp(-xi * T / period)
    oscillation = np.cos(omega_d * T) + xi / math.sqrt(1 - xi**2) * np.sin(omega_d * T)
    expected = offset + gain * test_voltage * (1 - envelope * oscillation)
    assert _relative_max_error(u_out, expected) < 1e-12


def _scaled_tf(numerator, denominator, time_unit):
    # p = s/τ: coefficients of p^k become c_k/τ^k, so the polynomials are O(1) for scipy.
    def scale(coefficients):
        coefficients = np.asarray(coefficients, dtype=float)
        powers = np.arange(len(coefficients))[::-1]
        return coefficients / time_unit**powers

    return scale(numerator), scale(denominator)


@pytest.mark.parametrize("lags", [(1e-5, 1e-5), (3e-5, 4e-6)])
def test_linear_matches_scipy_transfer_functions(lags):
    # Independent check of the state-space assembly: the closed-loop transfer functions
    # of _servo (docs/models.md eq. (1)) with the output filter appended, discretised by scipy.
    torquer_lag, filter_lag = lags
    params = _reference(torquer_time_constant=torquer_lag, filter_time_constant=filter_lag)
    rng = np.random.default_rng(0)
    n = TS.shape[0]
    levels = lambda scale: np.repeat(rng.normal(scale=scale, size=n // 50 + 1), 50)[:n]  # noqa: E731
    test_voltage = levels(1.0)
    acceleration = levels(2.0)
    moment = levels(1e-6)
    # scipy starts from rest: zero acceleration and moment at t_0 give the zero equilibrium.
    acceleration[:50] = 0.0
    moment[:50] = 0.0
    u_out = simulate_linear(params, TS, test_voltage, acceleration, moment)

    numerator, denominator = (np.asarray(c) for c in transfer_function(params))
    denominator = np.polymul(denominator, [filter_lag, 1.0])
    feedback = float(params.torquer_gain) * _pickoff_per_radian(params)
    pendulosity = float(params.pendulum_mass * params.pendulum_length)
    time_unit = 1e-4
    dt = 1 / SAMPLE_RATE
    expected = np.zeros(n)
    for tf_numerator, signal in (
        ([feedback], test_voltage),
        (numerator, acceleration),
        (numerator / pendulosity, moment),
    ):
        # Controllable canonical form, then ZOH: the discrete polynomial form would lose
        # ~1e-8 to the clustering of the discrete poles near z = 1.
        system = scipy.signal.tf2ss(*_scaled_tf(tf_numerator, denominator, time_unit))
        discrete = scipy.signal.cont2discrete(system, dt / time_unit, method="zoh")
        _, response, _ = scipy.signal.dlsim(discrete, signal)
        expected += response.ravel()
    assert _relative_max_error(u_out, expected) < 1e-12


def test_steady_state_matches_closed_forms():
    # U_ss = K_test U_test + K_a a + k_dp k_y l M_ext / (c + k_dm l k_dp k_y). The exact
    # discretisation allows a coarse grid: 40 ms at 10 kHz (the transient decays as e^{-ξt/T}).
    params = _reference()
    ts = jnp.arange(401) / 1e4
    test_voltage, acceleration, moment = 0.7, 2.0, 3e-6
    u_out = simulate_linear(params, ts, test_voltage, acceleration, moment)
    expected = (
        float(closed_loop_test_gain(params)) * test_voltage
        + float(scale_factor(params)) * acceleration
        + _pickoff_per_radian(params) * moment / float(loop_stiffness(params))
    )
    assert abs(float(u_out[-1]) - expected) / expected < 1e-10
    # Acceleration alone: U_amp/a → K_a (docs/models.md eq. (2)); starts settled at a = 0.
    accel = jnp.where(ts > 0, acceleration, 0.0)
    u_accel = simulate_linear(params, ts, 0.0, accel, 0.0)
    assert abs(float(u_accel[-1]) / acceleration / float(scale_factor(params)) - 1) < 1e-10
    state = equilibrium_state(params, test_voltage, acceleration, moment)
    assert abs(float(state[3]) - expected) / expected < 1e-13


def test_discretise_is_exact_for_a_scalar_lag():
    a, b, dt = -3.0, 2.0, 0.1
    ad, bd = discretise(jnp.array([[a]]), jnp.array([[b]]), dt)
    assert np.isclose(float(ad[0, 0]), math.exp(a * dt), rtol=1e-14)
    assert np.isclose(float(bd[0, 0]), b * (math.exp(a * dt) - 1) / a, rtol=1e-14)


def test_state_space_is_finite_at_zero_lags():
    jacobian = eqx.filter_jit(jax.jacfwd(state_space))
    for lags in [(0.0, 0.0), (0.0, 1e-5), (1e-5, 0.0)]:
        params = _reference(torquer_time_constant=lags[0], filter_time_constant=lags[1])
        matrices = state_space(params)
        assert all(np.all(np.isfinite(np.asarray(m))) for m in matrices)
        grads = jacobian(params)
        leaves = jax.tree_util.tree_leaves(grads)
        assert all(np.all(np.isfinite(np.asarray(leaf))) for leaf in leaves)


# ----------------------------------------------------------------------------------------
# Nonlinear simulator
# ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("constant", [False, True])
@pytest.mark.parametrize("stops", [False, True])
def test_nonlinear_matches_linear(stops, constant):
    # T_dm, T_f > 0 and a time-varying moment (held path: a step per sample) or a constant
    # one (every input a scalar: adaptive steps, dense output); with 1 V the stops are never
    # reached.
    params = _reference()
    moment = 1e-6 if constant else MOMENT
    linear, linear_states = simulate_linear(params, TS, 1.0, 0.0, moment, return_states=True)
    nonlinear, states = simulate_nonlinear(
        params, TS, 1.0, 0.0, moment, stops=stops, return_states=True
    )
    assert np.max(np.abs(np.asarray(states[:, 0]))) < float(params.stop_displacement) / float(
        params.pendulum_length
    )
    assert _relative_max_error(nonlinear, linear) < 1e-9
    assert _relative_max_error(states, linear_states) < 1e-9


@pytest.mark.parametrize("test_voltage", [5.0, -5.0])
def test_stops_clamp_the_output(test_voltage):
    # ±5 V drives the reference device onto its stops; the output settles at
    # ±k_dp k_y h_max, plus the contact penetration (θ_free − θ_max)/(1 + r).
    params = _reference()
    ratio = 1e4
    u_out = simulate_nonlinear(params, TS, test_voltage, stop_stiffness_ratio=ratio)
    theta_max = float(params.stop_displacement / params.pendulum_length)
    theta_free = float(
        (params.torquer_gain * test_voltage + params.external_moment) / loop_stiffness(params)
    )
    sign = math.copysign(1.0, test_voltage)
    theta = sign * theta_max + (theta_free - sign * theta_max) / (1 + ratio)
    expected = _pickoff_per_radian(params) * theta
    stop_output = sign * float(
        params.pickoff_gain * params.amplifier_gain * params.stop_displacement
    )
    final = float(u_out[-1])
    assert abs(final / stop_output - 1) < 1e-4  # the penetration is ≈ 2.6e-5 of h_max
    assert abs(final / expected - 1) < 1e-9
    # The linear loop (no stops) would settle 18-26 % further out.
    assert abs(float(simulate_linear(params, TS, test_voltage)[-1])) > 1.1 * abs(final)


# ----------------------------------------------------------------------------------------
# Ideal lags: continuity and derivatives at T = 0
# ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("field", ["torquer_time_constant", "filter_time_constant"])
def test_lag_to_zero_is_continuous(field):
    # The lag's effect must vanish linearly as T → 0. Lags far below the sample interval make
    # the ZOH matrix exponential stiff (‖A dt‖ = dt/T): at T = 1e-12 (‖A dt‖ = 1e6) expm
    # rounding alone is ~1e-8 of the output, comparable to the effect itself, so we test at
    # T = 1e-10 and 1e-9 where the effect (~1e-7, 1e-6) dominates the rounding (~1e-11).
    zero = _reference(**{field: 0.0})
    u_zero, states_zero = simulate_linear(zero, TS, 1.0, 0.0, MOMENT, return_states=True)
    u_zero = np.asarray(u_zero)
    slope = np.gradient(u_zero, T)
    differences = {}
    for lag in (1e-10, 1e-9):
        tiny = _reference(**{field: lag})
        u_tiny, states_tiny = simulate_linear(tiny, TS, 1.0, 0.0, MOMENT, return_states=True)
        differences[lag] = np.asarray(u_tiny) - u_zero
        scale = np.max(np.abs(np.asarray(states_zero)), axis=0)
        assert np.all(np.max(np.abs(np.asarray(states_tiny - states_zero)), axis=0) < 1e-5 * scale)
    effect = {lag: np.max(np.abs(d)) for lag, d in differences.items()}
    assert effect[1e-9] < 1e-5 * np.max(np.abs(u_zero))
    # Linear in T (to 1 %): continuity at zero with a finite derivative.
    assert abs(effect[1e-9] / effect[1e-10] / 10 - 1) < 1e-2
    if field == "filter_time_constant":
        # The output filter's first-order effect is a delay: u_T ≈ u_0 − T u_0'.
        for lag, d in differences.items():
            assert np.max(np.abs(d + lag * slope)) < 1e-2 * effect[lag]


def _loss(simulator, params):
    # A scalar functional of the whole record [V²].
    return jnp.mean(simulator(params, TS, 1.0, 0.0, MOMENT, stops=False) ** 2)


def _linear(params, ts, *inputs, stops=False):
    del stops
    return simulate_linear(params, ts, *inputs)


_LOSSES = {
    "linear": eqx.filter_jit(lambda p: _loss(_linear, p)),
    "nonlinear": eqx.filter_jit(lambda p: _loss(simulate_nonlinear, p)),
}
_GRADS = {name: eqx.filter_jit(eqx.filter_grad(loss)) for name, loss in _LOSSES.items()}


def _with(params, field, value):
    return eqx.tree_at(lambda p: getattr(p, field), params, jnp.asarray(value))


@pytest.mark.parametrize(
    "field, point",
    [
        ("damping", (1e-5, 1e-5)),
        ("torquer_time_constant", (1e-5, 1e-5)),
        ("filter_time_constant", (1e-5, 1e-5)),
        ("torquer_time_constant", (0.0, 1e-5)),
        ("filter_time_constant", (1e-5, 0.0)),
        ("torquer_time_constant", (0.0, 0.0)),
        ("filter_time_constant", (0.0, 0.0)),
    ],
)
def test_gradients_match_finite_differences(field, point):
    params = _reference(torquer_time_constant=point[0], filter_time_constant=point[1])
    value = float(getattr(params, field))
    loss = _LOSSES["linear"]
    if value > 0:  # central differences
        step = 1e-4 * value
        fd = loss(_with(params, field, value + step)) - loss(_with(params, field, value - step))
        fd = fd / (2 * step)
    else:  # at T = 0 the lagged model exists on one side only: second-order one-sided
        step = 1e-8
        f0, f1, f2 = (loss(_with(params, field, k * step)) for k in range(3))
        fd = (-f2 + 4 * f1 - 3 * f0) / (2 * step)
    linear_grad = getattr(_GRADS["linear"](params), field)
    nonlinear_grad = getattr(_GRADS["nonlinear"](params), field)
    assert np.isfinite(float(linear_grad)) and np.isfinite(float(nonlinear_grad))
    assert np.isclose(float(linear_grad), float(fd), rtol=1e-5, atol=0)
    assert np.isclose(float(nonlinear_grad), float(linear_grad), rtol=1e-7, atol=0)


def test_nonlinear_gradient_matches_finite_differences():
    # The nonlinear simulator on its own (adaptive steps move with the parameters).
    params = _reference()
    loss = _LOSSES["nonlinear"]
    grads = _GRADS["nonlinear"](params)
    for field in ("damping", "torquer_time_constant", "filter_time_constant"):
        value = float(getattr(params, field))
        step = 1e-5 * value
        fd = loss(_with(params, field, value + step)) - loss(_with(params, field, value - step))
        assert np.isclose(float(getattr(grads, field)), float(fd / (2 * step)), rtol=1e-5)


@pytest.mark.parametrize("held", [False, True])
def test_gradient_of_stopped_output(held):
    # The settled output on the stop (what docs/models.md eq. (11) uses) is differentiable exactly.
    # (A functional spanning the impact itself is not: the dashpot switches on
    # discontinuously, and differentiating the discretised solve misses that jump.)
    # A scalar test voltage takes the adaptive path (steps left to the error control); the
    # same voltage as a per-sample array takes the held-input path (a step per sample).
    params = _reference()
    voltage = jnp.full(TS.shape, 5.0) if held else 5.0
    ratio = 1e4

    @eqx.filter_jit
    def stopped(p):
        return simulate_nonlinear(p, TS, voltage, stop_stiffness_ratio=ratio)[-1]

    def closed_form(p):
        # θ = θ_max + (θ_free − θ_max)/(1 + r), read out by k_dp k_y l.
        theta_max = p.stop_displacement / p.pendulum_length
        theta_free = (p.torquer_gain * 5.0 + p.external_moment) / loop_stiffness(p)
        theta = theta_max + (theta_free - theta_max) / (1 + ratio)
        return p.pickoff_gain * p.amplifier_gain * p.pendulum_length * theta

    grads = eqx.filter_grad(stopped)(params)
    exact = jax.grad(closed_form)(params)
    for field in ("stop_displacement", "pickoff_gain", "torquer_gain"):
        assert np.isclose(float(getattr(grads, field)), float(getattr(exact, field)), rtol=1e-5)
        if held:
            # Central differences agree too on the fixed step sequence. (On the adaptive
            # path they do not to 1e-5: a parameter step changes the step sequence, and the
            # torquer gain acts only through the 1e-4 penetration — 3.6e-5 off here.)
            value = float(getattr(params, field))
            step = 1e-3 * value
            fd = stopped(_with(params, field, value + step)) - stopped(
                _with(params, field, value - step)
            )
            assert np.isclose(float(getattr(grads, field)), float(fd / (2 * step)), rtol=1e-5)


# ----------------------------------------------------------------------------------------
# Transforms
# ----------------------------------------------------------------------------------------


def _batch(params_list):
    return jax.tree_util.tree_map(lambda *leaves: jnp.stack(leaves), *params_list)


@pytest.mark.parametrize("simulator", [simulate_linear, simulate_nonlinear])
def test_jit_vmap_over_params_matches_loop_without_retracing(simulator):
    lags = [0.0, 1e-5, 1e-4]

    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def sweep(batch, moment):
        return eqx.filter_vmap(simulator, in_axes=(0, None, None, None, None))(
            batch, TS, 1.0, 0.0, moment
        )

    batch = _batch([_reference(torquer_time_constant=lag) for lag in lags])
    swept = sweep(batch, jnp.asarray(MOMENT))
    looped = jnp.stack(
        [simulator(_reference(torquer_time_constant=lag), TS, 1.0, 0.0, MOMENT) for lag in lags]
    )
    assert _relative_max_error(swept, looped) < 1e-12
    # New values, same shapes: no retrace (assert_max_traces would raise).
    batch2 = _batch([_reference(torquer_time_constant=lag, damping=3e-5) for lag in lags])
    sweep(batch2, jnp.asarray(0.5 * MOMENT))


def test_vmap_over_input_sequences():
    params = _reference()
    voltages = jnp.stack([jnp.full(TS.shape, v) for v in (0.5, 1.0, -1.0)])
    swept = eqx.filter_vmap(simulate_linear, in_axes=(None, None, 0))(params, TS, voltages)
    for row, voltages_row in zip(swept, voltages, strict=True):
        assert _relative_max_error(row, simulate_linear(params, TS, voltages_row)) < 1e-13


def test_float32_is_kept():
    params32 = jax.tree_util.tree_map(lambda x: x.astype(jnp.float32), _reference())
    u_out = simulate_linear(params32, TS.astype(jnp.float32), 1.0)
    assert u_out.dtype == jnp.float32
    u_out64 = simulate_linear(_reference(), TS, 1.0)
    assert _relative_max_error(u_out, u_out64) < 1e-4


# ----------------------------------------------------------------------------------------
# Noise, step_response, errors
# ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("simulator", [simulate_linear, simulate_nonlinear])
def test_noise_statistics_and_reproducibility(simulator):
    params = _reference()
    key = jax.random.key(42)
    clean = simulator(params, TS, 1.0)
    noisy = simulator(params, TS, 1.0, key=key)
    residual = np.asarray(noisy - clean)
    eps, n = float(params.noise_std), residual.size
    # Sample std of n Gaussians: relative standard error 1/sqrt(2n); allow 5 of them.
    assert abs(residual.std() / eps - 1) < 5 / math.sqrt(2 * n)
    assert abs(residual.mean()) < 5 * eps / math.sqrt(n)
    np.testing.assert_array_equal(np.asarray(simulator(params, TS, 1.0, key=key)), noisy)
    other = simulator(params, TS, 1.0, key=jax.random.key(43))
    assert not np.array_equal(np.asarray(other), np.asarray(noisy))


def test_step_response():
    params = _reference()
    ts, u_out = step_response(params, 1e-3, SAMPLE_RATE, 1.0)
    assert ts.shape == (1001,) and np.isclose(float(ts[-1]), 1e-3, rtol=1e-14)
    assert _relative_max_error(u_out, simulate_linear(params, TS, 1.0)) < 1e-14
    ts_nl, u_nl = step_response(params, 1e-3, SAMPLE_RATE, 1.0, method="nonlinear")
    assert _relative_max_error(u_nl, u_out) < 1e-9


def test_solver_failure_is_surfaced():
    params = _reference()
    with pytest.raises(Exception, match="max_steps"):
        simulate_nonlinear(params, TS, 1.0, max_steps=10)
    failed = simulate_nonlinear(params, TS, 1.0, max_steps=10, throw=False)
    assert np.all(np.isnan(np.asarray(failed)))


def test_bad_inputs_raise_with_the_value():
    params = _reference()
    uneven = TS.at[500].add(3e-7)
    with pytest.raises(ValueError, match=r"ts\[50[01]\]"):
        simulate_linear(params, uneven, 1.0)
    with pytest.raises(ValueError, match=r"uniform"):
        simulate_nonlinear(params, uneven, 1.0)
    with pytest.raises(ValueError, match=r"\(1000,\)"):
        simulate_linear(params, TS, jnp.ones(1000))
    with pytest.raises(ValueError, match=r"acceleration.*\(3,\)"):
        simulate_nonlinear(params, TS, 1.0, jnp.ones(3))
    with pytest.raises(ValueError, match=r"initial_state.*\(3,\)"):
        simulate_linear(params, TS, 1.0, initial_state=jnp.zeros(3))
    with pytest.raises(ValueError, match="-0.001"):
        step_response(params, -1e-3, SAMPLE_RATE)
    with pytest.raises(ValueError, match="-1000000.0"):
        step_response(params, 1e-3, -SAMPLE_RATE)
    with pytest.raises(ValueError, match="'euler'"):
        step_response(params, 1e-3, SAMPLE_RATE, method="euler")


@pytest.mark.parametrize("simulator", [simulate_linear, simulate_nonlinear])
def test_non_finite_inputs_raise_instead_of_nan(simulator):
    # A NaN input gave a NaN record (linear) or a misleading "maximum number of solver
    # steps" error (nonlinear); both now name the input and the sample.
    params = _reference()
    voltage = np.ones(TS.shape[0])
    voltage[37] = np.nan
    with pytest.raises(ValueError, match=r"test_voltage must be finite, got nan V \(sample 37\)"):
        simulator(params, TS, voltage)
    with pytest.raises(ValueError, match=r"acceleration must be finite, got inf m/s²\.$"):
        simulator(params, TS, 1.0, np.inf)
    with pytest.raises(ValueError, match="external_moment must be finite"):
        simulator(params, TS, 1.0, 0.0, jnp.full(TS.shape, -jnp.inf))
    # Under jit the values are not known: no check, and finite inputs run as before.
    assert np.isfinite(float(jax.jit(lambda u: simulator(params, TS, u)[-1])(1.0)))
