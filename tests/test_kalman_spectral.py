"""The smoothed estimate's expected autocovariance (`accel_jax.kalman.smoothed_autocovariance`):
the sample estimator's expectation against the centring-matrix algebra, the law of total
covariance against closed forms, and the prediction against the library's RTS smoother on
simulated INS logs (a second, time-domain method)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import accel_jax.kalman as ak


@pytest.fixture(autouse=True)
def _x64():
    with jax.enable_x64(True):
        yield


def _gauss_markov_in_white(phi=0.98, sigma=2.0, noise=1.5):
    return ak.LinearGaussianModel(
        jnp.array([[phi]]),
        jnp.array([[(1 - phi**2) * sigma**2]]),
        jnp.array([[1.0]]),
        jnp.array([[noise**2]]),
    )


def _ins_channel():
    """The noise study's INS channel (σ_a 1e-3 m/s², 600 s; σ_ω 5e-8 rad/s, 3,600 s)."""
    return ak.INSChannel(
        accel_sigma=1e-3,
        accel_correlation_time=600.0,
        gyro_sigma=5e-8,
        gyro_correlation_time=3600.0,
        velocity_noise=0.1,
    )


@pytest.mark.parametrize("kind", ["gauss_markov", "oscillating"])
def test_expected_sample_autocovariance_is_the_centred_covariance_algebra(kind):
    """E[R̂_k] = tr_k(J C J)/(n − k), J = I − 11ᵀ/n, computed densely for n = 60."""
    n, lags = 60, np.arange(60)
    r = 0.9**lags if kind == "gauss_markov" else 0.95**lags * np.cos(0.4 * lags)
    c = r[np.abs(np.subtract.outer(lags, lags))]
    centring = np.eye(n) - 1.0 / n
    centred = centring @ c @ centring
    dense = np.array([np.trace(centred, offset=k) / (n - k) for k in range(20)])
    got = ak.expected_sample_autocovariance(r, n, 19)
    np.testing.assert_allclose(got, dense, rtol=0, atol=1e-14)
    assert got[0] < r[0]  # the record's own mean takes variance out


def test_with_the_true_model_estimate_and_error_add_up_to_the_state():
    """Law of total covariance: the smoothed mean's and the smoothing error's
    autocovariances add up to σ² φ^k (a Gauss–Markov state in white noise) and to
    σ_ω² e^{−k/τ_ω} (the INS channel's gyro state, behind the undamped Schuler loop)."""
    model = _gauss_markov_in_white()
    got = ak.smoothed_autocovariance(model, model, 0, 300, fft_size=1 << 16)
    lags = np.arange(301)
    np.testing.assert_allclose(got.estimate + got.posterior, 4.0 * 0.98**lags, rtol=1e-9)
    assert 0 < got.posterior[0] < 4.0 and got.record_length is None
    channel = _ins_channel()
    ins = channel.discretise(1.0)
    both = ak.smoothed_autocovariance(ins, ins, (2, 3), 2000, fft_size=1 << 18)
    assert both.estimate.shape == both.posterior.shape == (2, 2001)
    k = np.arange(2001)
    true = np.stack([1e-6 * np.exp(-k / 600.0), 2.5e-15 * np.exp(-k / 3600.0)])
    np.testing.assert_allclose(both.estimate + both.posterior, true, rtol=1e-6)


def _smoothed_sample_autocovariances(truth, assumed, states, n, max_lag, runs, skip, key):
    """The sample autocovariance of `rts_smoother`'s means of `states` over samples
    skip..n − skip of `runs` simulated records (the ends, where the smoother is not yet
    at its steady state, left out)."""
    from accel_jax.noise import autocorrelation

    size = truth.state_size

    def one(key):
        _, observations = ak.simulate_linear_gaussian(
            truth, jnp.zeros(size), jnp.eye(size) * 0, n, key=key
        )
        prior = jnp.zeros(assumed.state_size)
        out = ak.kalman_filter(assumed, observations, prior, jnp.eye(assumed.state_size))
        x = ak.rts_smoother(assumed, out).smoothed_means[skip : n - skip, jnp.array(states)]
        return jax.vmap(lambda s: autocorrelation(s, max_lag), in_axes=1)(x)

    sample = np.asarray(jax.jit(jax.vmap(one))(jax.random.split(key, runs)))
    return sample.mean(0), sample.std(0, ddof=1) / np.sqrt(runs)


def test_the_prediction_matches_the_rts_smoother_on_simulated_records():
    """A Gauss–Markov state in white noise smoothed with the wrong φ and noise (128 records
    of 20,000 samples): the mean sample autocovariance of the smoothed means against the
    prediction within 4 standard errors; the smoother's own model would be far off."""
    truth = _gauss_markov_in_white(phi=0.98, sigma=2.0, noise=1.5)
    assumed = _gauss_markov_in_white(phi=0.9, sigma=1.0, noise=3.0)
    n, skip, lags = 20_000, 500, [0, 5, 20, 60, 150]
    mean, error = _smoothed_sample_autocovariances(
        truth, assumed, (0,), n, 150, 128, skip, jax.random.PRNGKey(0)
    )
    got = ak.smoothed_autocovariance(assumed, truth, 0, 150, record_length=n - 2 * skip)
    z = (mean[0, lags] - got.estimate[lags]) / error[0, lags]
    assert np.all(np.abs(z) < 4), z
    wrong = ak.smoothed_autocovariance(truth, truth, 0, 150, record_length=n - 2 * skip)
    assert np.max(np.abs(mean[0, lags] - wrong.estimate[lags]) / error[0, lags]) > 20


def test_the_prediction_matches_the_rts_smoother_on_simulated_ins_logs():
    """16 simulated 16 h INS logs (Schuler loop, velocity observed) smoothed with sensor
    models ten times too fast, the middle 8 h kept: the mean sample autocovariance of the
    smoothed Δa and Δω against the prediction for an 8 h record, within 4 standard errors
    at each lag checked."""
    channel = _ins_channel()
    assumed = ak.scale_noise_coefficients(channel, drift_factor=10.0, diffusion_factor=0.1)
    truth, model = channel.discretise(1.0), assumed.discretise(1.0)
    n, skip, max_lag = 16 * 3600, 4 * 3600, 1500
    mean, error = _smoothed_sample_autocovariances(
        truth, model, (2, 3), n, max_lag, 16, skip, jax.random.PRNGKey(3)
    )
    interior = n - 2 * skip
    predicted = ak.smoothed_autocovariance(model, truth, (2, 3), max_lag, record_length=interior)
    lags = [0, 100, 400, 800, 1500]
    z = (mean[:, lags] - predicted.estimate[:, lags]) / error[:, lags]
    assert np.all(np.abs(z) < 4), z


def test_bad_input_is_one_clear_error():
    model = _gauss_markov_in_white()
    two = ak.LinearGaussianModel(jnp.eye(1), jnp.eye(1), jnp.ones((2, 1)), jnp.eye(2))
    with pytest.raises(ValueError, match="state must index"):
        ak.smoothed_autocovariance(model, model, 1, 10)
    with pytest.raises(ValueError, match="same\\s+number"):
        ak.smoothed_autocovariance(model, two, 0, 10)
    with pytest.raises(ValueError, match="record_length"):
        ak.smoothed_autocovariance(model, model, 0, 10, record_length=5)
    with pytest.raises(ValueError, match="fft_size"):
        ak.smoothed_autocovariance(model, model, 0, 10, fft_size=15)
    with pytest.raises(ValueError, match="max_lag"):
        ak.expected_sample_autocovariance(np.ones(10), 10, 9)
