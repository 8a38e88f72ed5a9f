"""Tests of accel_jax._simulate.blocked (issue 7): the blocked-power record against
`simulate_linear` (an independent sequential scan) and a closed form; the fused Monte
Carlo kernel's input checks and gradient. Float64 (tests/conftest.py).
Records: 10 ms at 250 kHz (2 501 samples), small batches, to keep the file fast."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import central_difference, drawn_devices

import accel_jax as aj
from accel_jax._identify.monte_carlo import monte_carlo_oscillatory
from accel_jax._simulate import fast_step_response

TS = jnp.arange(2501) / 2.5e5  # 10 ms at 250 kHz: settled, δK_a ≈ 0.12 % (docs/models.md §1)
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
    # The scan (Padé ZOH) and the blocked powers (Taylor ZOH, `_expm`) share no code; they
    # agree to rounding (measured ≤ 2e-13 of the step on 64 drawn devices at 1 MHz, 5 001
    # samples: a ~1e-16 difference between the two exponentials grows over the record's
    # powers), including two coincident lag poles, where an
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


def test_rbg_noise_statistics():
    # rbg keys (faster on CPU): under vmap JAX's rbg stream depends on the batch, not only
    # on the key, but the noise is still i.i.d. N(0, ε²): std ε per row, rows uncorrelated.
    size = 8
    devices = eqx.tree_at(lambda p: p.noise_std, drawn_devices(size, 1), jnp.full(size, 1e-3))
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
    devices = drawn_devices(4, 0)
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


def test_float32_noise_is_jax_normals_transform_of_full_threefry_words():
    """The float32 deviates: JAX's own float32 normal transform (bitwise
    `jax.random.normal` for the same 32-bit words), applied to both halves of 64-bit
    threefry draws. Other samples than `jax.random.normal(key, shape, float32)`, the same
    distribution: mean, standard deviation and a Kolmogorov–Smirnov test on 2e5 deviates,
    and no correlation between the two halves of a draw (neighbours in the record are
    halves of different draws, the halves sit n/2 apart)."""
    import scipy.stats

    from accel_jax._simulate.blocked import _float32_normal_from_bits, _normal_float32

    key = jax.random.key(12)
    words = jax.random.bits(key, (10_001,), jnp.uint32)
    np.testing.assert_array_equal(
        _float32_normal_from_bits(words), jax.random.normal(key, (10_001,), jnp.float32)
    )
    n = 200_001
    deviates = np.asarray(_normal_float32(key, n), np.float64)
    assert deviates.dtype == np.float64 and deviates.shape == (n,)
    assert abs(deviates.mean()) < 4 / np.sqrt(n)
    assert abs(deviates.std() - 1) < 4 / np.sqrt(2 * n)
    assert scipy.stats.kstest(deviates, "norm").pvalue > 1e-3
    half = n // 2
    assert abs(np.corrcoef(deviates[:half], deviates[half + 1 : n])[0, 1]) < 4 / np.sqrt(half)
    assert abs(np.corrcoef(deviates[:-1], deviates[1:])[0, 1]) < 4 / np.sqrt(n)
    other = np.asarray(jax.random.normal(key, (n,), jnp.float32), np.float64)
    assert not np.array_equal(deviates, other)  # other samples for the same key


@pytest.mark.parametrize("make_key", ["key", "raw", "rbg"])
def test_float32_noise_words_are_jaxs_64_bit_draws(make_key):
    """The float32 noise's words: for a threefry key the hash written out round by round
    (`_threefry_words`) gives bitwise the two halves of `jax.random.bits(key, (m,),
    uint64)` (JAX's default partitionable threefry; this test would catch a change of
    JAX's counters); a raw uint32 key is the default implementation's; an `rbg` key's
    words come from `jax.random.bits`. Under vmap, each threefry key's deviates are its own
    (JAX's `rbg` under vmap draws a batch from one stream: see `monte_carlo_oscillatory`)."""
    from accel_jax._simulate.blocked import _float32_normal_from_bits, _normal_float32

    key = {
        "key": jax.random.key(21),
        "raw": jax.random.PRNGKey(21),
        "rbg": jax.random.key(21, impl="rbg"),
    }[make_key]
    typed = key if make_key != "raw" else jax.random.wrap_key_data(key)
    n = 1001
    wide = jax.random.bits(typed, ((n + 1) // 2,), jnp.uint64)
    words = jnp.concatenate([(wide >> 32).astype(jnp.uint32), wide.astype(jnp.uint32)])[:n]
    np.testing.assert_array_equal(_normal_float32(key, n), _float32_normal_from_bits(words))
    if make_key == "rbg":
        return
    keys = jax.random.split(typed, 3)
    batch = jax.vmap(lambda k: _normal_float32(k, 11))(keys)
    for i in range(3):
        np.testing.assert_array_equal(batch[i], _normal_float32(keys[i], 11))
