"""The in-flight identification loop (accel_jax.kalman.identify_in_flight): its six-state
channel against INSNoiseChannel's, its fixed-model filter against kalman_filter, the
structure test on known series, the guards, and the loop's recovery of a mis-tuned filter."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from accel_jax.kalman import (
    INSNoiseChannel,
    OnlineIdentification,
    SensorErrorModel,
    choose_structure,
    identify_in_flight,
    ins_initial_covariance,
    kalman_filter,
    online_channel,
    simulate_linear_gaussian,
)
from accel_jax.noise import ExponentialCosine, GaussMarkov, autocorrelation, simulate_noise

ALPHA, BETA = 1 / 3600, 2.5 / 3600


@pytest.fixture(autouse=True)
def _x64():
    with jax.enable_x64(True):
        yield


def _truth():
    return INSNoiseChannel(
        GaussMarkov(1e-3, 600.0), ExponentialCosine(5e-8, ALPHA, BETA), velocity_noise=0.1
    )


def test_six_state_channel_is_ins_noise_channel_with_a_decoupled_copy():
    """β = 0 makes the two-state block a Gauss–Markov state plus a copy the observation never
    sees: dropping it (index 3) leaves INSNoiseChannel's transition and process covariance,
    which come from the noise models' own state_space (a separate construction)."""
    six = online_channel(
        SensorErrorModel.gauss_markov(1e-3, 600.0),
        SensorErrorModel(5e-8, ALPHA, BETA),
        0.1,
        1.0,
    )
    five = _truth().discretise(1.0)
    keep = jnp.array([0, 1, 2, 4, 5])
    np.testing.assert_allclose(six.transition[jnp.ix_(keep, keep)], five.transition, rtol=1e-10, atol=1e-15)
    scale = jnp.sqrt(jnp.outer(jnp.diag(five.process_covariance), jnp.diag(five.process_covariance)))
    np.testing.assert_allclose(
        six.process_covariance[jnp.ix_(keep, keep)] / scale,
        five.process_covariance / scale,
        atol=1e-10,
    )
    # The copy is decoupled: no entry of F or Q links it to another state.
    assert float(jnp.max(jnp.abs(six.transition[3, jnp.array([0, 1, 2, 4, 5])]))) == 0.0
    assert float(jnp.max(jnp.abs(six.transition[jnp.array([0, 1, 2, 4, 5]), 3]))) == 0.0


def test_fixed_models_reproduce_kalman_filter_on_the_five_state_channel():
    truth = _truth()
    model = truth.discretise(1.0)
    p0 = ins_initial_covariance(truth)
    _, z = simulate_linear_gaussian(model, jnp.zeros(5), p0, 3600, key=jax.random.key(0))
    reference = kalman_filter(model, z, jnp.zeros(5), p0)
    run = identify_in_flight(
        z[:, 0],
        SensorErrorModel.gauss_markov(1e-3, 600.0),
        SensorErrorModel(5e-8, ALPHA, BETA),
        velocity_noise=0.1,
        settings=OnlineIdentification(adaptation="none", retune_every=600, window=120, max_lag=20, decimation=10),
    )
    np.testing.assert_allclose(run.innovations, reference.innovations[:, 0], rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(
        run.kinematic_covariances, reference.filtered_covariances[:, :2, :2], rtol=1e-7
    )
    np.testing.assert_allclose(
        run.kinematic_means[:, 1], reference.filtered_means[:, 1], rtol=1e-6, atol=1e-12
    )
    assert not bool(jnp.any(run.retuned))


@pytest.mark.parametrize("seed", range(3))
def test_structure_test_tells_the_true_series_apart(seed):
    """On the sensor error itself (a 24 h window every 30 s) the test picks exp-cos for an
    exp-cos series and Gauss–Markov for a Gauss–Markov one."""
    n, lag = 2880, 30.0
    key = jax.random.fold_in(jax.random.key(7), seed)
    for model, want_ec in (
        (ExponentialCosine(1.0, ALPHA, BETA), True),
        (GaussMarkov(1.0, 3600.0), False),
    ):
        x = simulate_noise(model, lag, n, key=key)
        centred = x - jnp.mean(x)
        _, ec, statistic, _, _ = choose_structure(autocorrelation(x, 480), centred, n, lag)
        assert bool(statistic > 0) == want_ec, (model, float(statistic))
        if want_ec:
            assert 0.5 < float(ec.angular_frequency / BETA) < 2.0


def _settings(**changes):
    base = dict(retune_every=1800, decimation=30, window=1440, max_lag=240, min_window=360)
    return OnlineIdentification(**{**base, **changes})


def test_loop_retunes_a_mis_tuned_filter_towards_the_truth():
    """Started with drift and diffusion ×10 (τ ÷ 10), the loop re-identifies both sensors
    from its own estimates (after 3 h of window) and ends with the accelerometer's τ near
    600 s and a filter whose vertical error leaves ±3σ far less often than the wrong one's."""
    truth = _truth()
    model = truth.discretise(1.0)
    steps = 24 * 3600
    keys = jax.random.split(jax.random.key(3), 2)

    def one(key):
        x, z = simulate_linear_gaussian(model, jnp.zeros(5), ins_initial_covariance(truth), steps, key=key)
        return x, z[:, 0]

    states, z = jax.vmap(one)(keys)
    start = (SensorErrorModel.gauss_markov(1e-3, 60.0), SensorErrorModel.gauss_markov(5e-8, 360.0))

    @jax.jit
    def run(z):
        loop = jax.vmap(lambda zz: identify_in_flight(zz, *start, velocity_noise=0.1, settings=_settings()))(z)
        fixed = jax.vmap(
            lambda zz: identify_in_flight(zz, *start, velocity_noise=0.1, settings=_settings(adaptation="none"))
        )(z)
        return loop, fixed

    loop, fixed = run(z)
    retuned = np.asarray(loop.retuned)
    assert not retuned[:, :5].any()  # the window holds < 3 h before block 6
    assert retuned[:, 5:].mean() > 0.9
    tau_a = 1 / np.asarray(loop.models)[:, -1, 0, 1]
    assert np.all((tau_a > 300) & (tau_a < 1200)), tau_a

    def outside(run):
        e = states[:, steps // 2 :, 1] - run.kinematic_means[:, steps // 2 :, 1]
        return float(jnp.mean(jnp.abs(e) > 3 * jnp.sqrt(run.kinematic_covariances[:, steps // 2 :, 1, 1])))

    assert outside(loop) < 0.3 * outside(fixed), (outside(loop), outside(fixed))


def test_sage_husa_matches_the_innovations_and_stays_finite():
    truth = _truth()
    model = truth.discretise(1.0)
    _, z = simulate_linear_gaussian(model, jnp.zeros(5), ins_initial_covariance(truth), 7200, key=jax.random.key(1))
    run = identify_in_flight(
        z[:, 0],
        SensorErrorModel.gauss_markov(1e-3, 60.0),
        SensorErrorModel.gauss_markov(5e-8, 360.0),
        velocity_noise=0.1,
        settings=_settings(adaptation="sage_husa", fading_window=600.0),
    )
    assert bool(jnp.all(jnp.isfinite(run.kinematic_covariances)))
    assert bool(jnp.all(jnp.linalg.eigvalsh(run.kinematic_covariances) > 0))
    nis = np.asarray(run.innovations**2 / run.innovation_variances)
    assert 0.7 < nis[3600:].mean() < 1.3


def test_bad_input_is_refused():
    a, g = SensorErrorModel.gauss_markov(1e-3, 600.0), SensorErrorModel.gauss_markov(5e-8, 3600.0)
    with pytest.raises(ValueError, match="multiple of retune_every"):
        identify_in_flight(jnp.zeros(1000), a, g, velocity_noise=0.1, settings=_settings())
    with pytest.raises(ValueError, match="not finite"):
        identify_in_flight(jnp.full(1800, jnp.nan), a, g, velocity_noise=0.1, settings=_settings())
    with pytest.raises(ValueError, match="multiple of decimation"):
        OnlineIdentification(retune_every=1000, decimation=30)
    with pytest.raises(ValueError, match="adaptation"):
        OnlineIdentification(adaptation="mehra")
    with pytest.raises(ValueError, match="angular_frequency"):
        SensorErrorModel(1.0, 1.0, -1.0)
