"""Tests of accel_jax._identify.monte_carlo (issue 7): the fused simulate-and-identify kernel
against `identify_oscillatory` called on the same records, and its float32 noise draws.
Float64 (tests/conftest.py). Records: 10 ms at 250 kHz (2 501 samples), small batches."""

import textwrap

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import drawn_devices

import accel_jax as aj
from accel_jax._identify.monte_carlo import _monte_carlo, monte_carlo_oscillatory
from accel_jax._simulate import fast_step_response

TS = jnp.arange(2501) / 2.5e5  # 10 ms at 250 kHz: settled, δK_a ≈ 0.12 % (docs/models.md §1)
GAIN = 2.5e5 * 8.5  # k_dp k_y [V/m]


def test_monte_carlo_matches_identify_oscillatory():
    # One batch (one compilation): odd trajectories noise-free, even ones with ε = 1e-4 V.
    size = 11  # not a multiple of the chunk: exercises the padding
    noise = jnp.where(jnp.arange(size) % 2 == 0, 1e-4, 0.0)
    devices = eqx.tree_at(lambda p: p.noise_std, drawn_devices(size, 3), noise)
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
    # Physically (exact γ and k_dp k_y): what is left is the lags' bias, ≈ 0.12 % (docs/models.md §1),
    # plus at 1e-4 V noise a spread of a few 0.01 %.
    truth = jax.vmap(aj.scale_factor)(devices)
    error = np.asarray(aj.relative_error_percent(fused.scale_factor, truth))
    assert np.all((error[1::2] > 0.05) & (error[1::2] < 0.3))
    assert np.all(np.abs(error) < 1.0)

    # New values of the same shapes and settings reuse the compiled kernel.
    compiled = _monte_carlo._cached._cache_size()
    monte_carlo_oscillatory(
        drawn_devices(size, 4),
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
    devices = eqx.tree_at(lambda p: p.noise_std, drawn_devices(size, 7), jnp.full(size, 1e-4))
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


def test_monte_carlo_on_two_simulated_devices_matches_one():
    # A fresh interpreter: the device count is fixed when JAX starts. The batch (13, not a
    # multiple of 2 devices × chunks of 4) is split across both devices and each
    # trajectory's estimate is that of the single-device kernel to rounding.
    code = textwrap.dedent(
        """
        import jax
        jax.config.update("jax_enable_x64", True)
        import equinox as eqx, jax.numpy as jnp, numpy as np
        import accel_jax as aj
        assert jax.device_count() == 2, jax.devices()
        size = 13
        mus = jnp.linspace(1.5e-5, 3.5e-5, size)  # ξ ≈ 0.3 … 0.7
        devices = eqx.filter_vmap(
            lambda mu: aj.ServoParams.reference(damping=mu, noise_std=1e-4)
        )(mus)
        keys = jax.random.split(jax.random.key(9), size)
        ts = jnp.arange(2501) / 2.5e5
        run = lambda d: aj.monte_carlo_oscillatory(
            devices, keys, ts, pickoff_amplifier_gain=2.125e6, shape_factor=0.75,
            chunk_size=4, devices=d,
        )
        both, one = run(None), run(jax.devices()[:1])
        assert bool(jnp.all(one.result == aj.IdentificationResult.successful))
        assert bool(jnp.all(both.result == one.result))
        for a, b in zip(jax.tree_util.tree_leaves(both), jax.tree_util.tree_leaves(one)):
            # The per-device program is compiled on its own and fuses differently: the
            # same numbers to rounding (seen: 1 ulp), not bitwise.
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-13, atol=0)
        print("OK", len(both.scale_factor.sharding.device_set))
        """
    )
    from helpers import run_on_simulated_cpu_devices

    proc = run_on_simulated_cpu_devices(code, 2)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.strip() == "OK 2", proc.stdout
    with pytest.raises(ValueError, match="at least one device"):
        monte_carlo_oscillatory(
            drawn_devices(2, 1),
            jax.random.split(jax.random.key(0), 2),
            TS,
            pickoff_amplifier_gain=GAIN,
            shape_factor=0.75,
            devices=[],
        )


@pytest.mark.parametrize("window", [1, 128])
def test_monte_carlo_fast_path_and_its_fallback_match_identify_oscillatory(monkeypatch, window):
    # The kernel fits the crossings within ±window samples of each sign change when every
    # fit of a chunk fits there (128: at least the low-noise chunk) and otherwise identifies the
    # chunk over the whole record (1: no fit fits). Either way: identify_oscillatory's
    # estimates, including the ones it fails, with both polarities of the records' noise.
    from accel_jax._identify import monte_carlo

    monkeypatch.setattr(monte_carlo, "_FIT_WINDOW", window)
    size = 12
    noise = jnp.where(jnp.arange(size) < 6, 3e-5, 3e-3)  # the last 6: noise dominates A2
    devices = eqx.tree_at(lambda p: p.noise_std, drawn_devices(size, 21), noise)
    keys = jax.random.split(jax.random.key(22), size)
    fused = monte_carlo_oscillatory(
        devices, keys, TS, pickoff_amplifier_gain=GAIN, shape_factor=0.75, chunk_size=6
    )
    records = jax.vmap(lambda d, k: fast_step_response(d, TS, 1.0, key=k, noise_dtype="float32"))(
        devices, keys
    )
    expected = jax.vmap(
        lambda u: aj.identify_oscillatory(
            TS, u, pickoff_amplifier_gain=GAIN, shape_factor=0.75, throw=False
        )
    )(records)
    assert bool(jnp.all(fused.result == expected.result))
    ok = np.asarray(expected.result == aj.IdentificationResult.successful)
    assert ok[:6].all()
    # Which path each chunk took: the fast one needs every fit of the chunk exact.
    from accel_jax._identify.oscillatory import _oscillatory_estimate

    _, exact = jax.vmap(
        lambda u: _oscillatory_estimate(
            TS, u, GAIN, 0.75, TS[0], None, jnp.inf, 500, "linear", "sample", "full", window
        )
    )(records)
    fast_chunks = np.asarray(exact).reshape(2, 6).all(axis=1)
    assert list(fast_chunks[:1]) == ([True] if window == 128 else [False])
    for name in ("scale_factor", "t1", "t2", "overshoot", "undershoot", "period"):
        np.testing.assert_allclose(
            np.asarray(getattr(fused, name))[ok],
            np.asarray(getattr(expected, name))[ok],
            rtol=1e-12,
            err_msg=name,
        )


def test_chunks_that_need_many_squarings_take_the_full_exponential():
    """The kernel computes a chunk's ZOH exponentials with a short squaring loop when every
    device in it needs few (`record_squarings` ≤ `_FEW_SQUARINGS`), else with the full one.
    A stiff torquer lag (T_dm = 0.1 µs against a 4 µs sample step) needs more: its chunk
    must give `identify_oscillatory` on `fast_step_response`'s record, as the plain chunks
    do (the short loop would give NaN there, never a wrong record)."""
    from accel_jax._identify.monte_carlo import _FEW_SQUARINGS
    from accel_jax._simulate.blocked import record_squarings

    lags = jnp.asarray([1e-5, 2e-5, 1e-7, 1e-5])  # chunks of 2: the second holds the stiff lag
    devices = eqx.tree_at(lambda p: p.torquer_time_constant, drawn_devices(4, 8), lags)
    needed = jax.vmap(record_squarings, in_axes=(0, None))(devices, TS)
    assert np.all(np.asarray(needed)[[0, 1, 3]] <= _FEW_SQUARINGS)
    assert float(needed[2]) > _FEW_SQUARINGS
    keys = jax.random.split(jax.random.key(9), 4)
    gamma = jax.vmap(aj.shape_factor)(devices)
    fused = monte_carlo_oscillatory(
        devices, keys, TS, pickoff_amplifier_gain=GAIN, shape_factor=gamma, chunk_size=2
    )

    def separate(device, key, gamma):
        record = fast_step_response(device, TS, 1.0, key=key, noise_dtype=jnp.float32)
        return aj.identify_oscillatory(
            TS, record, pickoff_amplifier_gain=GAIN, shape_factor=gamma, throw=False
        )

    expected = jax.vmap(separate)(devices, keys, gamma)
    assert bool(jnp.all(expected.result == aj.IdentificationResult.successful))
    assert bool(jnp.all(fused.result == expected.result))
    np.testing.assert_allclose(fused.scale_factor, expected.scale_factor, rtol=1e-12)
