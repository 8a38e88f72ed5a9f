"""The blind harness's ideal observer (studies/sensor_noise_harness.py, NumPy/SciPy only):
its expected evidence checked against exact time-domain values."""

import math
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.linalg import toeplitz

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "studies"))
import sensor_noise_harness as harness  # noqa: E402


def _gaussian_2kl(cov_true, cov_alt, project=True):
    """2 KL(N(0, C_true) ‖ N(0, C_alt)) of the record with its level taken out (projected
    on the complement of the constant, as the diagnosis treats the level as unknown): the
    expected 2 ln Λ of the truth against the alternative, exactly."""
    m = cov_true.shape[0]
    if project:
        basis, _ = np.linalg.qr(np.concatenate([np.ones((m, 1)), np.eye(m)[:, : m - 1]], 1))
        q = basis[:, 1:]
        cov_true, cov_alt = q.T @ cov_true @ q, q.T @ cov_alt @ q
    solved = np.linalg.solve(cov_alt, cov_true)
    _, logdet = np.linalg.slogdet(solved)
    return float(np.trace(solved) - cov_true.shape[0] - logdet)


@pytest.mark.parametrize(
    "name, spec",
    [
        ("gauss_markov", {"gauss_markov": (0.5e-3, 0.4)}),
        ("random_walk", {"random_walk": (3e-3) ** 2 / 9.0}),
        ("flicker", {"flicker": 0.15e-3}),
        ("bandlimit", {"bandlimit": 20.0, "gauss_markov": (0.5e-3, 0.05)}),
    ],
)
def test_oracle_of_a_stochastic_effect_is_the_exact_divergence(name, spec):
    """Against the dense-matrix 2 KL of the level-free record (its first difference), the
    covariances from the truth's own spectra; and a random walk's value against the
    level-domain one (covariance σ²I + qΔ min(i, j), the level projected out)."""
    n, dt, white = 900, 0.01, 1e-3  # training part: 600 samples
    spec = {"white": white, **spec}
    full = harness._differenced_autocovariance(spec, dt, 599)
    alt = harness._differenced_autocovariance(spec, dt, 599, without=name)
    dense = _gaussian_2kl(toeplitz(full), toeplitz(alt), project=False)
    assert harness.oracle_evidence(spec, dt, n)[name] == pytest.approx(dense, rel=1e-8)
    if name == "random_walk":
        k = np.arange(600)
        walk = white**2 * np.eye(600) + spec[name] * dt * np.minimum.outer(k, k)
        level = _gaussian_2kl(walk, white**2 * np.eye(600))
        assert dense == pytest.approx(level, rel=1e-6)


def test_oracle_of_a_transient_and_a_line_match_exact_values():
    """The transient's oracle against the level-domain GLS with the level projected out
    (white noise plus a random walk from the record's start: covariance σ²I + qΔ min(i, j)),
    and in white noise against the closed form; the line's against A² m / 2σ²."""
    n, dt, white = 900, 0.01, 1e-3
    m = 600
    a, tau = 3e-3, 0.6
    k = np.arange(m)
    signal = a * np.exp(-k * dt / tau)
    ones = np.ones(m)

    def projected(cov):
        solved_s, solved_1 = np.linalg.solve(cov, signal), np.linalg.solve(cov, ones)
        return signal @ solved_s - (ones @ solved_s) ** 2 / (ones @ solved_1)

    for walk in (0.0, (3 * white) ** 2 / (n * dt)):
        spec = {"white": white, "transient": (a, tau), "lines": [(7.3, 2e-4)]}
        if walk:
            spec["random_walk"] = walk
        cov = white**2 * np.eye(m) + walk * dt * np.minimum.outer(k, k)
        oracle = harness.oracle_evidence(spec, dt, n)
        assert oracle["startup_transient"] == pytest.approx(projected(cov), rel=1e-6)
    white_only = harness.oracle_evidence(
        {"white": white, "transient": (a, tau), "lines": [(7.3, 2e-4)]}, dt, n
    )
    closed = a**2 * np.sum(np.exp(-2 * k * dt / tau)) / white**2
    level = (a * np.sum(np.exp(-k * dt / tau))) ** 2 / m / white**2
    assert white_only["startup_transient"] == pytest.approx(closed - level, rel=1e-6)
    assert white_only["sinusoid"] == pytest.approx(2e-4**2 * m / 2 / white**2, rel=1e-12)


def test_detectable_needs_twice_the_bar():
    n = 10000
    bar = 10 + math.log(n // 2)
    assert harness.detectable("flicker", {"flicker": 2.01 * bar}, n)
    assert not harness.detectable("flicker", {"flicker": 1.99 * bar}, n)
    assert harness.detectable("quantization", {}, n)


def test_realized_evidence_is_the_exact_likelihood_ratio_and_averages_to_the_oracle():
    """On one record, against the dense-matrix Gaussian log-likelihood ratio of the whole
    record's first difference; over records drawn by the truth generator, its mean is the
    oracle's expected value for records of that length (within 3 standard errors)."""
    from scipy.stats import multivariate_normal

    n, dt = 600, 0.01
    spec = {"white": 1e-3, "gauss_markov": (0.6e-3, 0.05)}
    rng = np.random.default_rng(3)
    x = harness.noise_truth.record(rng, n, dt, spec)
    y = np.diff(x)
    full = toeplitz(harness._differenced_autocovariance(spec, dt, n - 1))
    alt = toeplitz(harness._differenced_autocovariance(spec, dt, n - 1, without="gauss_markov"))
    dense = 2 * (multivariate_normal(cov=full).logpdf(y) - multivariate_normal(cov=alt).logpdf(y))
    found = harness.realized_evidence(spec, dt, x)["gauss_markov"]
    assert found == pytest.approx(dense, rel=1e-8)

    draws = [
        harness.realized_evidence(spec, dt, harness.noise_truth.record(rng, n, dt, spec))
        for _ in range(100)
    ]
    values = np.array([d["gauss_markov"] for d in draws])
    # the oracle's is on the training part, 2/3 of its n: records of 900 → 600 samples
    expected = harness.oracle_evidence(spec, dt, 900)["gauss_markov"]
    assert abs(values.mean() - expected) < 3 * values.std(ddof=1) / math.sqrt(values.size)
    # a record with a line: its phase is not the observer's, so no value
    assert harness.realized_evidence({**spec, "lines": [(1.0, 1e-3)]}, dt, x) == {}


def test_score_counts_each_effect_by_expected_and_realized_evidence():
    """The scoring of rows (synthetic here): named rates over all records, where the
    expected oracle clears twice the bar, and where the realized evidence clears the bar
    (stochastic effects only: quantisation and lines have none)."""
    n = 10000
    bar = 10 + math.log(n // 2)
    rows = [
        {
            "truth": {"effects": ["flicker", "quantization"], "step_g": 1e-3},
            "oracle": {"flicker": 3 * bar},
            "realized": {"flicker": 1.5 * bar},
            "verdict": "flicker+quantization+unexplained",
            "effects": ["flicker", "quantization"],
            "spectral_change": True,
            "step_relative_error": 0.01,
            "seconds": 1.0,
        },
        {
            "truth": {"effects": ["flicker"]},
            "oracle": {"flicker": 3 * bar},
            "realized": {"flicker": 0.5 * bar},
            "verdict": "none",
            "effects": [],
            "seconds": 1.0,
        },
        {
            "truth": {"effects": []},
            "oracle": {},
            "realized": {},
            "verdict": "none",
            "effects": [],
            "seconds": 1.0,
        },
    ]
    score = harness.score(rows, n)
    flicker = score["per_effect"]["flicker"]
    assert (flicker["named"], flicker["records"]) == (1, 2)
    assert (flicker["named_when_detectable"], flicker["detectable"]) == (1, 2)
    assert (flicker["named_when_realized_detectable"], flicker["realized_detectable"]) == (1, 1)
    assert score["per_effect"]["quantization"]["realized_detectable"] == 0
    assert score["false_alarms"] == 0 and score["steps_within_5pct"] == 1
    assert score["records_with_a_false_spectral_change"] == 1


def test_realized_evidence_where_the_covariance_is_not_positive_definite():
    """A low-pass far below Nyquist leaves the differenced spectrum near zero over most of
    the band: the whole record's Toeplitz covariance is then not positive definite in
    float64 (a Durbin–Levinson variance ≤ 0), and the observer is not computed (None, the
    row marked) instead of raising — a harness run of 624 records once died there at the
    567th (harness seed 2026: bandlimit + exp-cosine)."""
    spec = {
        "white": 0.0013159045828774348,
        "bandlimit": 14.288698028117059,
        "exp_cosine": (0.00242826206239547, 6.537273760195531, 45.63364465629214),
    }
    rng = np.random.default_rng(0)
    x = harness.noise_truth.record(rng, 10000, 0.01, spec)
    assert harness.realized_evidence(spec, 0.01, x) is None
    assert harness.realized_evidence_unavailable(spec, {})
    assert not harness.realized_evidence_unavailable({**spec, "lines": [(1.0, 1e-3)]}, {})
    row = {"truth": {"effects": ["bandlimit"]}, "oracle": {}, "realized": {}, "verdict": "none"}
    row.update(effects=[], seconds=1.0, realized_unavailable=True)
    assert harness.score([row], 10000)["realized_unavailable_records"] == 1
