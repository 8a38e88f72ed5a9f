"""ML (GLS) state estimate, linearisation error, compensation and the nonlinear fit
(docs/models.md §2), checked against NumPy brute force, Cramer's rule, Monte Carlo and
simulate-then-fit-then-recover on the exact sine motion."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

from accel_jax._ml_estimate import (
    GaussMarkovDisturbance,
    HarmonicDisturbance,
    MLEstimate,
    WhiteDisturbance,
    compensate_linearisation,
    error_covariance,
    fit_sensing_element,
    linearisation_error,
    linearisation_residual,
    ml_estimate,
    state_basis,
)
from accel_jax._pendulum import (
    SensingElement,
    cubic_approximation,
    record_mask,
    sample_sensing_element,
    sample_times,
)

OMEGA0 = 2 * np.pi
TS = sample_times(0.02, 128)  # 2.56 s: 2.56 periods


def _numpy_gls(ts, y, omega, r):
    a = np.stack([np.ones_like(ts), np.sin(omega * ts), np.cos(omega * ts)], axis=1)
    r_inv = np.linalg.inv(r)
    psi = np.linalg.inv(a.T @ r_inv @ a)
    return psi @ a.T @ r_inv @ y, psi


def test_gls_matches_numpy_brute_force_with_correlated_errors():
    ts = np.asarray(TS)
    disturbance = GaussMarkovDisturbance(1e-4, 0.3)
    r = error_covariance(TS, 5e-5, disturbance)
    rng = np.random.default_rng(0)
    y = 0.01 + 0.02 * np.sin(OMEGA0 * ts + 0.4) + rng.normal(0, 1e-4, ts.shape)
    estimate = ml_estimate(TS, y, OMEGA0, r)
    z, psi = _numpy_gls(ts, y, OMEGA0, np.asarray(r))
    np.testing.assert_allclose(estimate.state, z, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(estimate.covariance, psi, rtol=1e-8)
    # Eq. (9): the estimate is the gain applied to the samples, linear in them.
    np.testing.assert_allclose(estimate.gain @ y, estimate.state, rtol=1e-10, atol=1e-16)
    other = rng.normal(0, 1e-3, ts.shape)
    combined = ml_estimate(TS, y + 3 * other, OMEGA0, r).state
    np.testing.assert_allclose(
        combined, estimate.state + 3 * ml_estimate(TS, other, OMEGA0, r).state, atol=1e-15
    )
    # Ψ = G R Gᵀ (eq. 10 from eq. 9).
    np.testing.assert_allclose(estimate.gain @ np.asarray(r) @ estimate.gain.T, psi, rtol=1e-8)


def test_diagonal_and_full_covariance_agree_and_weights_matter():
    ts = np.asarray(TS)
    variances = np.linspace(1e-8, 9e-8, ts.size)
    y = 0.003 + 0.02 * np.cos(OMEGA0 * ts) + np.sin(7.0 * ts) * 1e-4
    diag = ml_estimate(TS, y, OMEGA0, variances)
    full = ml_estimate(TS, y, OMEGA0, np.diag(variances))
    np.testing.assert_allclose(diag.state, full.state, rtol=1e-10)
    np.testing.assert_allclose(diag.covariance, full.covariance, rtol=1e-10)
    z, _ = _numpy_gls(ts, y, OMEGA0, np.diag(variances))
    np.testing.assert_allclose(diag.state, z, rtol=1e-10)
    unweighted = ml_estimate(TS, y, OMEGA0, np.ones_like(variances))
    assert abs(unweighted.state[0] - diag.state[0]) > 1e-7


@pytest.mark.parametrize("full", [False, True])
def test_mask_equals_truncated_record(full):
    ts = np.asarray(TS)
    rng = np.random.default_rng(1)
    y = 0.02 * np.sin(OMEGA0 * ts + 1.0) + rng.normal(0, 1e-4, ts.size)
    r = error_covariance(TS, 1e-4, GaussMarkovDisturbance(1e-4, 0.1))
    cov = r if full else jnp.diagonal(r)
    k = 70
    masked = ml_estimate(TS, y, OMEGA0, cov, mask=record_mask(ts.size, k))
    short = ml_estimate(TS[:k], y[:k], OMEGA0, cov[:k, :k] if full else cov[:k])
    np.testing.assert_allclose(masked.state, short.state, rtol=1e-9)
    np.testing.assert_allclose(masked.covariance, short.covariance, rtol=1e-9)


def test_monte_carlo_error_covariance_equals_psi():
    # Simulate-then-estimate-then-recover: linear-model records plus correlated errors.
    ts = sample_times(0.05, 48)
    disturbance = GaussMarkovDisturbance(2e-4, 0.2)
    sigma = 1e-4
    r = error_covariance(ts, sigma, disturbance)
    z_true = jnp.array([0.01, 0.015, -0.01])
    clean = state_basis(ts, OMEGA0) @ z_true

    def one(key):
        k1, k2 = jax.random.split(key)
        y = clean + sigma * jax.random.normal(k1, ts.shape) + disturbance.sample(ts, key=k2)
        return ml_estimate(ts, y, OMEGA0, r).state - z_true

    n = 4000
    errors = np.asarray(jax.jit(jax.vmap(one))(jax.random.split(jax.random.key(7), n)))
    psi = np.asarray(ml_estimate(ts, clean, OMEGA0, r).covariance)
    std = np.sqrt(np.diag(psi))
    # Unbiased: mean within 4 standard errors.
    assert np.all(np.abs(errors.mean(axis=0)) < 4 * std / np.sqrt(n))
    # Variances within 10 % (the sampling error of a variance from 4000 draws is ~2.2 %).
    np.testing.assert_allclose(errors.var(axis=0), np.diag(psi), rtol=0.1)
    # ML beats ordinary least squares under correlated errors (Gauss–Markov theorem).
    ols = ml_estimate(ts, clean, OMEGA0, jnp.ones(ts.shape))
    ols_var = (ols.gain @ np.asarray(r) @ ols.gain.T)[0, 0]
    assert psi[0, 0] < ols_var


@pytest.mark.parametrize(
    "disturbance",
    [WhiteDisturbance(1e-3), GaussMarkovDisturbance(1e-3, 0.05), HarmonicDisturbance(1e-3, 5.0)],
)
def test_disturbance_samples_have_their_covariance(disturbance):
    ts = jnp.array([0.0, 0.02, 0.05, 0.11, 0.2])
    n = 20000
    draws = jax.vmap(lambda k: disturbance.sample(ts, key=k))(
        jax.random.split(jax.random.key(2), n)
    )
    empirical = np.asarray(draws.T @ draws / n)
    expected = np.asarray(disturbance.covariance(ts))
    assert np.max(np.abs(empirical - expected)) < 0.05 * 1e-6


def test_linearisation_error_is_cramers_rule_18():
    element = SensingElement(OMEGA0, 0.03)
    r = error_covariance(TS, 1e-5, GaussMarkovDisturbance(2e-5, 0.2))
    omega = 0.999 * OMEGA0  # an a-priori frequency error Δω
    delta = linearisation_error(
        TS, 0.03, 0.8, angular_frequency=omega, element=element, covariance=r
    )
    a = np.asarray(state_basis(TS, omega))
    r_inv = np.linalg.inv(np.asarray(r))
    b = a.T @ r_inv @ a
    c = (
        a.T
        @ r_inv
        @ np.asarray(
            linearisation_residual(TS, 0.03, 0.8, angular_frequency=omega, element=element)
        )
    )
    cofactors = np.linalg.inv(b).T * np.linalg.det(b)
    cramer = (cofactors[0, 0] * c[0] + cofactors[1, 0] * c[1] + cofactors[2, 0] * c[2]) / (
        np.linalg.det(b)
    )
    assert float(delta[0]) == pytest.approx(cramer, rel=1e-7)
    np.testing.assert_allclose(delta, np.linalg.solve(b, c), rtol=1e-7)


def test_predicted_bias_matches_estimate_on_paper_model_11():
    # Records of the paper's own refined model (11), noise-free: the linear estimator's
    # error equals Δ to first order (the residual of the first-order Taylor expansion in
    # t is O(A⁵ ω0² T_c²)), and the printed all-plus signs of eq. (17) do not.
    element = SensingElement(OMEGA0, 0.0)
    variances = jnp.full(TS.shape, 1e-10)
    amplitude = 0.033
    measured, predicted, printed = [], [], []
    for phase in np.linspace(0, 2 * np.pi, 6, endpoint=False):
        y = 0.02 + cubic_approximation(element, amplitude, phase, TS)
        estimate = ml_estimate(TS, y, OMEGA0, variances)
        measured.append(float(estimate.constant_angle) - 0.02)
        delta = linearisation_error(
            TS, amplitude, phase, angular_frequency=OMEGA0, element=element, covariance=variances
        )
        predicted.append(float(delta[0]))
        psi = OMEGA0 * np.asarray(TS) + phase
        d_printed = amplitude**3 / 192 * np.sin(3 * psi) + amplitude**3 / 16 * OMEGA0 * np.asarray(
            TS
        ) * np.cos(psi)
        printed.append(float((estimate.gain @ d_printed)[0]))
    measured, predicted, printed = map(np.asarray, (measured, predicted, printed))
    scale = np.sqrt(np.mean(measured**2))
    assert scale > 1e-7  # the bias is real and well above float64 noise
    assert np.max(np.abs(measured - predicted)) < 1e-2 * scale
    assert np.max(np.abs(measured - printed)) > 0.3 * scale


@pytest.mark.parametrize(("decay_rate", "removed"), [(0.0, 0.99), (0.02, 0.95)])
def test_compensation_on_exact_sine_motion(decay_rate, removed):
    # Without damping the bias is the cubic nonlinearity (third harmonic and the A²/16
    # frequency shift) and the paper's first-order Δ_αP removes > 99 % of it at A = 2°.
    # With ξ = 0.02 1/s the envelope term −Aξt dominates, and the neglected (ξt)²/2 term
    # (ξ T_c/2 ≈ 2.6 % here) limits the compensation to ~97 %.
    element = SensingElement(OMEGA0, decay_rate)
    variances = jnp.full(TS.shape, 1e-10)
    omega = element.damped_frequency
    alpha_p = 0.01

    def errors(phase, amplitude):
        _, y = sample_sensing_element(
            element, amplitude, phase, sample_interval=0.02, n_samples=128, constant_angle=alpha_p
        )
        plain = ml_estimate(TS, y, omega, variances).constant_angle - alpha_p
        comp = compensate_linearisation(
            TS, y, angular_frequency=omega, element=element, covariance=variances
        )
        return plain, comp.constant_angle - alpha_p, comp.correction

    phases = jnp.linspace(0, 2 * jnp.pi, 8, endpoint=False)
    plain, comp, correction = eqx.filter_jit(jax.vmap(errors, in_axes=(0, None)))(phases, 0.033)
    rms_plain = float(jnp.sqrt(jnp.mean(plain**2)))
    rms_comp = float(jnp.sqrt(jnp.mean(comp**2)))
    assert rms_plain > 1e-7
    assert rms_comp < (1 - removed) * rms_plain
    # The correction is the measured bias, evaluated at the estimated Â, φ̂.
    np.testing.assert_allclose(correction, plain, atol=(1 - removed) * rms_plain)


def test_nonlinear_fit_recovers_truth_noise_free_and_noisy():
    element = SensingElement(OMEGA0, 0.05)
    alpha_p = 0.012
    _, y = sample_sensing_element(
        element, 0.2, 2.0, sample_interval=0.02, n_samples=128, constant_angle=alpha_p
    )
    sigma = 1e-4
    variances = jnp.full(TS.shape, sigma**2)
    fit = fit_sensing_element(TS, y, element, covariance=variances)
    assert fit.result == optx.RESULTS.successful
    # Far beyond the linear estimator's bias at A = 0.2 rad.
    linear_error = abs(
        float(ml_estimate(TS, y, element.damped_frequency, variances).state[0]) - alpha_p
    )
    assert linear_error > 1e-5
    assert abs(float(fit.constant_angle) - alpha_p) < 1e-11
    noise = sigma * jax.random.normal(jax.random.key(4), TS.shape)
    noisy = fit_sensing_element(TS, y + noise, element, covariance=variances)
    std = float(jnp.sqrt(noisy.covariance[0, 0]))
    assert abs(float(noisy.constant_angle) - alpha_p) < 5 * std
    # Its covariance is the GLS one at small amplitude (the models coincide as A → 0).
    small = fit_sensing_element(
        TS, 0.01 + 1e-4 * jnp.sin(OMEGA0 * TS), SensingElement(OMEGA0, 0.0), covariance=variances
    )
    psi = ml_estimate(TS, y, OMEGA0, variances).covariance
    assert float(small.covariance[0, 0]) == pytest.approx(float(psi[0, 0]), rel=1e-3)


def test_bad_input_raises():
    with pytest.raises(ValueError, match="covariance must have shape"):
        ml_estimate(TS, jnp.zeros(128), OMEGA0, jnp.ones(7))
    with pytest.raises(ValueError, match="positive variances"):
        ml_estimate(TS, jnp.zeros(128), OMEGA0, jnp.zeros(128))
    with pytest.raises(ValueError, match="positive variances"):
        ml_estimate(TS, jnp.zeros(128), OMEGA0, HarmonicDisturbance(1e-3, 1.0).covariance(TS) * 0)
    with pytest.raises(ValueError, match="mask"):
        ml_estimate(TS, jnp.zeros(128), OMEGA0, jnp.ones(128), mask=jnp.ones(3))
    with pytest.raises(ValueError, match="angular_frequency"):
        ml_estimate(TS, jnp.zeros(128), -1.0, jnp.ones(128))
    with pytest.raises(ValueError, match="samples must have the shape"):
        ml_estimate(TS, jnp.zeros(5), OMEGA0, jnp.ones(128))
    with pytest.raises(ValueError, match="correlation_time"):
        GaussMarkovDisturbance(1e-3, 0.0)
    with pytest.raises(ValueError, match="pickoff_std"):
        error_covariance(TS, -1.0)
    with pytest.raises(ValueError, match="initial_guess"):
        fit_sensing_element(
            TS, jnp.zeros(128), SensingElement(OMEGA0), covariance=jnp.ones(128), initial_guess=1.0
        )
    assert isinstance(ml_estimate(TS, jnp.zeros(128), OMEGA0, jnp.ones(128)), MLEstimate)


def test_exponential_disturbance_covariance_is_that_of_its_samples():
    from accel_jax._ml_estimate import ExponentialDisturbance

    ts = sample_times(0.05, 40)
    disturbance = ExponentialDisturbance(2e-5, 0.4)
    samples = jax.vmap(lambda k: disturbance.sample(ts, key=k))(
        jax.random.split(jax.random.key(4), 20_000)
    )
    empirical = np.cov(np.asarray(samples), rowvar=False)
    expected = np.asarray(disturbance.covariance(ts))
    # Rank one: s² e_i e_j. The sample covariance of 20,000 draws: within ~3 % of s².
    np.testing.assert_allclose(empirical, expected, atol=0.03 * 2e-5**2)
    assert np.linalg.matrix_rank(expected, tol=1e-6 * expected.max()) == 1
    with pytest.raises(ValueError, match="time_constant"):
        ExponentialDisturbance(1e-5, 0.0)


def test_column_sum_estimate_is_gls_for_diagonal_r_and_worse_for_correlated_r():
    from accel_jax._ml_estimate import ExponentialDisturbance, column_sum_estimate

    ts = sample_times(0.02, 128)
    omega = 2 * np.pi
    truth = jnp.array([0.01, 0.003, -0.002])
    clean = state_basis(ts, omega) @ truth
    # A diagonal R (unequal variances): the paper's (8) is the GLS estimate.
    variances = jnp.linspace(1e-10, 4e-10, ts.shape[0])
    gls = ml_estimate(ts, clean + 1e-5, omega, variances)
    paper = column_sum_estimate(ts, clean + 1e-5, omega, variances)
    np.testing.assert_allclose(paper.state, gls.state, rtol=1e-10)
    np.testing.assert_allclose(paper.covariance, gls.covariance, rtol=1e-8)
    # Correlated R (white pickoff + Gauss–Markov + exponential transient): still unbiased
    # (G A = I) but with a larger variance of α̂_P than GLS (Gauss–Markov theorem); its
    # stated covariance G R Gᵀ is that of its errors over 4,000 noisy records.
    r = error_covariance(ts, 1e-5, GaussMarkovDisturbance(1e-5, 0.1)) + ExponentialDisturbance(
        3e-5, 0.5
    ).covariance(ts)
    paper = column_sum_estimate(ts, clean, omega, r)
    gls = ml_estimate(ts, clean, omega, r)
    np.testing.assert_allclose(paper.gain @ state_basis(ts, omega), np.eye(3), atol=1e-9)
    np.testing.assert_allclose(paper.state, truth, rtol=1e-9)
    assert float(paper.covariance[0, 0]) > 1.01 * float(gls.covariance[0, 0])  # here +4 %
    root = np.linalg.cholesky(np.asarray(r))
    noise = np.random.default_rng(5).standard_normal((4000, ts.shape[0])) @ root.T
    errors = (np.asarray(clean) + noise) @ np.asarray(paper.gain).T - np.asarray(truth)
    assert np.var(errors[:, 0]) == pytest.approx(float(paper.covariance[0, 0]), rel=0.1)
