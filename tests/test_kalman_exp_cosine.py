"""The INS channel with white, Gauss–Markov or exponential-cosine sensor errors
(`accel_jax._kalman_models.INSNoiseChannel`, docs/models.md §4, eqs. (7), (16)–(17)):
the exp-cos state's stationary covariance and autocorrelation from the channel's own
discrete model (SciPy's discrete Lyapunov solver), a Monte Carlo autocorrelation, the
filter's consistency with the true model, and `INSChannel`'s results reproduced bit for bit
by the Gauss–Markov choice."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
import scipy.stats

from accel_jax._kalman import kalman_filter, simulate_linear_gaussian
from accel_jax._kalman_ins import INSChannel, ins_consistency_trial, ins_initial_covariance
from accel_jax._kalman_models import INSNoiseChannel
from accel_jax.noise import ExponentialCosine, GaussMarkov, WhiteNoise

DT = 1.0
# Accelerometer: σ 1e-3 m/s², decay 1/600 s⁻¹, period 1200 s; gyro: σ 5e-8 rad/s, decay
# 1/3600 s⁻¹, period 2 h — both oscillate within the Schuler period's range.
ACCEL_EC = ExponentialCosine(1e-3, 1 / 600, 2 * np.pi / 1200)
GYRO_EC = ExponentialCosine(5e-8, 1 / 3600, 2 * np.pi / 7200)
EC_CHANNEL = INSNoiseChannel(ACCEL_EC, GYRO_EC, velocity_noise=0.1)
GM_ARGS = {"accel_sigma": 1e-3, "accel_correlation_time": 600.0, "gyro_sigma": 5e-8,
           "gyro_correlation_time": 3600.0, "velocity_noise": 0.1}  # fmt: skip
GM_CHANNEL = INSChannel(**GM_ARGS)
GM_NOISE_CHANNEL = INSNoiseChannel(GaussMarkov(1e-3, 600.0), GaussMarkov(5e-8, 3600.0), 0.1)


def _sensor_block(model, index, size):
    sl = slice(index, index + size)
    return (
        np.asarray(model.transition)[sl, sl],
        np.asarray(model.process_covariance)[sl, sl],
    )


@pytest.mark.parametrize("which", ["accel", "gyro"])
def test_exp_cosine_state_covariance_and_autocorrelation_from_discrete_lyapunov(which):
    noise = ACCEL_EC if which == "accel" else GYRO_EC
    index = EC_CHANNEL.sensor_indices()[0 if which == "accel" else 1]
    assert index == (2 if which == "accel" else 4)
    model = EC_CHANNEL.discretise(DT)
    F_s, Q_s = _sensor_block(model, index, 2)
    # The sensor states are autonomous (no kinematic state feeds them) ...
    rows = np.asarray(model.transition)[index : index + 2]
    assert np.all(np.delete(rows, [index, index + 1], axis=1) == 0)
    # ... and their block is the noise model's own exact discrete form.
    f, q, h, p0, _ = (np.asarray(m) for m in noise.state_space(DT))
    np.testing.assert_allclose(F_s, f, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(Q_s, q, rtol=1e-10, atol=1e-12 * q[0, 0])
    # Stationary covariance, independently: P = F P Fᵀ + Q (SciPy).
    P = scipy.linalg.solve_discrete_lyapunov(F_s, Q_s)
    sigma2, alpha, beta = (float(v) for v in (noise.sigma**2, noise.decay_rate,
                                              noise.angular_frequency))  # fmt: skip
    np.testing.assert_allclose(P, sigma2 * np.eye(2), rtol=1e-9, atol=1e-9 * sigma2)
    np.testing.assert_allclose(P, p0, rtol=1e-9, atol=1e-9 * sigma2)
    # Autocorrelation H Fᵏ P Hᵀ against σ² e^{−αkΔ} cos βkΔ (and the model's own), 1e-6
    # relative to R(0) (the cosine's zeros make a pointwise relative error meaningless).
    lags = np.arange(0, 3 * int(2 * np.pi / beta), 7)
    H = np.array([[1.0, 0.0]])
    acf = np.array([(H @ np.linalg.matrix_power(F_s, int(k)) @ P @ H.T)[0, 0] for k in lags])
    closed = sigma2 * np.exp(-alpha * lags * DT) * np.cos(beta * lags * DT)
    assert np.max(np.abs(acf - closed)) / sigma2 < 1e-6
    own = np.asarray(noise.autocovariance(lags * DT))
    assert np.max(np.abs(acf - own)) / sigma2 < 1e-6
    # The shaping filter (17), σ√(2α)(p + b)/(p² + 2αp + b²): its stationary output
    # covariance (continuous Lyapunov, controllable canonical form) is σ² too.
    b2 = alpha**2 + beta**2
    A = np.array([[0.0, 1.0], [-b2, -2 * alpha]])
    Bw = np.array([[0.0], [1.0]])
    C = np.sqrt(2 * alpha * sigma2) * np.array([[np.sqrt(b2), 1.0]])
    X = scipy.linalg.solve_continuous_lyapunov(A, -Bw @ Bw.T)
    assert (C @ X @ C.T)[0, 0] == pytest.approx(sigma2, rel=1e-10)
    for k in (50, 300, 700):  # and its autocorrelation C e^{Aτ} X Cᵀ is (16)
        r = (C @ scipy.linalg.expm(A * k * DT) @ X @ C.T)[0, 0]
        assert abs(r - closed[0] * np.exp(-alpha * k) * np.cos(beta * k)) < 1e-9 * sigma2


def test_monte_carlo_autocorrelation_within_its_standard_error():
    runs, steps = 400, 4000
    model = EC_CHANNEL.discretise(DT)
    p0 = ins_initial_covariance(EC_CHANNEL)  # the sensor states start stationary

    def accel_error(key):
        states, _ = simulate_linear_gaussian(model, jnp.zeros(6), p0, steps, key=key)
        return states[:, 2]

    x = np.asarray(jax.jit(jax.vmap(accel_error))(jax.random.split(jax.random.key(7), runs)))
    lags = np.array([0, 60, 150, 300, 450, 600, 900, 1200])
    # Each run's mean lagged product (zero mean known) has expectation R_k exactly; the runs
    # are independent, so the standard error is their spread over √runs.
    per_run = np.stack([np.mean(x[:, : steps - k] * x[:, k:], axis=1) for k in lags], axis=1)
    estimate = per_run.mean(axis=0)
    stderr = per_run.std(axis=0, ddof=1) / np.sqrt(runs)
    truth = np.asarray(ACCEL_EC.autocovariance(lags * DT))
    z = (estimate - truth) / stderr
    assert np.all(np.abs(z) < 3.0), z  # seed fixed; over seeds 8–17 the z had mean ≈ 0, sd ≈ 1
    # Jointly (the lags' estimates are correlated): Hotelling's T² against χ²(8) at 99 %.
    d = estimate - truth
    t2 = d @ np.linalg.solve(np.cov(per_run, rowvar=False) / runs, d)
    assert t2 < scipy.stats.chi2.ppf(0.99, len(lags)), t2
    # The lag-600 value is negative (half a period: e^{−1} cos π): the oscillation is there.
    assert estimate[lags == 600][0] < -5 * stderr[lags == 600][0]


def test_filter_with_the_true_exp_cosine_model_is_consistent():
    runs, steps = 64, 7200  # 2 h at 1 Hz
    n = 6

    def trial(key):
        return ins_consistency_trial(EC_CHANNEL, EC_CHANNEL, key, num_steps=steps)

    out = eqx.filter_jit(jax.vmap(trial))(jax.random.split(jax.random.key(11), runs))
    nees = np.asarray(out.nees)  # (runs, steps)
    # At fixed times the runs are independent: Σ_runs NEES_k ~ χ²(runs·n) exactly.
    lo, hi = scipy.stats.chi2.ppf([0.025, 0.975], runs * n) / runs
    for k in (0, 600, 1800, 3600, steps - 1):
        assert lo < nees[:, k].mean() < hi, (k, nees[:, k].mean(), lo, hi)
    # Time-averaged NEES: each run's average is one independent draw with mean n; their mean
    # lies in its 95 % band (the runs' spread), and inside the single-time χ² band.
    per_run = nees.mean(axis=1)
    mean, half = per_run.mean(), 1.96 * per_run.std(ddof=1) / np.sqrt(runs)
    assert abs(mean - n) < half, (mean, half)
    assert lo < mean < hi
    assert abs(float(out.nis.mean()) - 1.0) < 0.05
    assert float(out.fraction_outside_3sigma.mean()) < 0.01


def test_gauss_markov_choice_reproduces_ins_channel_bit_for_bit():
    for sample_interval in (1.0, 0.1):
        old, new = GM_CHANNEL.discretise(sample_interval), GM_NOISE_CHANNEL.discretise(
            sample_interval
        )
        for field in ("transition", "process_covariance", "observation",
                      "observation_covariance"):  # fmt: skip
            assert np.array_equal(getattr(old, field), getattr(new, field)), field
    for a, b in zip(GM_CHANNEL.continuous(), GM_NOISE_CHANNEL.continuous(), strict=True):
        assert np.array_equal(a, b)
    p0_old, p0_new = ins_initial_covariance(GM_CHANNEL), ins_initial_covariance(GM_NOISE_CHANNEL)
    assert np.array_equal(p0_old, p0_new)
    model = GM_CHANNEL.discretise(1.0)
    _, z = simulate_linear_gaussian(model, jnp.zeros(4), p0_old, 500, key=jax.random.key(3))
    out_old = kalman_filter(model, z, jnp.zeros(4), p0_old)
    out_new = kalman_filter(GM_NOISE_CHANNEL.discretise(1.0), z, jnp.zeros(4), p0_new)
    for a, b in zip(jax.tree.leaves(out_old), jax.tree.leaves(out_new), strict=True):
        assert np.array_equal(a, b)
    key = jax.random.key(4)
    t_old = ins_consistency_trial(GM_CHANNEL, GM_CHANNEL, key, num_steps=300)
    t_new = ins_consistency_trial(GM_NOISE_CHANNEL, GM_NOISE_CHANNEL, key, num_steps=300)
    for a, b in zip(jax.tree.leaves(t_old), jax.tree.leaves(t_new), strict=True):
        assert np.array_equal(a, b)
    assert GM_NOISE_CHANNEL.sensor_indices() == (2, 3)


def test_white_choice_matches_an_independent_construction():
    """White sensor errors (σ per sample at Δ) have no state: the channel is [ΔV, δ] driven
    by white intensities σ²Δ — checked against SciPy's Van Loan; a mixed channel (white
    accelerometer, Gauss–Markov gyro) is `INSChannel`'s model without the Δa state."""
    g, radius = 9.80665, 6.371e6
    for dt in (1.0, 0.5):
        channel = INSNoiseChannel(WhiteNoise(1e-3), WhiteNoise(5e-8), 0.1)
        model = channel.discretise(dt)
        a = np.array([[0.0, -g], [1 / radius, 0.0]])
        d = np.diag([1e-6 * dt, 2.5e-15 * dt])
        e = scipy.linalg.expm(np.block([[-a, d], [np.zeros((2, 2)), a.T]]) * dt)
        f, q = e[2:, 2:].T, e[2:, 2:].T @ e[:2, 2:]
        np.testing.assert_allclose(model.transition, f, rtol=1e-12, atol=1e-16)
        q = 0.5 * (q + q.T)  # SciPy's two off-diagonal entries differ by ~4e-9 relative
        scale = np.sqrt(np.outer(np.diag(q), np.diag(q)))  # cross terms against the diagonal
        assert np.max(np.abs(np.asarray(model.process_covariance) - q) / scale) < 1e-10
        assert channel.sensor_indices() == (None, None)
        assert ins_initial_covariance(channel).shape == (2, 2)
    mixed = INSNoiseChannel(WhiteNoise(1e-3), GaussMarkov(5e-8, 3600.0), 0.1)
    assert mixed.sensor_indices() == (None, 2)
    a_old, d_old, _ = (np.asarray(m) for m in GM_CHANNEL.continuous())
    a_new, d_new, h_new = (np.asarray(m) for m in mixed.continuous(1.0))
    keep = [0, 1, 3]
    assert np.array_equal(a_new, a_old[np.ix_(keep, keep)])
    assert np.array_equal(d_new[1:, 1:], d_old[np.ix_(keep, keep)][1:, 1:])
    assert d_new[0, 0] == pytest.approx(1e-6) and np.all(d_new[0, 1:] == 0)
    assert np.array_equal(h_new, [[1.0, 0.0, 0.0]])


def _observability(channel, horizon_s, every_s):
    """Singular values of the observability matrix [H Fᵏ] over a horizon, the states scaled
    by their prior standard deviation; and the steady-state filter's posterior correlation
    matrix and its standard deviations over the stationary (prior) ones."""
    model = channel.discretise(DT)
    F, H = np.asarray(model.transition), np.asarray(model.observation)
    Q, R = np.asarray(model.process_covariance), np.asarray(model.observation_covariance)
    s = np.sqrt(np.diag(np.asarray(ins_initial_covariance(channel))))
    Fs, Hs = F * s[None, :] / s[:, None], H * s
    O = np.vstack([Hs @ np.linalg.matrix_power(Fs, k) for k in range(0, horizon_s, every_s)])
    sv = np.linalg.svd(O, compute_uv=False)
    P = scipy.linalg.solve_discrete_are(F.T, H.T, Q, R)
    K = P @ H.T / (H @ P @ H.T + R)
    post = (np.eye(len(F)) - K @ H) @ P
    sd = np.sqrt(np.diag(post))
    return sv, post / np.outer(sd, sd), sd / s


def test_velocity_aiding_observability():
    """What z = ΔV observes: every state is observable over 2 h (full rank, modest
    condition number, states scaled by their prior σ), yet the filter separates the
    accelerometer error from the tilt only partly; for a near-constant bias (τ_a = 1e9 s)
    Δa and g δ are indistinguishable (posterior correlation → 1)."""
    sv, corr, ratio = _observability(EC_CHANNEL, 7200, 60)
    assert len(sv) == 6 and sv[0] / sv[-1] < 1e3
    assert 0.3 < corr[1, 2] < 0.8  # δ against Δa: partly separated
    assert np.all(ratio[2:] > 0.4)  # each sensor state keeps ≥ 40 % of its prior σ
    sv, corr, _ = _observability(GM_NOISE_CHANNEL, 7200, 60)
    assert sv[0] / sv[-1] < 1e3 and 0.7 < corr[1, 2] < 0.95
    bias = INSNoiseChannel(GaussMarkov(1e-3, 1e9), GaussMarkov(5e-8, 3600.0), 0.1)
    sv, corr, _ = _observability(bias, 7200, 60)
    assert sv[0] / sv[-1] > 1e5 and corr[1, 2] > 0.99


def test_bad_inputs_raise_clear_errors():
    with pytest.raises(ValueError, match="WhiteNoise, GaussMarkov or ExponentialCosine"):
        INSNoiseChannel(ACCEL_EC, "gyro", 0.1)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="velocity_noise"):
        INSNoiseChannel(ACCEL_EC, GYRO_EC, -0.1)
    with pytest.raises(ValueError, match="sample_interval"):
        EC_CHANNEL.discretise(0.0)
    with pytest.raises(ValueError, match="6 states and the assumed channel 4"):
        ins_consistency_trial(EC_CHANNEL, GM_CHANNEL, jax.random.key(0), num_steps=10)


@pytest.mark.parametrize("factors", [(10.0, 0.1), (0.1, 10.0), (10.0, 10.0)])
def test_scale_noise_coefficients_on_either_channel(factors):
    """The paper's mis-tuning on `INSNoiseChannel`: with Gauss–Markov errors it is
    `INSChannel`'s (the same discrete model); for exponential-cosine the generator's decay
    α is ×drift and its diffusion 2ασ² ×diffusion, β kept; a white error's intensity
    ×diffusion."""
    from accel_jax.kalman import scale_noise_coefficients

    drift, diffusion = factors
    with jax.enable_x64(True):
        gm = scale_noise_coefficients(GM_NOISE_CHANNEL, drift_factor=drift, diffusion_factor=diffusion)
        ref = scale_noise_coefficients(GM_CHANNEL, drift_factor=drift, diffusion_factor=diffusion)
        assert isinstance(gm, INSNoiseChannel) and isinstance(ref, INSChannel)
        a, b = gm.discretise(DT), ref.discretise(DT)
        np.testing.assert_allclose(a.transition, b.transition, rtol=1e-12)
        np.testing.assert_allclose(a.process_covariance, b.process_covariance, rtol=1e-10, atol=0)

        mixed = INSNoiseChannel(WhiteNoise(1e-3), GYRO_EC, velocity_noise=0.1)
        scaled = scale_noise_coefficients(mixed, drift_factor=drift, diffusion_factor=diffusion)
        a0, d0, _ = mixed.continuous(DT)
        a1, d1, _ = scaled.continuous(DT)
        np.testing.assert_allclose(a1[2:, 2:], a0[2:, 2:] * jnp.array([[drift, 1], [1, drift]]), rtol=1e-12)
        np.testing.assert_allclose(jnp.diag(d1)[2:], jnp.diag(d0)[2:] * diffusion, rtol=1e-12)
        np.testing.assert_allclose(d1[0, 0], d0[0, 0] * diffusion, rtol=1e-12)  # white: ΔV
        assert float(scaled.gyro_error.angular_frequency) == float(GYRO_EC.angular_frequency)


def test_scale_noise_coefficients_refuses_a_bad_factor():
    from accel_jax.kalman import scale_noise_coefficients

    with pytest.raises(ValueError, match="drift_factor must be positive"):
        scale_noise_coefficients(EC_CHANNEL, drift_factor=0.0, diffusion_factor=1.0)
