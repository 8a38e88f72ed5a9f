"""The noise_identification study (studies/noise_identification.py): its quick run's
results, read from the session's shared quick report (each study script run alone in a
fresh process; see tests/conftest.py)."""

import numpy as np
import pytest


@pytest.mark.slow
def test_study_quick(quick_report):
    from helpers import study_result

    tmp_path, saved = study_result(quick_report, "noise_identification")
    for key in ("title", "summary", "figures", "assumptions", "provenance"):
        assert key in saved
    gm, ec = saved["gauss_markov"], saved["exp_cosine"]
    assert gm["tau_fit"] == pytest.approx(gm["tau_true"], rel=0.2)
    assert gm["sigma_fit"] == pytest.approx(gm["sigma_true"], rel=0.1)
    assert ec["beta_fit"] == pytest.approx(ec["beta_true"], rel=0.1)
    kal = saved["kalman"]
    assert (
        kal["wrong_model"]["fraction_outside_3sigma"]
        > 10 * kal["identified"]["fraction_outside_3sigma"]
    )
    assert kal["identified"]["fraction_outside_3sigma"] < 0.02
    for figure in saved["figures"]:
        assert (tmp_path / figure["file"]).exists() and figure["caption"]


@pytest.mark.slow
def test_study_allan_intervals(quick_report):
    """The Allan figure's ±1σ EDF intervals bracket each ADEV point and contain the true
    model's exact ADEV at most τ (nominal 68 % each; the τ of one record are correlated)."""
    import numpy as np
    from helpers import study_result

    _, saved = study_result(quick_report, "noise_identification")
    allan = saved["allan"]
    band = allan["interval_1sigma_rad_per_s"]
    adev = np.asarray(allan["adev_rad_per_s"])
    assert np.all(np.asarray(band["lower"]) <= adev) and np.all(adev <= np.asarray(band["upper"]))
    assert band["n_taus"] == adev.size and band["true_adev_inside"] >= adev.size / 2
    # The IEEE terms: the white N and the random walk K of the truth inside their 95 %
    # bootstrap intervals; every term either supported with value ∈ [lower, upper] or an
    # upper bound only.
    ieee = allan["ieee_terms"]
    for name, truth in (("N", ieee["white_N_true"]), ("K", ieee["rate_random_walk_K_true"])):
        term = ieee["terms"][name]
        assert term["supported"] and term["lower"] <= truth <= term["upper"], (name, term)
    for term in ieee["terms"].values():
        if term["supported"]:
            assert term["lower"] <= term["value"] <= term["upper"]
        else:
            assert term["value"] is None and term["upper"] >= 0
    assert len(ieee["model_adev_rad_per_s"]) == adev.size


@pytest.mark.slow
def test_study_filter_identification_loop(quick_report):
    """Seed 001's loop: the filter with the wrong model, its smoothed estimates identified
    and the filter retuned, per iteration, beside the oracle; the oracle filter is
    consistent (its NEES near the state dimension 4), the wrong model is not."""
    from helpers import study_result

    _, saved = study_result(quick_report, "noise_identification")
    loops = saved["filter_identification_loop"]
    assert set(loops) == {"rule_15", "ml"}
    for loop in loops.values():
        rows = loop["iterations"]
        assert [row["iteration"] for row in rows] == list(range(len(rows)))
        assert len(rows) >= 2
        assert rows[0]["mean_nees"] > 10 * loop["oracle"]["mean_nees"]  # the wrong model
        for row in rows:
            assert set(row["model"]) == {
                "accel_sigma",
                "accel_correlation_time",
                "gyro_sigma",
                "gyro_correlation_time",
            }
            assert all(v > 0 for v in row["model"].values())
        # The model changes between iterations: the loop retunes the filter.
        assert rows[1]["model"] != rows[0]["model"]
    assert 2.0 < loops["rule_15"]["oracle"]["mean_nees"] < 8.0
    summary = [row["quantity"] for row in saved["summary"]]
    assert any("the §4 paper's loop" in q and "oracle" in q for q in summary)
    # The bias from the spectra: one predicted step per iteration; at the true models the
    # smoothed means alone give a τ_ω well above the truth, and with the smoother's
    # posterior autocovariance added what rule (15) gives on the true errors (the law of
    # total covariance, to the frequency grid's round-off).
    spectral = loops["rule_15"]["spectral_map"]
    assert len(spectral["steps"]) == len(loops["rule_15"]["iterations"]) - 1
    at_truth = spectral["at_the_true_models"]
    assert at_truth["smoothed_means"]["gyro"]["tau_s"] > 2 * 3600.0
    for sensor in ("accelerometer", "gyro"):
        ratio = (
            at_truth["with_posterior"][sensor]["tau_s"]
            / at_truth["rule_15_on_the_true_errors"][sensor]["tau_s"]
        )
        assert abs(ratio - 1) < 1e-6, (sensor, ratio)
    row = next(r for r in saved["summary"] if "map from the spectra" in r["quantity"])
    assert row["status"] == ("explained" if spectral["agree"] else "differs")
    assert len(spectral["over_logs"]["gyro_tau_s_median"]) == len(spectral["steps"])


@pytest.mark.slow
def test_study_in_flight(quick_report):
    """The in-flight part (studies/noise_in_flight.py), quick: per-hour statistics for every
    variant; the oracle's innovations are white with the variance it predicts (NIS ≈ 1); the
    wrong starting model leaves ±3σ far more often than the oracle; the simplified Sage–Husa
    filter matches the innovations yet its NEES is far above χ²(2)'s 2 (its covariance
    collapses); every in-flight row of the summary has a status."""
    from helpers import study_result

    _, saved = study_result(quick_report, "noise_identification")
    fl = saved["in_flight"]
    assert set(fl["configurations"]) >= {"too_large", "too_small", "gauss_markov_truth"}
    for config in fl["configurations"].values():
        for variant in config["variants"].values():
            assert len(variant["outside_3sigma_per_hour"]) == fl["hours"]
            assert len(variant["nis_per_hour"]) == fl["hours"]
        assert 0.8 < config["variants"]["oracle"]["nis_settled"] < 1.2
        assert config["log_likelihood_second_half"]["observations"] == fl["hours"] * 1800
        # the structure over time: a share of logs per block and sensor
        shares = config["structure"]["exp_cosine_share_by_block"]
        blocks = len(config["structure"]["retuned_share"])
        assert all(len(shares[s]) == blocks for s in ("accelerometer", "gyro"))
        assert all(0.0 <= v <= 1.0 for s in shares.values() for v in s)
    large = fl["configurations"]["too_large"]["variants"]
    assert large["wrong_model"]["outside_3sigma_settled"] > 3 * large["oracle"][
        "outside_3sigma_settled"
    ] + 0.01
    assert 0.8 < large["sage_husa"]["nis_settled"] < 1.2
    assert large["sage_husa"]["nees_settled"] > 10
    rows = [row for row in saved["summary"] if row["quantity"].startswith("in flight")]
    assert len(rows) >= 6
    assert all(row.get("status") in {"reproduced", "explained", "differs"} for row in rows)
    false_row = next(row for row in rows if "Gauss–Markov gyro drift" in row["quantity"])
    assert "held as exponential-cosine at one time" in false_row["note"]
    # What the log can tell at best, for every exponential-cosine configuration, in the
    # structure row's explanation.
    for name, config in fl["configurations"].items():
        info = config["information_true_over_best_gauss_markov"]
        if config["gyro_truth"] == "gauss_markov":
            assert info is None, name
        else:
            assert np.isfinite(info["median"]) and info["loop_price"] > 0, name
            perfect = info["drift_itself_noise_free"]
            assert perfect["hours"] == min(24, fl["hours"]) and perfect["realisations"] >= 64
    # The study's drift seen through a 0.1 m/s velocity log holds far less of its structure
    # than the drift itself would, noise-free (the bound the loop cannot beat).
    weak = fl["configurations"]["too_large"]["information_true_over_best_gauss_markov"]
    assert weak["drift_itself_noise_free"]["median"] > weak["median"]
    switch_row = next(
        row for row in rows if "ends modelling as exponential-cosine (the truth)" in row["quantity"]
    )
    assert "what the log can tell at best" in switch_row["explanation"]


def test_in_flight_information_bound_tells_a_structured_log_from_a_weak_one():
    """`noise_in_flight._information`: the true exponential-cosine models against the best
    Gauss–Markov drift of its τ grid, over the second half of each log. On logs that carry
    the structure (the strongly oscillating drift against a 0.01 m/s reference) it is far
    above the loop's price; on the study's weak configuration (σ 5e-8 rad/s, βτ_c 2.5,
    0.1 m/s) it is below it on every log — which is why no test switches there."""
    import jax
    import jax.numpy as jnp

    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "studies"))
    import noise_in_flight as nf

    from accel_jax.kalman import OnlineIdentification, ins_initial_covariance

    hours = 24
    fixed = OnlineIdentification(adaptation="none")
    gains = {}
    for kind, velocity_noise in (("strong_exp_cosine", 0.01), ("exp_cosine", 0.1)):
        truth = nf._truth(kind, velocity_noise)
        keys = jax.random.split(jax.random.key(11), 2)
        model, p0 = truth.discretise(1.0), ins_initial_covariance(truth)
        _, z = nf._simulate(model, p0, keys, hours * 3600)
        true = nf._true_models(kind)
        oracle_ll = nf._second_half_log_likelihood(nf._run_logs(z, *true, velocity_noise, fixed))
        info = nf._information(
            z, true, velocity_noise, fixed, oracle_ll, hours * 3600, OnlineIdentification()
        )
        gains[kind] = (np.asarray(info["p10_p90"]), info["loop_price"])
        assert jnp.isfinite(info["median"])
    strong, price = gains["strong_exp_cosine"]
    assert strong[0] > 3 * price, gains
    weak, price = gains["exp_cosine"]
    assert weak[1] < price, gains


def test_perfect_observation_bound_against_the_dense_gaussian_likelihood():
    """`noise_in_flight.perfect_observation_bound`'s two likelihoods against SciPy's
    multivariate normal with the Toeplitz covariance of each model (an independent route:
    no filter); the best AR(1) of the grid within 1e-3 nats of a bounded scalar search; and
    the bound itself: about zero for a drift with no oscillation (β = 0: the true model is
    one of the Gauss–Markov ones, which then fit two parameters by maximum likelihood: −1
    expected), and for βτ_c = 2.5 over 24 h at 30 s of the size the Whittle approximation
    gives — n times the Kullback–Leibler rate between the sampled process's spectrum and
    the nearest AR(1) spectrum (16.7 nats), less the one nat of the fitted parameters —
    within 3 standard errors of 256 realisations and one nat."""
    import sys
    from pathlib import Path

    from scipy import optimize, stats
    from scipy.linalg import toeplitz

    sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "studies"))
    import noise_in_flight as nf

    rng = np.random.default_rng(3)
    a, b, dt, n = 1 / 600, 2.5 / 600, 30.0, 120
    lags = dt * np.arange(n)
    cov_ec = toeplitz(np.exp(-a * lags) * np.cos(b * lags))
    x = rng.multivariate_normal(np.zeros(n), cov_ec, size=3)
    dense = stats.multivariate_normal(np.zeros(n), cov_ec).logpdf(x)
    np.testing.assert_allclose(nf.exp_cosine_log_likelihood(x, a, b, dt), dense, rtol=1e-10)

    def ar1(phi, series):
        s2 = np.mean(
            np.r_[series[0] ** 2 * (1 - phi**2), (series[1:] - phi * series[:-1]) ** 2]
        )
        cov = toeplitz(s2 / (1 - phi**2) * phi ** np.arange(n))
        return stats.multivariate_normal(np.zeros(n), cov).logpdf(series)

    best = [
        -optimize.minimize_scalar(
            lambda p, s=s: -ar1(p, s), bounds=(-0.999, 0.999), method="bounded",
            options={"xatol": 1e-9},
        ).fun
        for s in x
    ]
    np.testing.assert_allclose(nf.gauss_markov_max_log_likelihood(x), best, atol=1e-3)

    flat = nf.perfect_observation_bound(1 / 3600, 0.0, dt, 24, 256, 1)
    assert -1.5 < np.mean(flat) <= 0.0
    a, b = 1 / 3600, 2.5 / 3600
    lam = np.linspace(-np.pi, np.pi, 40001)
    spectrum = sum(
        0.5 * (1 - abs(rho) ** 2) / abs(1 - rho * np.exp(-1j * lam)) ** 2
        for rho in (np.exp(-a * dt + 1j * b * dt), np.exp(-a * dt - 1j * b * dt))
    )

    def kl(p):
        nearest = np.exp(p[1]) / abs(1 - np.tanh(p[0]) * np.exp(-1j * lam)) ** 2
        ratio = spectrum / nearest
        return np.trapezoid(ratio - 1 - np.log(ratio), lam) / (4 * np.pi)

    rate = min(
        optimize.minimize(kl, [np.arctanh(phi), np.log(0.05)], method="Nelder-Mead").fun
        for phi in (0.9, 0.99)
    )
    expected = rate * 24 * 3600 / dt - 1.0
    assert 15 < expected + 1 < 18.5  # 16.7 nats
    evidence = nf.perfect_observation_bound(a, b, dt, 24, 256, 2)
    standard_error = np.std(evidence) / np.sqrt(evidence.size)
    mean = np.mean(evidence)
    assert abs(mean - expected) < 3 * standard_error + 1.0, (mean, expected)
