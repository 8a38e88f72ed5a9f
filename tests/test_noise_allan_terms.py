"""`fit_allan_terms`, the IEEE Std 952/1554 noise terms of an Allan deviation: the design
matrix against the formula on a noise-free curve, each bootstrap simulator against its
column, the flicker normalisation (two-sided PSD B²/(2π|f|) → ADEV floor √(2 ln 2/π)·B),
simulate-then-fit-then-recover coverage of the intervals with truth generators independent
of the bootstrap's, a second method for the point estimate, and bad input.

The truth generators: white noise and random walks by NumPy; quantisation noise by really
rounding the integrated record to a quantum q (Q = q/√12); flicker as a sum of first-order
Gauss-Markov (AR(1)) recursions whose weights fit the PSD B²/(2π|f|) over the sampled band
(time domain, nothing shared with the bootstrap's FFT shaping); the ramp R·t.
"""

import math

import jax
import numpy as np
import pytest
from scipy.optimize import nnls
from scipy.signal import lfilter

import accel_jax as aj
from accel_jax._noise import allan_terms as at
from accel_jax._noise.allan_intervals import octave_cluster_sizes

DT = 0.01
TERMS = at.TERM_NAMES
FLICKER = 2 * math.log(2) / math.pi


# ---------------------------------------------------------------------------------------
# Truth generators (independent of `allan_terms._simulate`)


def _gauss_markov_flicker_weights(n, dt, per_decade=3):
    """(φ_j, σ_j²/B²) of AR(1) components, corners 3 per decade from 0.1/(nΔ) to Nyquist,
    weights by NNLS so that Σ σ_j² Δ(1 − φ_j²)/|1 − φ_j e^{−iω}|² ≈ 1/(2π|f|) on a log grid
    of the sampled band (relative error)."""
    ratio = 10 ** (1 / per_decade)
    low, high = 0.1 / (n * dt), 0.5 / dt
    corners = low * ratio ** np.arange(int(np.floor(np.log(high / low) / np.log(ratio))) + 1)
    phi = np.exp(-2 * np.pi * corners * dt)
    f = np.geomspace(1 / (n * dt), 0.5 / dt, 400)
    omega = 2 * np.pi * f * dt
    psd = dt * (1 - phi**2) / (1 - 2 * phi * np.cos(omega[:, None]) + phi**2)
    target = 1 / (2 * np.pi * f)
    weights, _ = nnls(psd / target[:, None], np.ones_like(f))
    return phi, weights


def _flicker_truth(n, dt, b, rng):
    x = np.zeros(n)
    for phi, weight in zip(*_gauss_markov_flicker_weights(n, dt), strict=True):
        if weight == 0:
            continue
        variance = weight * b**2
        w = rng.standard_normal(n + 1) * math.sqrt(variance * (1 - phi**2))
        w[0] = rng.standard_normal() * math.sqrt(variance)  # stationary start
        x += lfilter([1.0], [1.0, -phi], w)[1:]
    return x


def _truth_record(n, dt, rng, Q=0.0, N=0.0, B=0.0, K=0.0, R=0.0):
    x = np.zeros(n)
    if N:
        x += rng.normal(0.0, N / math.sqrt(dt), n)
    if B:
        x += _flicker_truth(n, dt, B, rng)
    if K:
        x += np.cumsum(rng.normal(0.0, K * math.sqrt(dt), n))
    if R:
        x += R * dt * np.arange(n)
    if Q:  # round the integrated record to a quantum q: white error of variance q²/12
        q = Q * math.sqrt(12)
        theta = rng.uniform(0, q) + np.concatenate([[0.0], np.cumsum(x) * dt])
        x = np.diff(q * np.round(theta / q)) / dt
    return x


def _ieee_avar(taus, c):
    """The IEEE Std 952 formula, c = {name: coefficient}."""
    taus = np.asarray(taus, float)
    return (
        3 * c.get("Q", 0) ** 2 / taus**2
        + c.get("N", 0) ** 2 / taus
        + FLICKER * c.get("B", 0) ** 2
        + c.get("K", 0) ** 2 * taus / 3
        + c.get("R", 0) ** 2 * taus**2 / 2
    )


# ---------------------------------------------------------------------------------------
# The design matrix and the simulators


def test_noise_free_curve_recovers_the_terms():
    """A noise-free σ²(τ) from the IEEE formula is fitted back to 1e-6 by the weighted NNLS
    (formula columns), and the sampled-process columns the fit uses converge to the
    formula for τ ≫ Δ and recover their own noise-free curve just as well."""
    n = 2**17
    sizes = octave_cluster_sizes(n)
    taus = DT * np.asarray(sizes, float)
    truth = {"Q": 3e-6, "N": 1e-4, "B": 2e-4, "K": 3e-5, "R": 2e-6}
    c_true = np.array([truth[t] ** 2 for t in TERMS])
    root_edf = np.sqrt(at._edf_table(TERMS, sizes, n))
    formula = at._design(TERMS, taus)
    np.testing.assert_allclose(formula @ c_true, _ieee_avar(taus, truth), rtol=1e-14)
    c, free, se = at._fit(formula @ c_true, formula, root_edf, ramp=4)
    np.testing.assert_allclose(np.sqrt(c), np.sqrt(c_true), rtol=1e-6)
    np.testing.assert_allclose(free, c_true, rtol=1e-6)
    assert np.all(se > 0)

    sampled = at._design(TERMS, taus, DT, n)
    far = taus >= 256 * DT
    np.testing.assert_allclose(sampled[far], formula[far], rtol=2e-3)  # B: −0.1 % at N/16
    np.testing.assert_allclose(sampled[:, [0, 1, 4]], formula[:, [0, 1, 4]], rtol=1e-14)
    c, _, _ = at._fit(sampled @ c_true, sampled, root_edf, ramp=4)
    np.testing.assert_allclose(np.sqrt(c), np.sqrt(c_true), rtol=1e-6)


def test_bootstrap_simulators_have_their_columns_allan_variance():
    """Each simulated term's mean σ̂²(τ) over many records is its design column (within
    4 standard errors of the Monte Carlo mean); the ramp is exact; the batched ADEV is
    `allan_deviation`'s."""
    n, count = 4096, 200
    sizes = tuple(octave_cluster_sizes(n))
    taus = DT * np.asarray(sizes, float)
    rng = np.random.default_rng(3)
    for name in ("Q", "N", "B", "K"):
        avars = at._batched_avar(at._simulate({name: 1.0}, n, DT, rng, count), DT, sizes)
        column = at._design((name,), taus, DT, n)[:, 0]
        mean, error = avars.mean(0), avars.std(0) / math.sqrt(count)
        assert np.all(np.abs(mean - column) < 4 * error), (name, mean / column - 1, error / column)
    ramp = at._batched_avar(at._simulate({"R": 1.0}, n, DT, rng, 1), DT, sizes)[0]
    np.testing.assert_allclose(ramp, taus**2 / 2, rtol=1e-8)

    x = at._simulate({"N": 1e-3, "B": 1e-3, "K": 1e-4}, n, DT, rng, 1)
    _, dev = aj.noise.allan_deviation(x[0], DT, sizes)
    np.testing.assert_allclose(at._batched_avar(x, DT, sizes)[0], np.asarray(dev) ** 2, rtol=1e-12)


def test_flicker_normalisation_gives_the_ieee_floor():
    """B is defined by the two-sided PSD S(f) = B²/(2π|f|) (one-sided B²/(πf)). The
    bootstrap's band-limited flicker has the exact ADEV `_sampled_flicker`, which tends to
    √(2 ln 2/π)·B for τ ≫ Δ; a Monte Carlo of its FFT generator reaches that floor; and the
    independent Gauss-Markov-sum truth has the same ADEV (its exact value, from its
    autocovariance) within 1 %, so both generators mean the same B."""
    n = 2**14
    sizes = octave_cluster_sizes(n)
    taus = DT * np.asarray(sizes, float)
    exact = at._sampled_flicker(taus, DT, n) / FLICKER
    assert exact[0] == pytest.approx(1.189, abs=2e-3)  # +19 % in σ² at τ = Δ
    # → 1 for τ ≫ Δ; the longest octave loses ~0.1 % to the frequencies below 1/(2NΔ).
    np.testing.assert_allclose(exact[taus >= 64 * DT], 1.0, atol=2e-3)

    b = 2e-4
    avars = at._batched_avar(
        at._simulate({"B": b}, n, DT, np.random.default_rng(5), 200), DT, sizes
    )
    floor = avars.mean(0)[(taus >= 16 * DT) & (taus <= 128 * DT)] / (FLICKER * b**2)
    np.testing.assert_allclose(floor, 1.0, atol=0.03)

    phi, weights = _gauss_markov_flicker_weights(n, DT)
    lags = np.arange(2 * max(sizes) + 1)
    acov = (weights[:, None] * phi[:, None] ** lags).sum(0)  # per B²
    truth = []
    for m in sizes:
        j = np.arange(-(m - 1), m)
        w = m - np.abs(j)
        truth.append((np.sum(w * acov[np.abs(j)]) - np.sum(w * acov[j + m])) / m**2)
    ratio = np.asarray(truth) / at._sampled_flicker(taus, DT, n)
    np.testing.assert_allclose(ratio, 1.0, atol=0.01)


# ---------------------------------------------------------------------------------------
# Coverage


COMPOSITES = {
    "N+K": {"N": 1e-4, "K": 1.7e-4},
    "N+B+K": {"N": 1e-4, "B": 3e-4, "K": 2e-4},
    "Q+N": {"Q": 5e-6, "N": 1e-4},
    "Q+N+B": {"Q": 5e-6, "N": 1e-4, "B": 3e-4},
    "N+R": {"N": 1e-4, "R": 2e-5},
    "N+K+R": {"N": 1e-4, "K": 1e-4, "R": 2e-5},
    "Q+N+R": {"Q": 5e-6, "N": 1e-4, "R": 2e-5},
    "N+B+R": {"N": 1e-4, "B": 3e-4, "R": 5e-5},
}


def test_intervals_cover_the_truth_and_absent_terms_are_not_supported():
    """Simulate (independent truth generators) → fit all five terms → recover: over 8
    composites × 20 records of 2^14 samples (τ = 0.01 … 10 s), every present term is
    inside its 95 % interval (an unsupported term's interval being [0, upper]) in ≥ 90 %
    of the records where it is present, and every absent term is reported not supported in
    ≥ 90 % of the records where it is absent. n_bootstrap = 79: with (B + 1)·0.025 = 2 the
    bootstrap-t ends are the 2nd order statistics, as exact in level as the default 199.
    Measured when written: present Q 58/60, N 153/160, B 59/60, K 58/60, R 76/80; absent
    not supported Q 94/100, B 99/100, K 99/100, R 80/80 (~23 s)."""
    per_composite = 20
    covered = {t: 0 for t in TERMS}
    present = {t: 0 for t in TERMS}
    unsupported = {t: 0 for t in TERMS}
    absent = {t: 0 for t in TERMS}
    outside = 0
    for k, truth in enumerate(COMPOSITES.values()):
        for i in range(per_composite):
            seed = 1000 * k + i
            x = _truth_record(2**14, DT, np.random.default_rng(seed), **truth)
            fit = aj.noise.fit_allan_terms(x, DT, n_bootstrap=79, seed=seed + 500)
            for t, term in fit.terms.items():
                if t in truth:
                    present[t] += 1
                    covered[t] += (term["lower"] or 0.0) <= truth[t] <= term["upper"]
                else:
                    absent[t] += 1
                    unsupported[t] += not term["supported"]
                if term["supported"]:
                    outside += not term["lower"] <= term["value"] <= term["upper"]
    report = (
        f"present terms covered {covered} of {present}; absent terms not supported "
        f"{unsupported} of {absent}; supported values outside their interval: {outside}"
    )
    print(report)
    for t in TERMS:
        assert covered[t] >= 0.9 * present[t], report
        assert unsupported[t] >= 0.9 * absent[t], report


# ---------------------------------------------------------------------------------------
# Point estimate against other methods, the result, bad input


def test_point_estimate_agrees_with_reading_the_curve_and_allan_coefficients():
    """On a white + random-walk record: N̂ against σ̂(τ)·√τ read where white noise
    dominates (K²τ/3 ≪ N²/τ, IEEE's reading at a slope of −1/2), K̂ against σ̂(τ)·√(3/τ)
    at the longest τ (slope +1/2), and both against `allan_coefficients` (log-space
    Levenberg-Marquardt on N, B, K); B is reported not supported."""
    n, true_n, true_k = 2**16, 1e-4, 1e-3
    rng = np.random.default_rng(21)
    x = _truth_record(n, DT, rng, N=true_n, K=true_k)
    fit = aj.noise.fit_allan_terms(x, DT, seed=1)
    terms = fit.terms
    assert terms["N"]["supported"] and terms["K"]["supported"]
    assert not terms["B"]["supported"] and terms["B"]["value"] is None
    white = fit.taus <= 0.02  # K²τ/3 < 0.3 % of N²/τ there
    read_n = np.mean(fit.deviation[white] * np.sqrt(fit.taus[white]))
    assert terms["N"]["value"] == pytest.approx(read_n, rel=0.02)
    assert terms["N"]["value"] == pytest.approx(true_n, rel=0.02)
    read_k = fit.deviation[-1] * math.sqrt(3 / fit.taus[-1])
    assert terms["K"]["value"] == pytest.approx(read_k, rel=0.35)
    other = aj.noise.allan_coefficients(fit.taus, fit.deviation)
    assert terms["N"]["value"] == pytest.approx(float(other.white), rel=0.03)
    assert terms["K"]["value"] == pytest.approx(float(other.random_walk), rel=0.2)
    for t in ("N", "K"):
        assert terms[t]["lower"] <= terms[t]["value"] <= terms[t]["upper"]


def test_result_fields_units_model_curve_and_float64():
    """Supported terms carry value and interval, unsupported ones only an upper bound;
    `deviation_at` reproduces `model_deviation` and follows the IEEE formula for τ ≫ Δ;
    a terms subset fits only those; the result is the same with JAX's x64 off (float64
    inside, the caller's setting untouched)."""
    x = _truth_record(2**13, DT, np.random.default_rng(8), N=1e-4, K=1e-3)
    fit = aj.noise.fit_allan_terms(x, DT, n_bootstrap=99, seed=2)
    assert isinstance(fit, aj.noise.AllanTerms)
    assert set(fit.terms) == set(TERMS) and fit.n_bootstrap == 99 and fit.confidence == 0.95
    assert fit.n_samples == 2**13 and "bootstrap" in fit.method
    for t, term in fit.terms.items():
        assert term["unit"] == at.TERM_UNITS[t]
        assert term["upper"] >= 0
        if term["supported"]:
            assert 0 < term["lower"] <= term["upper"] and term["value"] > 0
        else:
            assert term["value"] is None and term["lower"] is None
    np.testing.assert_allclose(fit.deviation_at(fit.taus), fit.model_deviation, rtol=1e-12)
    far = np.array([[3.0, 20.0]])
    coefficients = fit.fit_coefficients
    assert fit.deviation_at(far).shape == (1, 2)
    np.testing.assert_allclose(
        fit.deviation_at(far), np.sqrt(_ieee_avar(far, coefficients)), rtol=1e-3
    )
    subset = aj.noise.fit_allan_terms(x, DT, n_bootstrap=99, seed=2, terms=("K", "N"))
    assert list(subset.terms) == ["N", "K"]
    assert subset.terms["N"]["supported"] and subset.terms["K"]["supported"]

    before = jax.config.jax_enable_x64
    with jax.enable_x64(False):
        low = aj.noise.fit_allan_terms(x, DT, n_bootstrap=99, seed=2)
        assert not jax.config.jax_enable_x64
    assert jax.config.jax_enable_x64 == before
    assert low.terms == fit.terms
    np.testing.assert_array_equal(low.deviation, fit.deviation)


def test_bad_input_raises_value_error():
    rng = np.random.default_rng(0)
    x = rng.normal(size=4096)
    cases = [
        (dict(record=np.r_[x[:10], np.nan, x[11:]]), "finite"),
        (dict(record=x[:300]), "too short"),
        (dict(record=np.ones(4096)), "constant"),
        (dict(record=x.reshape(64, 64)), "1-D"),
        (dict(sample_interval=0.0), "sample_interval"),
        (dict(sample_interval=-0.01), "sample_interval"),
        (dict(sample_interval=float("nan")), "sample_interval"),
        (dict(terms=("N", "X")), "terms"),
        (dict(terms=("N", "N")), "terms"),
        (dict(terms=()), "terms"),
        (dict(terms=("R",)), "noise term"),
        (dict(confidence=1.0), "confidence"),
        (dict(confidence=0.0), "confidence"),
        (dict(confidence=float("nan")), "confidence"),
        (dict(n_bootstrap=10), "n_bootstrap"),
        (dict(n_bootstrap=100.5), "n_bootstrap"),
        (dict(confidence=0.999, n_bootstrap=199), "n_bootstrap"),
    ]
    for change, match in cases:
        arguments = dict(record=x, sample_interval=DT) | change
        record = arguments.pop("record")
        dt = arguments.pop("sample_interval")
        with pytest.raises(ValueError, match=match):
            aj.noise.fit_allan_terms(record, dt, **arguments)


def test_the_batched_adev_is_each_rows_allan_deviation():
    """`_batched_avar` maps `allan_deviation`'s kernel over the rows (`lax.map`): each row's
    σ̂² is that row's `allan_deviation`², whatever its neighbours (three different records,
    and a batch of one)."""
    n = 4096
    sizes = tuple(octave_cluster_sizes(n))
    rows = at._simulate({"N": 1e-3, "B": 1e-3, "K": 1e-4}, n, DT, np.random.default_rng(8), 3)
    rows[1] *= 40.0  # neighbours of very different size
    batched = at._batched_avar(rows, DT, sizes)
    assert batched.shape == (3, len(sizes))
    for row, avar in zip(rows, batched, strict=True):
        _, dev = aj.noise.allan_deviation(row, DT, sizes)
        np.testing.assert_allclose(avar, np.asarray(dev) ** 2, rtol=1e-12)
        np.testing.assert_allclose(at._batched_avar(row[None], DT, sizes)[0], avar, rtol=1e-12)
