"""Tests of accel_jax._fast (issue 7): the blocked-power record against `simulate_linear`
(an independent sequential scan) and a closed form, and the fused Monte Carlo kernel
against `identify_oscillatory` called on the same records. Float64 (tests/conftest.py).
Records: 10 ms at 250 kHz (2 501 samples), small batches, to keep the file fast."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import central_difference

import accel_jax as aj
from accel_jax._fast import _monte_carlo, fast_step_response, monte_carlo_oscillatory

TS = jnp.arange(2501) / 2.5e5  # 10 ms at 250 kHz: settled, δK_a ≈ 0.12 % (SPEC §1)
GAIN = 2.5e5 * 8.5  # k_dp k_y [V/m]


def _step(record):
    return float(jnp.abs(record[-1] - record[0]))


def _coincident_filter():
    """T_f making the output filter's pole −1/T_f equal to the loop's real (torquer) pole."""
    a_matrix, _, _, _ = aj.state_space(aj.ServoParams.reference())
    loop_poles = np.linalg.eigvals(np.asarray(a_matrix)[:3, :3])
    real_pole = loop_poles[np.argmin(np.abs(loop_poles.imag))].real
    return -1.0 / real_pole


@pytest.mark.parametrize(
    "overrides",
    [
        {},
        {"torquer_time_constant": 0.0},
        {"filter_time_constant": 0.0},
        {"torquer_time_constant": 0.0, "filter_time_constant": 0.0},
        {"damping": aj.APERIODIC_DAMPING},
        "coincident",
    ],
)
def test_record_matches_scan(overrides):
    # The scan and the blocked powers share only the ZOH matrix; they agree to rounding
    # (measured ~2e-14 of the step), including two coincident lag poles, where an
    # eigendecomposition-based modal form would divide by their zero gap.
    if overrides == "coincident":
        overrides = {"filter_time_constant": _coincident_filter()}
    params = aj.ServoParams.reference(**overrides)
    for test_voltage in (1.0, -5.0):
        expected = aj.simulate_linear(params, TS, test_voltage)
        record = fast_step_response(params, TS, test_voltage)
        np.testing.assert_allclose(record, expected, rtol=0, atol=1e-10 * _step(expected))


@pytest.mark.parametrize("n", [2, 3, 17, 1000])
def test_record_lengths(n):
    # Lengths that are not a multiple of the block (padding and slicing of the product).
    params = aj.ServoParams.reference()
    ts = jnp.arange(n) / 1e6
    expected = aj.simulate_linear(params, ts, 1.0, acceleration=0.3, external_moment=2e-6)
    record = fast_step_response(params, ts, 1.0, acceleration=0.3, external_moment=2e-6)
    np.testing.assert_allclose(record, expected, rtol=0, atol=1e-12)


def test_record_closed_form_ideal_lags():
    # T_dm = T_f = 0: U_out = U_0 + K_test U_test s(t; T, ξ), the second-order step (eq. 3).
    params = aj.ServoParams.reference(torquer_time_constant=0.0, filter_time_constant=0.0)
    record = fast_step_response(params, TS, 2.0)
    u0 = aj.equilibrium_state(params)[3]
    expected = u0 + aj.closed_loop_test_gain(params) * 2.0 * aj.second_order_step(
        TS, aj.time_constant(params), aj.damping_ratio(params)
    )
    np.testing.assert_allclose(record, expected, rtol=0, atol=1e-10 * 2.0)


def test_noise_is_simulate_linear_noise():
    params = aj.ServoParams.reference(noise_std=1e-3)
    for impl in ("threefry2x32", "rbg"):
        key = jax.random.key(7, impl=impl)
        expected = aj.simulate_linear(params, TS, 1.0, key=key)
        record = fast_step_response(params, TS, 1.0, key=key)
        np.testing.assert_allclose(record, expected, rtol=0, atol=1e-10 * _step(expected))
        assert float(jnp.std(record - fast_step_response(params, TS, 1.0))) == pytest.approx(
            1e-3, rel=0.1
        )


def _drawn_devices(size, seed):
    """Devices with J, μ, c, k_dm, T_dm, T_f drawn ±3 % (1σ) around the reference."""
    reference = aj.ServoParams.reference()
    rng = np.random.default_rng(seed)
    fields = {name: np.full(size, value) for name, value in aj.REFERENCE_VALUES.items()}
    for name in (
        "moment_of_inertia",
        "damping",
        "stiffness",
        "torquer_gain",
        "torquer_time_constant",
        "filter_time_constant",
    ):
        fields[name] = fields[name] * (1 + 0.03 * rng.standard_normal(size))
    del reference
    return aj.ServoParams(**{k: jnp.asarray(v) for k, v in fields.items()})


def test_monte_carlo_matches_identify_oscillatory():
    # One batch (one compilation): odd trajectories noise-free, even ones with ε = 1e-4 V.
    size = 11  # not a multiple of the chunk: exercises the padding
    noise = jnp.where(jnp.arange(size) % 2 == 0, 1e-4, 0.0)
    devices = eqx.tree_at(lambda p: p.noise_std, _drawn_devices(size, 3), noise)
    # threefry: vmap- and lax.map-exact, so the fused kernel draws each trajectory's noise
    # exactly as simulate_linear does (JAX's rbg on CPU is not: see monte_carlo_oscillatory).
    keys = jax.random.split(jax.random.key(5), size)
    gamma = jax.vmap(aj.shape_factor)(devices)  # per trajectory: γ = m l²/J
    fused = monte_carlo_oscillatory(
        devices,
        keys,
        TS,
        pickoff_amplifier_gain=GAIN,
        shape_factor=gamma,
        chunk_size=4,
        extremum="parabolic",
        noise_dtype=jnp.float64,
    )

    def separate(device, key, gamma):
        record = aj.simulate_linear(device, TS, 1.0, key=key)
        return aj.identify_oscillatory(
            TS,
            record,
            pickoff_amplifier_gain=GAIN,
            shape_factor=gamma,
            extremum="parabolic",
            throw=False,
        )

    expected = jax.vmap(separate)(devices, keys, gamma)
    assert bool(jnp.all(expected.result == aj.IdentificationResult.successful))
    assert bool(jnp.all(fused.result == expected.result))
    for name in ("scale_factor", "t1", "t2", "overshoot", "undershoot", "steady_state"):
        np.testing.assert_allclose(getattr(fused, name), getattr(expected, name), rtol=1e-10)
    # Physically (exact γ and k_dp k_y): what is left is the lags' bias, ≈ 0.12 % (SPEC §1),
    # plus at 1e-4 V noise a spread of a few 0.01 %.
    truth = jax.vmap(aj.scale_factor)(devices)
    error = np.asarray(aj.relative_error_percent(fused.scale_factor, truth))
    assert np.all((error[1::2] > 0.05) & (error[1::2] < 0.3))
    assert np.all(np.abs(error) < 1.0)

    # New values of the same shapes and settings reuse the compiled kernel.
    compiled = _monte_carlo._cached._cache_size()
    monte_carlo_oscillatory(
        _drawn_devices(size, 4),
        jax.random.split(jax.random.key(6), size),
        TS,
        pickoff_amplifier_gain=GAIN * 1.01,
        shape_factor=gamma * 0.99,
        chunk_size=4,
        extremum="parabolic",
        noise_dtype=jnp.float64,
    )
    assert _monte_carlo._cached._cache_size() == compiled


def test_monte_carlo_default_draws_noise_in_float32():
    # The default: float64 simulation and identification, noise deviates drawn in float32
    # and widened: exactly fast_step_response(..., noise_dtype=float32) then identify, and
    # the noise is N(0, ε²) all the same.
    size = 24
    devices = eqx.tree_at(lambda p: p.noise_std, _drawn_devices(size, 7), jnp.full(size, 1e-4))
    keys = jax.random.split(jax.random.key(8), size)
    fused = monte_carlo_oscillatory(
        devices, keys, TS, pickoff_amplifier_gain=GAIN, shape_factor=0.75, chunk_size=8
    )
    records = jax.vmap(lambda d, k: fast_step_response(d, TS, 1.0, key=k, noise_dtype="float32"))(
        devices, keys
    )
    assert records.dtype == jnp.float64
    expected = jax.vmap(
        lambda u: aj.identify_oscillatory(
            TS, u, pickoff_amplifier_gain=GAIN, shape_factor=0.75, throw=False
        )
    )(records)
    np.testing.assert_allclose(fused.scale_factor, expected.scale_factor, rtol=1e-12)
    assert bool(jnp.all(fused.result == aj.IdentificationResult.successful))
    clean = jax.vmap(lambda d: fast_step_response(d, TS, 1.0))(devices)
    residual = np.asarray(records - clean)
    np.testing.assert_allclose(residual.std(axis=1), 1e-4, rtol=0.1)
    wide = jax.vmap(lambda d, k: fast_step_response(d, TS, 1.0, key=k))(devices, keys)
    assert not np.array_equal(np.asarray(wide), np.asarray(records))  # other draws
    with pytest.raises(ValueError, match="noise_dtype"):
        fast_step_response(devices, TS, 1.0, key=keys[0], noise_dtype=jnp.int32)
    with pytest.raises(ValueError, match="noise_dtype"):
        monte_carlo_oscillatory(
            devices,
            keys,
            TS,
            pickoff_amplifier_gain=GAIN,
            shape_factor=0.75,
            noise_dtype="float16",
        )


def test_rbg_noise_statistics():
    # rbg keys (faster on CPU): under vmap JAX's rbg stream depends on the batch, not only
    # on the key, but the noise is still i.i.d. N(0, ε²): std ε per row, rows uncorrelated.
    size = 8
    devices = eqx.tree_at(lambda p: p.noise_std, _drawn_devices(size, 1), jnp.full(size, 1e-3))
    keys = jax.random.split(jax.random.key(2, impl="rbg"), size)
    clean = jax.vmap(lambda d: fast_step_response(d, TS, 1.0))(devices)
    noisy = jax.vmap(lambda d, k: fast_step_response(d, TS, 1.0, key=k))(devices, keys)
    residual = np.asarray(noisy - clean)
    np.testing.assert_allclose(residual.std(axis=1), 1e-3, rtol=0.1)
    assert abs(np.corrcoef(residual)[np.triu_indices(size, 1)]).max() < 0.1  # 5σ at n=2501


def test_gradient_through_fast_path():
    # d δK_a / d μ through the blocked record and identify_oscillatory, against central
    # differences of the same function (noise-free: the estimate is smooth in μ away from
    # the kinks where a sample crosses the steady-state line).
    base = aj.ServoParams.reference()

    def error(damping):
        params = eqx.tree_at(lambda p: p.damping, base, damping)
        record = fast_step_response(params, TS, 1.0)
        estimate = aj.identify_oscillatory(
            TS, record, pickoff_amplifier_gain=GAIN, shape_factor=aj.shape_factor(params)
        )
        return aj.relative_error_percent(estimate.scale_factor, aj.scale_factor(params))

    damping = base.damping
    gradient = jax.jit(jax.grad(error))(damping)
    numeric = central_difference(jax.jit(error), damping, rel_step=1e-7)
    assert float(gradient) == pytest.approx(float(numeric), rel=1e-4)
    assert abs(float(gradient) * float(damping)) > 1e-3  # not trivially zero


def test_bad_input():
    params = aj.ServoParams.reference()
    with pytest.raises(ValueError, match="scalar"):
        fast_step_response(params, TS, jnp.ones(TS.shape[0]))
    keys = jax.random.split(jax.random.key(0), 3)
    with pytest.raises(ValueError, match="leading batch axis"):
        monte_carlo_oscillatory(params, keys, TS, pickoff_amplifier_gain=GAIN, shape_factor=0.75)
    devices = _drawn_devices(4, 0)
    with pytest.raises(ValueError, match="batch size"):
        monte_carlo_oscillatory(devices, keys, TS, pickoff_amplifier_gain=GAIN, shape_factor=0.75)
    with pytest.raises(ValueError, match="chunk_size"):
        monte_carlo_oscillatory(
            devices,
            jax.random.split(keys[0], 4),
            TS,
            pickoff_amplifier_gain=GAIN,
            shape_factor=0.75,
            chunk_size=0,
        )
    with pytest.raises(ValueError, match="uniform"):
        fast_step_response(params, TS.at[5].add(1e-7), 1.0)
