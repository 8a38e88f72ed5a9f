"""Noise-model identification (docs/models.md §4): autocorrelation against a NumPy loop, every
estimator by simulate-then-fit-recover, the exact likelihood against a dense Gaussian
density, structure selection, the Allan deviation against brute force (and allantools),
and bad input."""

import json

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
import scipy.stats

from accel_jax._noise import (
    ExponentialCosine,
    GaussMarkov,
    NoiseSum,
    RandomWalk,
    WhiteNoise,
    allan_coefficients,
    allan_deviation,
    allan_variance_of_model,
    autocorrelation,
    fit_autocorrelation_least_squares,
    fit_exp_cosine_paper,
    fit_gauss_markov_paper,
    fit_maximum_likelihood,
    initial_model,
    log_likelihood,
    select_noise_model,
    simulate_noise,
)

DT = 0.5


def _records(model, n, count, seed):
    keys = jax.random.split(jax.random.key(seed), count)
    return jax.vmap(lambda k: simulate_noise(model, DT, n, key=k))(keys)


def test_autocorrelation_matches_numpy_loop_and_transforms():
    x = np.asarray(jax.random.normal(jax.random.key(0), (257,))) + 3.0
    m = x.mean()
    brute = [np.sum((x[: 257 - k] - m) * (x[k:] - m)) / (257 - k) for k in range(41)]
    np.testing.assert_allclose(autocorrelation(x, 40), brute, rtol=1e-11, atol=1e-13)
    batch = jnp.stack([x, 2 * x])
    out = jax.jit(jax.vmap(lambda r: autocorrelation(r, 40)))(batch)
    np.testing.assert_allclose(out[1], 4 * np.asarray(brute), rtol=1e-11)


def test_autocorrelation_bad_input():
    with pytest.raises(ValueError, match="too short for 50 lags"):
        autocorrelation(jnp.arange(60.0), 50)
    with pytest.raises(ValueError, match=r"constant \(1.5"):
        autocorrelation(jnp.full(100, 1.5), 10)
    with pytest.raises(ValueError, match="sample 7 .* nan"):
        autocorrelation(jnp.arange(100.0).at[7].set(jnp.nan), 10)
    with pytest.raises(ValueError, match="1-D"):
        autocorrelation(jnp.ones((10, 10)), 2)
    # Inside jit the value checks become runtime errors, never a silent NaN.
    with pytest.raises(Exception, match="NaN or inf"):
        jax.jit(lambda r: autocorrelation(r, 10))(jnp.arange(100.0).at[7].set(jnp.nan))
    with pytest.raises(ValueError, match="sample_interval"):
        fit_gauss_markov_paper(jnp.array([1.0, 0.5]), -1.0)


def test_gauss_markov_rule_15_and_least_squares_recover_parameters():
    truth = GaussMarkov(2.0, 10.0)  # τ_c = 20 samples
    records = _records(truth, 3000, 12, seed=1)
    R = jax.vmap(lambda r: autocorrelation(r, 60))(records)
    # Rule (15) over lags up to τ_c (20 samples), where r_j > e^{-1}.
    paper = jax.vmap(lambda r: fit_gauss_markov_paper(r[:21], DT))(R)
    tau_paper = np.asarray(paper.model.correlation_time)
    ls = jax.vmap(lambda r: fit_autocorrelation_least_squares(GaussMarkov(1.0, 5.0), r, DT))(R)
    tau_ls = np.asarray(ls.model.correlation_time)
    # 150 correlation times per record: no bias beyond 3 standard errors of the mean (the
    # per-record spread is ~25 % for rule (15) and ~40 % for least squares), plus the ~2 %
    # the mean removal in (11) costs.
    for tau in (tau_paper, tau_ls):
        assert abs(np.mean(tau) - 10.0) < 3 * np.std(tau, ddof=1) / np.sqrt(tau.size) + 0.2
        assert 0.05 < np.std(tau) / 10.0 < 0.6
    assert np.mean(np.asarray(paper.model.sigma)) == pytest.approx(2.0, rel=0.05)
    # Noise-free autocovariance: every estimator is exact.
    exact = truth.autocovariance(jnp.arange(61) * DT)
    assert float(fit_gauss_markov_paper(exact[:21], DT).model.correlation_time) == pytest.approx(
        10.0, rel=1e-12
    )
    fit = fit_autocorrelation_least_squares(GaussMarkov(1.0, 5.0), exact, DT)
    assert float(fit.model.correlation_time) == pytest.approx(10.0, rel=1e-8)


def test_exp_cosine_rules_19_21_recover_parameters():
    truth = ExponentialCosine(1.0, 0.05, 0.2)  # first zero at τ_β = π/(2β) = 7.85 s
    exact = truth.autocovariance(jnp.arange(41) * DT)
    fit = fit_exp_cosine_paper(exact, DT)
    # Linear interpolation of the zero between samples: β̂ within 0.3 %; α̂ then follows.
    assert float(fit.model.angular_frequency) == pytest.approx(0.2, rel=3e-3)
    assert float(fit.model.decay_rate) == pytest.approx(0.05, rel=0.05)
    records = _records(truth, 4000, 8, seed=2)
    R = jax.vmap(lambda r: autocorrelation(r, 40))(records)
    fits = jax.vmap(lambda r: fit_exp_cosine_paper(r, DT))(R)
    assert np.mean(np.asarray(fits.model.angular_frequency)) == pytest.approx(0.2, rel=0.05)
    assert np.mean(np.asarray(fits.model.decay_rate)) == pytest.approx(0.05, rel=0.3)
    # No zero within the lags: a result code, raised by default.
    gm = GaussMarkov(1.0, 100.0).autocovariance(jnp.arange(11) * DT)
    with pytest.raises(Exception, match="no zero"):
        fit_exp_cosine_paper(gm, DT)


def _dense_conditional_loglik(model, x):
    """log p(x_2..N | x_1) from the dense Toeplitz covariance (SciPy), mean removed."""
    x = np.asarray(x) - np.mean(x)
    n = x.shape[0]
    acov = np.asarray(model.autocovariance(jnp.arange(n) * DT))
    cov = scipy.linalg.toeplitz(acov)
    full = scipy.stats.multivariate_normal(np.zeros(n), cov).logpdf(x)
    first = scipy.stats.norm(0, np.sqrt(acov[0])).logpdf(x[0])
    return full - first


@pytest.mark.parametrize(
    "model",
    [
        GaussMarkov(1.3, 4.0),
        ExponentialCosine(0.7, 0.3, 0.9),
        NoiseSum((WhiteNoise(0.4), GaussMarkov(1.0, 3.0))),
    ],
)
def test_exact_likelihood_matches_dense_gaussian(model):
    x = simulate_noise(model, DT, 150, key=jax.random.key(3))
    assert float(log_likelihood(model, x, DT)) == pytest.approx(
        _dense_conditional_loglik(model, x), rel=1e-9
    )


def test_random_walk_likelihood_is_the_increments_density():
    # Diffuse start: log p(x_2..N | x_1) is the density of N−1 independent increments.
    model = RandomWalk(0.3)
    x = simulate_noise(model, DT, 300, key=jax.random.key(4))
    expected = scipy.stats.norm(0, np.sqrt(0.3 * DT)).logpdf(np.diff(np.asarray(x))).sum()
    assert float(log_likelihood(model, x, DT)) == pytest.approx(expected, rel=1e-6)


def test_maximum_likelihood_recovers_with_calibrated_intervals():
    truth = GaussMarkov(2.0, 10.0)
    records = _records(truth, 2000, 12, seed=5)
    fit = eqx.filter_jit(
        eqx.filter_vmap(lambda r: fit_maximum_likelihood(GaussMarkov(1.0, 3.0), r, DT))
    )(records)
    tau = np.asarray(fit.model.correlation_time)
    assert np.mean(tau) == pytest.approx(10.0, rel=0.1)
    lower, upper = np.asarray(fit.lower.correlation_time), np.asarray(fit.upper.correlation_time)
    # 95 % intervals: at least 9 of 12 cover the truth (P(fewer) < 2 % if calibrated).
    assert np.sum((lower < 10.0) & (10.0 < upper)) >= 9
    # The intervals' width (observed information) matches the spread of τ̂ across records
    # to within a factor of two (12 records: the sample spread is itself good to ~20 %).
    rel_se = np.mean((np.log(upper) - np.log(lower)) / (2 * 1.96))
    assert 0.5 < rel_se / np.std(np.log(tau)) < 2.0


def test_maximum_likelihood_convergence_is_judged_at_the_point_returned():
    """A fit whose BFGS budget ran out at the optimum counts as converged (Newton-step
    test on the exact Hessian); one stopped short of the optimum does not."""
    from accel_jax._noise import NoiseFitResult

    x = simulate_noise(GaussMarkov(2.0, 10.0), DT, 2000, key=jax.random.key(11))
    fit = jax.jit(fit_maximum_likelihood)
    best = fit(GaussMarkov(1.0, 3.0), x, DT)
    assert best.result == NoiseFitResult.successful
    # Restarted at the optimum with a budget of one step: BFGS itself reports max_steps,
    # but the point returned is the optimum.
    again = fit_maximum_likelihood(best.model, x, DT, max_steps=1, throw=False)
    assert again.result == NoiseFitResult.successful
    np.testing.assert_allclose(again.model.correlation_time, best.model.correlation_time, rtol=1e-6)
    # Two steps from a poor start: far from the optimum, so not converged (and raises).
    short = fit_maximum_likelihood(GaussMarkov(1.0, 3.0), x, DT, max_steps=2, throw=False)
    assert short.result == NoiseFitResult.not_converged
    with pytest.raises(Exception, match="did not converge"):
        fit_maximum_likelihood(GaussMarkov(1.0, 3.0), x, DT, max_steps=2)


def test_structure_selection_picks_the_true_structure():
    truth = NoiseSum((WhiteNoise(0.5), GaussMarkov(1.0, 5.0)))
    x = simulate_noise(truth, DT, 1200, key=jax.random.key(6))
    structures = ("white", "gauss_markov", "white+gauss_markov")
    sel = select_noise_model(x, DT, structures=structures, residual_lags=15)
    assert sel.chosen == "white+gauss_markov"
    rows = {row["structure"]: row for row in sel.table}
    assert rows["white+gauss_markov"]["delta"] == 0.0
    # Wrong structures leave correlated innovations; the right one leaves white ones.
    assert rows["white"]["ljung_box_p"] < 1e-6
    assert rows["gauss_markov"]["ljung_box_p"] < 1e-3
    assert rows["white+gauss_markov"]["ljung_box_p"] > 1e-3
    params = rows["white+gauss_markov"]["parameters"]
    assert params["gauss_markov.correlation_time_s"] == pytest.approx(5.0, rel=0.5)
    assert params["white.sigma"] == pytest.approx(0.5, rel=0.2)
    json.dumps(sel.table)  # the table is plain data
    with pytest.raises(ValueError, match="unknown or repeated"):
        initial_model("white+pink", x, DT)
    with pytest.raises(ValueError, match="constant"):
        select_noise_model(jnp.zeros(500), DT)


def test_allan_deviation_matches_brute_force_and_allantools():
    x = np.asarray(jax.random.normal(jax.random.key(7), (1000,)))
    sizes = [1, 2, 5, 10, 50, 200]
    taus, adev = allan_deviation(x, DT, sizes)
    theta = np.concatenate([[0.0], np.cumsum(x - x.mean())]) * DT
    for m, value in zip(sizes, np.asarray(adev), strict=True):
        terms = [
            (theta[k + 2 * m] - 2 * theta[k + m] + theta[k]) ** 2 for k in range(len(theta) - 2 * m)
        ]
        expected = np.sqrt(np.sum(terms) / (2 * (m * DT) ** 2 * len(terms)))
        assert value == pytest.approx(expected, rel=1e-12)
    allantools = pytest.importorskip("allantools")
    t2, ad2, _, _ = allantools.oadev(x, rate=1 / DT, data_type="freq", taus=np.asarray(taus))
    np.testing.assert_allclose(t2, taus)
    np.testing.assert_allclose(ad2, adev, rtol=1e-10)
    with pytest.raises(ValueError, match="cluster sizes"):
        allan_deviation(x, DT, [600])


def test_allan_slopes_identify_white_and_random_walk():
    sizes = [1, 2, 4, 8, 16, 32, 64, 128, 256]
    white = simulate_noise(WhiteNoise(0.2), DT, 8000, key=jax.random.key(8))
    taus, adev = allan_deviation(white, DT, sizes)
    coeff = allan_coefficients(taus, adev)
    assert float(coeff.white) == pytest.approx(0.2 * np.sqrt(DT), rel=0.05)
    assert np.all(np.abs(np.asarray(coeff.slopes) + 0.5) < 0.15)
    walk = simulate_noise(RandomWalk(1e-4), DT, 8000, key=jax.random.key(9))
    taus, adev = allan_deviation(walk, DT, sizes)
    coeff = allan_coefficients(taus, adev)
    assert float(coeff.random_walk) == pytest.approx(1e-2, rel=0.35)
    assert np.mean(np.asarray(coeff.slopes)[3:]) == pytest.approx(0.5, abs=0.15)
    # A Gauss-Markov record's ADEV follows the exact Allan variance of its autocovariance.
    gm = GaussMarkov(1.0, 5.0)
    records = _records(gm, 8000, 4, seed=10)
    theory = np.sqrt(np.asarray(allan_variance_of_model(gm, DT, sizes)))
    measured = np.mean([np.asarray(allan_deviation(r, DT, sizes)[1]) for r in records], axis=0)
    # 4 × 8000 samples: the ADEV at τ ≤ 32 s (≤ 13 τ_c) is good to a few %.
    np.testing.assert_allclose(measured[:6], theory[:6], rtol=0.1)


def test_model_validation():
    with pytest.raises(ValueError, match="correlation_time .* -3.0 s"):
        GaussMarkov(1.0, -3.0)
    with pytest.raises(ValueError, match="at least two"):
        NoiseSum((WhiteNoise(1.0),))
    with pytest.raises(ValueError, match="no autocovariance"):
        RandomWalk(1.0).autocovariance(jnp.arange(3.0))


def test_ljung_box_is_the_standard_statistic_with_fitted_parameters_removed():
    """One Ljung–Box for the library (`aj.noise.ljung_box`, the diagnosis's too): Q from the
    standard autocorrelation r_k = Σ e_t e_{t−k}/Σ e_t² (checked against a direct sum),
    χ²(L − p) for p fitted parameters (scipy)."""
    from scipy import stats

    import accel_jax as aj
    from accel_jax.diagnose import ljung_box as diagnose_ljung_box

    assert diagnose_ljung_box is aj.noise.ljung_box
    rng = np.random.default_rng(4)
    e = rng.normal(size=600) + 3.0
    result = aj.noise.ljung_box(e, 12, 3)
    d = e - e.mean()
    r = [np.sum(d[k:] * d[:-k]) / np.sum(d * d) for k in range(1, 13)]
    q = 600 * 602 * sum(rk**2 / (600 - k) for k, rk in enumerate(r, start=1))
    assert result["statistic"] == pytest.approx(q, rel=1e-12)
    assert result["p_value"] == pytest.approx(stats.chi2.sf(q, 9), rel=1e-8)
    assert aj.noise.ljung_box(np.ones(100))["p_value"] == 1.0


def test_allan_deviation_intervals_are_allantools_and_cover_the_truth():
    """The ADEV intervals are allantools' own (noise identification, Greenhall EDF, χ²) on
    the same data, and on white records (true ADEV σ_x √(Δ/τ)) the ±1σ intervals contain
    the truth about 68 % of the time (20 records × 10 octaves; binomial 3σ band, widened
    for the octaves' correlation within a record)."""
    import allantools

    import accel_jax as aj

    dt, sigma = 0.01, 2e-3
    rng = np.random.default_rng(11)
    x = rng.normal(size=20000) * sigma
    adev = aj.noise.allan_deviation_intervals(x, dt)
    identified = ~np.isnan(adev.alpha)  # where allantools can tell the noise (≥ ~30 clusters)
    assert identified.sum() >= 8
    for m, dev, lo, hi in zip(
        np.rint(adev.taus[identified] / dt).astype(int),
        adev.deviation[identified],
        adev.lower[identified],
        adev.upper[identified],
        strict=True,
    ):
        ref = allantools.confidence_interval_noiseID(x, dev, m, dev_type="oadev", data_type="freq")
        assert (lo, hi) == pytest.approx(ref, rel=1e-12)
    _, oadev, _, _ = allantools.oadev(x, rate=1 / dt, data_type="freq", taus=adev.taus)
    np.testing.assert_allclose(adev.deviation, oadev, rtol=1e-10)
    covered = total = 0
    for seed in range(20):
        x = np.random.default_rng(100 + seed).normal(size=20000) * sigma
        a = aj.noise.allan_deviation_intervals(x, dt)
        truth = sigma * np.sqrt(dt / a.taus)
        covered += int(np.sum((a.lower <= truth) & (truth <= a.upper)))
        total += truth.size
    assert 0.55 <= covered / total <= 0.80, covered / total
    assert np.all(np.isnan(a.alpha) | (a.alpha == 0))  # white FM wherever identified


def test_allan_deviation_intervals_bad_input():
    import accel_jax as aj

    with pytest.raises(ValueError, match="too short"):
        aj.noise.allan_deviation_intervals(np.random.default_rng(0).normal(size=12), 0.01)
    with pytest.raises(ValueError, match="confidence"):
        aj.noise.allan_deviation_intervals(
            np.random.default_rng(0).normal(size=1000), 0.01, confidence=1.5
        )
    # The time vector passed where the sample interval belongs (analyse_static_record(t, y)
    # turned around): one short message naming the array's shape, not its 1e5 values.
    t = np.arange(100_000) * 0.005
    with pytest.raises(ValueError, match=r"an array of shape \(100000,\)") as caught:
        aj.noise.allan_deviation_intervals(np.sin(t), t)
    assert len(str(caught.value)) < 200


def test_ljung_box_refuses_non_finite_or_tiny_residuals():
    import accel_jax as aj

    with pytest.raises(ValueError, match="non-finite"):
        aj.noise.ljung_box(np.array([1.0, np.nan, 2.0] * 50))
    with pytest.raises(ValueError, match="at least 4"):
        aj.noise.ljung_box(np.array([1.0, 2.0]))


def test_allan_deviation_intervals_on_a_drift_like_record():
    """A record steeper than random-walk FM (a random walk of a random walk: α ≤ −3
    identified) still gets finite intervals (random-walk FM's EDF), no assertion error."""
    import accel_jax as aj

    x = np.cumsum(np.cumsum(np.random.default_rng(2).normal(size=4000)))
    adev = aj.noise.allan_deviation_intervals(x, 0.01)
    assert np.nanmax(adev.alpha) <= -3
    assert np.all(np.isfinite(adev.edf)) and np.all(adev.edf > 0)
    assert np.all((adev.lower <= adev.deviation) & (adev.deviation <= adev.upper))


def test_shaping_filter_17_read_with_the_zero_at_minus_b_has_autocorrelation_16():
    # The paper's filter (17), b² = α² + β², read as σ√(2α)(p + b)/(p² + 2αp + b²) and driven
    # by unit white noise: its stationary autocovariance C e^{Aτ} P Cᵀ (P from the
    # Lyapunov equation, SciPy) is ExponentialCosine's σ² e^{−α|τ|} cos βτ; without the
    # zero (numerator σ√(2α)·b) it is e^{−α|τ|}(cos βτ + (α/β) sin β|τ|) instead.
    sigma, alpha, beta = 0.7, 0.3, 1.9
    b = np.hypot(alpha, beta)
    a = np.array([[0.0, 1.0], [-(b**2), -2 * alpha]])  # controllable canonical form
    noise_in = np.array([[0.0], [1.0]])
    p = scipy.linalg.solve_continuous_lyapunov(a, -noise_in @ noise_in.T)
    lags = np.linspace(0.0, 12.0, 41)
    model = ExponentialCosine(sigma, alpha, beta)
    expected = np.asarray(model.autocovariance(jnp.asarray(lags)))
    gain = sigma * np.sqrt(2 * alpha)
    for numerator, target in (
        (np.array([[b, 1.0]]), expected),  # p + b
        (np.array([[b, 0.0]]), None),  # b alone
    ):
        c = gain * numerator
        covariance = np.array([(c @ scipy.linalg.expm(a * t) @ p @ c.T).item() for t in lags])
        if target is None:
            # K/(p² + 2αp + b²) has variance K²/(4αb²): here σ²/2.
            variance = (gain * b) ** 2 / (4 * alpha * b**2)
            damped = variance * np.exp(-alpha * lags)
            target = damped * (np.cos(beta * lags) + alpha / beta * np.sin(beta * lags))
        np.testing.assert_allclose(covariance, target, rtol=1e-9, atol=1e-12 * sigma**2)
