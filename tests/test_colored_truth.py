"""The coloured-noise truth simulator (studies/colored_truth.py), checked against other
computations: step_truth's simulator (every noise off; and the same white-noise stream),
the exact AR(1) statistics of the output Gauss–Markov noise, the moment noise's stationary
variance and autocovariance from the augmented linear system, that variance again from the
closed-loop transfer function and the moment's PSD integrated numerically (an independent
derivation), the stationary start, the draws and reproducibility. NumPy/SciPy only.

Monte-Carlo tolerances are `Z` standard errors (the standard error exact for the AR(1)
checks, Bartlett's formula for its autocorrelation; the empirical one over independent
records for the moment noise)."""

import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.linalg import expm

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "studies"))
import colored_truth  # noqa: E402
import step_truth  # noqa: E402

Z = 4.0
"""Monte-Carlo tolerance, in standard errors."""


def _quiet(rec):
    """The record with no noise and no ADC (offset and sign kept)."""
    return dataclasses.replace(rec, noise=0.0, adc_step=0.0, gm=(0.0, 1.0))


def _handmade():
    """A device with both lags and a record with changes between samples (two in one
    sample interval), one exactly on a sample, one before t0 inside the start's transient,
    an output offset and a negative output sign, t0 ≠ 0, an inverted test winding."""
    device = step_truth.Device(T_dm=2e-5, T_f=3e-5, test_gain=-0.97)
    rate, n, t0 = 1e6, 2000, 2.5e-5
    on_sample = t0 + np.arange(n)[400] / rate
    changes = np.array([-4e-5, 3.0037e-4, on_sample, 8.0002e-4, 8.0007e-4, 1.4409e-3])
    record = step_truth.Record(
        levels=np.array([0.3, 1.7, -1.2, 0.0, 2.0, -0.6, 1.1]),
        change_times=changes,
        rate=rate,
        n=n,
        t0=t0,
        moment=1.1e-6,
        output_offset=0.031,
        output_sign=-1.0,
        start=1e-4,
        start_level=-0.8,
    )
    return device, record


# --------------------------------------------------------------------------------------
# 1. No coloured noise: step_truth's record
# --------------------------------------------------------------------------------------


def _cases():
    cases = [("handmade", *_handmade())]
    for seed in (0, 1, 2):
        truth = colored_truth.draw_truth(np.random.default_rng(seed), "moment_gm")
        device, record = colored_truth.truth_device(truth), colored_truth.truth_record(truth)
        cases.append((f"drawn {seed}", device, record))
        lagged = dataclasses.replace(device, T_dm=2e-5, T_f=3e-5)
        cases.append((f"drawn {seed} lags", lagged, record))
    return cases


def test_noise_off_agrees_with_step_truth():
    """Both coloured noises off, white noise off, no ADC: the record equals
    step_truth.simulate's (DOP853 at rtol 1e-10) to 1e-9 V, on drawn worlds (start at rest
    or in a transient; with and without T_dm = 20 µs, T_f = 30 µs) and the handmade one."""
    worst = 0.0
    for name, device, record in _cases():
        record = _quiet(record)
        t, u, mine = colored_truth.simulate(
            device, record, rng=np.random.default_rng(0), moment_gm=(0.0, 1e-4)
        )
        t2, u2, theirs = step_truth.simulate(device, record, rng=np.random.default_rng(0))
        np.testing.assert_array_equal(t, t2)
        np.testing.assert_array_equal(u, u2)
        diff = float(np.max(np.abs(mine - theirs)))
        worst = max(worst, diff)
        assert diff < 1e-9, name
    print(f"max |colored_truth − step_truth| = {worst:.2e} V")


def test_white_noise_and_output_gm_use_step_truths_stream():
    """σ_M = 0: the rng is used as step_truth's (white noise, then the output Gauss–Markov
    noise), so the same seed gives step_truth's record, ADC included; `output_gm` is
    step_truth's `Record.gm`. (Equal but where the clean outputs' ≤ 1e-9 V difference tips
    an ADC rounding.)"""
    device, record = _handmade()
    record = dataclasses.replace(record, noise=7e-4, adc_step=20.0 / 2**16)
    _, _, mine = colored_truth.simulate(
        device, record, rng=np.random.default_rng(5), output_gm=(2e-3, 3e-5)
    )
    theirs_record = dataclasses.replace(record, gm=(2e-3, 3e-5))
    _, _, theirs = step_truth.simulate(device, theirs_record, rng=np.random.default_rng(5))
    assert np.max(np.abs(mine - theirs)) <= record.adc_step * (1 + 1e-9)
    assert np.mean(mine != theirs) < 1e-3


def test_make_none_is_step_truths_make():
    """make() of a "none" world: step_truth.make's columns and noise stream."""
    truth = colored_truth.draw_truth(np.random.default_rng(4), "none")
    t, u, y, noise = colored_truth.make(truth, np.random.default_rng(11))
    t2, u2, y2, noise2 = step_truth.make(truth, np.random.default_rng(11))
    np.testing.assert_array_equal(t, t2)
    np.testing.assert_array_equal(u, u2)
    assert np.max(np.abs(y - y2)) <= truth["adc_step_V"] * (1 + 1e-9)
    assert np.mean(y != y2) < 1e-3
    assert np.max(np.abs((y - noise) - (y2 - noise2))) < 1e-9


def test_noise_component_is_record_minus_noise_free_record():
    """make()'s noise component is u_out minus the same record simulated separately with
    every noise off and no ADC (the noise-free state propagated alongside is that record)."""
    truth = colored_truth.draw_truth(np.random.default_rng(6), "moment_gm")
    _, _, y, noise = colored_truth.make(truth, np.random.default_rng(1))
    quiet = _quiet(colored_truth.truth_record(truth))
    _, _, clean = colored_truth.simulate(
        colored_truth.truth_device(truth), quiet, rng=np.random.default_rng(2)
    )
    assert np.max(np.abs((y - noise) - clean)) < 1e-12
    assert np.std(noise) > truth["noise_V"]  # the moment noise is in it


# --------------------------------------------------------------------------------------
# 2. The output Gauss–Markov noise
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("tau_samples", [3.0, 40.0])
def test_output_gm_variance_and_autocorrelation(tau_samples):
    """A 200 000-sample record with only the output Gauss–Markov noise (σ = 3 mV): the
    noise component's mean square is σ² within Z standard errors (exact for a Gaussian
    AR(1): σ² √(2(1 + φ²)/((1 − φ²) n))) and its lag-1..5 autocorrelations are φ^k =
    exp(−k dt/τ) within Z of Bartlett's standard errors."""
    rate, n, sigma = 1e6, 200_000, 3e-3
    tau = tau_samples / rate
    device = step_truth.Device()
    record = step_truth.Record(
        levels=np.array([0.0, 1.5, -1.5]),
        change_times=np.array([0.0500003, 0.1300007]),
        rate=rate,
        n=n,
        output_offset=0.01,
        output_sign=-1.0,
    )
    result = colored_truth.run(
        device, record, rng=np.random.default_rng(int(tau_samples)), output_gm=(sigma, tau)
    )
    x = result["noise"]
    phi = np.exp(-1 / tau_samples)
    mean_square = float(np.mean(x**2))
    se = sigma**2 * np.sqrt(2 * (1 + phi**2) / ((1 - phi**2) * n))
    ratio, ratio_se = mean_square / sigma**2, se / sigma**2
    print(f"τ = {tau_samples} samples: var/σ² = {ratio:.4f} ± {ratio_se:.4f}")
    assert abs(mean_square - sigma**2) < Z * se
    for k in range(1, 6):
        r = float(np.sum(x[:-k] * x[k:]) / np.sum(x**2))
        rho = phi**k
        # Bartlett: n var(r_k) = (1 + φ²)(1 − φ^2k)/(1 − φ²) − 2k φ^2k for an AR(1).
        bartlett = np.sqrt(((1 + phi**2) * (1 - rho**2) / (1 - phi**2) - 2 * k * rho**2) / n)
        print(f"  lag {k}: r = {r:.4f}, exp(−k dt/τ) = {rho:.4f} ± {bartlett:.4f}")
        assert abs(r - rho) < Z * bartlett


# --------------------------------------------------------------------------------------
# 3. The moment noise inside the loop
# --------------------------------------------------------------------------------------


def _closed_loop_variance(device, tau_m, sigma_m):
    """Var of U_out's moment-noise part from the closed loop's transfer function, derived
    from the loop equations here (not from the simulator's matrices):
    U_out/M_n (s) = k_dp k_y l / (1 + T_f s) / (J s² + μ s + c + k_dm k_dp k_y l / (1 + T_dm s)),
    S_M(ω) = 2 σ_M² τ_M / (1 + ω² τ_M²) (two-sided; ∫ S_M dω / 2π = σ_M²),
    Var = (1/π) ∫₀^∞ |U_out/M_n (jω)|² S_M(ω) dω by scipy.integrate.quad, split at the
    loop's natural frequency and the corners."""
    d = device
    gain = d.k_dp * d.k_y * d.l

    def integrand(w):
        s = 1j * w
        loop = d.J * s**2 + d.mu * s + d.c + d.k_dm * gain / (1 + d.T_dm * s)
        h = gain / (1 + d.T_f * s) / loop
        return abs(h) ** 2 * 2 * sigma_m**2 * tau_m / (1 + (w * tau_m) ** 2) / np.pi

    natural = np.sqrt((d.c + d.k_dm * gain) / d.J)
    corners = [natural, 1 / tau_m] + [1 / x for x in (d.T_dm, d.T_f) if x > 0]
    points = sorted({c * f for c in corners for f in (0.1, 0.5, 1.0, 2.0, 10.0)})
    edges = [0.0, *points]
    total = 0.0
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        total += quad(integrand, a, b, epsabs=0, epsrel=1e-12, limit=500)[0]
    # The tail beyond 10 × the highest corner (falling as ω⁻⁶ or faster), to 1e-12 of it.
    total += quad(integrand, edges[-1], np.inf, epsabs=1e-12 * total, epsrel=0, limit=500)[0]
    return total


@pytest.mark.parametrize(
    "T_dm,T_f,tau_m",
    [(0, 0, 3e-6), (0, 0, 1e-4), (2e-5, 3e-5, 1e-5), (3e-5, 0, 6e-4), (0, 4e-5, 2e-4)],
)
def test_lyapunov_variance_equals_psd_integral(T_dm, T_f, tau_m):
    """The Lyapunov solution's output variance H P Hᵀ equals the closed-loop PSD's
    integral to 1e-6 (relative); `moment_sigma_for_output_std` inverts it."""
    device = step_truth.Device(T_dm=T_dm, T_f=T_f, test_gain=-1.02)
    sigma_m = 1e-7
    model = colored_truth.moment_noise_model(device, tau_m, sigma_m)
    psd = _closed_loop_variance(device, tau_m, sigma_m)
    rel = abs(model["output_var"] / psd - 1)
    print(f"T_dm {T_dm}, T_f {T_f}, τ_M {tau_m}: std {np.sqrt(psd):.4e} V, rel. diff {rel:.1e}")
    assert rel < 1e-6
    std = colored_truth.moment_sigma_for_output_std(device, tau_m, np.sqrt(psd))
    assert abs(std / sigma_m - 1) < 1e-6
    # P is the joint stationary covariance: A P + P Aᵀ + G Gᵀ = 0, symmetric, PSD;
    # checked in the states' own units (D = √diag P: P/D D the correlation matrix).
    a, g, p = model["A"], model["G"], model["P"]
    d = np.sqrt(np.diag(p))
    a_n, p_n, g_n = a * d[None, :] / d[:, None], p / np.outer(d, d), g / d
    residual = a_n @ p_n + p_n @ a_n.T + np.outer(g_n, g_n)
    assert np.max(np.abs(residual)) < 1e-12 * np.max(np.abs(a_n))
    np.testing.assert_array_equal(p, p.T)
    assert np.min(np.linalg.eigvalsh(p_n)) > -1e-12


@pytest.mark.parametrize("T_dm,T_f,tau_m", [(0, 0, 3e-6), (2e-5, 3e-5, 1e-5), (1e-5, 1e-5, 6e-4)])
def test_van_loan_process_noise_is_stationary(T_dm, T_f, tau_m):
    """Van Loan's Q(h) (with its halving and doubling) equals P − Φ(h) P Φ(h)ᵀ, the
    stationarity identity, over a sample period, a fraction of one and ten of them; the
    eigen-factors reproduce Q and P."""
    model = colored_truth._Model(step_truth.Device(T_dm=T_dm, T_f=T_f), tau_m)
    p = model.P_unit
    for h in (1e-6, 0.3e-6, 2e-5):
        q = model.process_cov(h)
        phi = model.transition(h)
        np.testing.assert_allclose(phi, expm(model.A * h), rtol=0, atol=1e-13)
        stationary = p - phi @ p @ phi.T
        assert np.max(np.abs(q - stationary)) < 1e-10 * np.max(np.abs(q)), h
        factor = model.step(h)[1]
        assert np.max(np.abs(factor @ factor.T - q)) < 1e-12 * np.max(np.abs(q))
    # The stationary start's factor (eigh, clipped) reproduces P and its output variance.
    factor = colored_truth._factor(p)
    assert np.max(np.abs(factor @ factor.T - p)) < 1e-12 * np.max(np.abs(p))
    h_row = model.H
    assert abs(h_row @ factor @ factor.T @ h_row / (h_row @ p @ h_row) - 1) < 1e-12


def _drawn_moment_truth():
    """The first drawn "moment_gm" world (seeds 0, 1, ...) at 0.5 MHz with τ_M of 10–200 µs."""
    for seed in range(200):
        truth = colored_truth.draw_truth(np.random.default_rng(seed), "moment_gm")
        if truth["rate"] == 5e5 and 1e-5 <= truth["tau_s"] <= 2e-4:
            return seed, truth
    raise RuntimeError("no such draw")


def _moment_cases():
    seed, truth = _drawn_moment_truth()
    drawn = (
        f"drawn seed {seed}",
        colored_truth.truth_device(truth),
        colored_truth.truth_record(truth),
        truth["tau_s"],
        truth["sigma"],
        truth["ratio"] * truth["noise_V"],
    )
    device = step_truth.Device(T_dm=2e-5, T_f=1e-5, test_gain=-1.0)
    record = dataclasses.replace(drawn[2], n=6000)
    target = 4e-3
    sigma_m = colored_truth.moment_sigma_for_output_std(device, 6e-6, target)
    lagged = ("lags, τ_M = 3 samples", device, record, 6e-6, sigma_m, target)
    return [drawn, lagged]


@pytest.mark.parametrize("case", range(2))
def test_moment_noise_output_std_and_autocovariance(case):
    """Over 150 independent records of 6000 samples: (a) the moment-noise part's mean
    square is (ratio × noise_V)², the output std the draw asked for, and (b) its
    autocovariance at lags 0–250 samples is C(k) = H Φ^k P Hᵀ (Φ = expm(A dt), P the
    Lyapunov solution), each within Z empirical standard errors over the records."""
    name, device, record, tau_m, sigma_m, target = _moment_cases()[case]
    model = colored_truth.moment_noise_model(device, tau_m, sigma_m)
    assert abs(model["output_var"] / target**2 - 1) < 1e-9
    lags = [0, 1, 5, 25, 100, 250]
    count = 150
    estimates = np.empty((count, len(lags)))
    for r in range(count):
        x = colored_truth.run(
            device, record, rng=np.random.default_rng(1000 + r), moment_gm=(sigma_m, tau_m)
        )["moment_part"]
        estimates[r] = [np.mean(x[: x.size - k] * x[k:]) for k in lags]
    phi = expm(model["A"] / record.rate)
    h, p = model["H"], model["P"]
    mean = estimates.mean(axis=0)
    se = estimates.std(axis=0, ddof=1) / np.sqrt(count)
    std_ratio = np.sqrt(mean[0]) / target
    print(f"{name}: output std / (ratio noise_V) = {std_ratio:.4f} (± {se[0] / mean[0] / 2:.4f})")
    for i, k in enumerate(lags):
        theory = float(h @ np.linalg.matrix_power(phi, k) @ p @ h)
        print(f"  C({k}) = {mean[i]:.4e} ± {se[i]:.1e}, theory {theory:.4e}")
        assert abs(mean[i] - theory) < Z * se[i], k


def test_stationary_start():
    """The first sample's moment-noise part over 4000 independent short records has the
    stationary variance (no start-up transient), and so do samples 100 and 200 later (where
    a start with M_n drawn apart from the loop's states, the loop's marginal right but not
    their correlation, would be 21 % and 41 % low; a loop starting at rest, ≥ 73 % low:
    the test tells them apart)."""
    device = step_truth.Device(T_dm=1e-5, T_f=1e-5)
    tau_m, sigma_m = 6e-4, 1e-7
    record = step_truth.Record(
        levels=np.array([0.5, -1.0]), change_times=np.array([101.3e-6]), rate=5e5, n=201
    )
    model = colored_truth.moment_noise_model(device, tau_m, sigma_m)
    h, p = model["H"], model["P"]
    var = float(h @ p @ h)
    count = 4000
    samples = [0, 100, 200]
    x = np.empty((count, len(samples)))
    for r in range(count):
        part = colored_truth.run(
            device, record, rng=np.random.default_rng(r), moment_gm=(sigma_m, tau_m)
        )["moment_part"]
        x[r] = part[samples]
    phi = expm(model["A"] / record.rate)
    apart = p.copy()
    apart[-1, :-1] = apart[:-1, -1] = 0.0
    for i, k in enumerate(samples):
        mean_square = float(np.mean(x[:, i] ** 2))
        se = float(np.std(x[:, i] ** 2, ddof=1) / np.sqrt(count))
        phi_k = np.linalg.matrix_power(phi, k)
        wrong = var + float(h @ phi_k @ (apart - p) @ phi_k.T @ h)
        print(
            f"sample {k}: var / stationary = {mean_square / var:.4f} ± {se / var:.4f}"
            f" (M_n drawn apart: {wrong / var:.3f})"
        )
        assert abs(mean_square - var) < Z * se
        if k == samples[-1]:
            assert abs(wrong - var) > 2 * Z * se  # the check has the power to see it
    # E[y_0 y_200] = H Φ^200 P Hᵀ
    cov = float(np.mean(x[:, 0] * x[:, -1]))
    se = float(np.std(x[:, 0] * x[:, -1], ddof=1) / np.sqrt(count))
    theory = float(h @ np.linalg.matrix_power(phi, samples[-1]) @ p @ h)
    print(f"cov(y0, y200) / var = {cov / var:.4f} ± {se / var:.4f}, theory {theory / var:.4f}")
    assert abs(cov - theory) < Z * se


# --------------------------------------------------------------------------------------
# 4. The draws
# --------------------------------------------------------------------------------------


def test_reproducible():
    """The same seeds give the same world and the same record; another seed another record."""
    for effect in colored_truth.CLASSES:
        truth = colored_truth.draw_truth(np.random.default_rng(3), effect)
        assert truth == colored_truth.draw_truth(np.random.default_rng(3), effect)
        json.dumps(truth)
        first = colored_truth.make(truth, np.random.default_rng(9))
        second = colored_truth.make(truth, np.random.default_rng(9))
        for a, b in zip(first, second, strict=True):
            np.testing.assert_array_equal(a, b)
        other = colored_truth.make(truth, np.random.default_rng(10))
        assert not np.array_equal(first[2], other[2])


def test_draw_ranges_and_worlds():
    """50 draws per class: step_truth's "none" world draw for draw, no lags, the ratio in
    [1, 20], τ in [3 samples, DURATION/20], σ consistent with the ratio (σ_gm = ratio ×
    noise_V; σ_M giving that std at the output, through the Lyapunov solution)."""
    for effect in colored_truth.CLASSES:
        ratios, taus = [], []
        for seed in range(50):
            truth = colored_truth.draw_truth(np.random.default_rng(seed), effect)
            world = step_truth.draw_truth(np.random.default_rng(seed), "none")
            for key, value in world.items():
                if key != "effect":
                    assert truth[key] == value, key
            assert truth["effect"] == effect
            assert truth["T_dm_s"] == truth["T_f_s"] == 0.0
            if effect == "none":
                assert truth["ratio"] is None and truth["tau_s"] is None
                assert truth["sigma"] == 0.0
                continue
            low, high = 3 / truth["rate"], step_truth.DURATION / 20
            assert 1.0 <= truth["ratio"] <= 20.0
            assert low <= truth["tau_s"] <= high
            ratios.append(truth["ratio"])
            taus.append(truth["tau_s"] / low)
            std = truth["ratio"] * truth["noise_V"]
            assert abs(truth["output_std_V"] / std - 1) < 1e-12
            if effect == "output_gm":
                assert truth["sigma"] == pytest.approx(std, rel=1e-12)
            else:
                device = colored_truth.truth_device(truth)
                var = colored_truth.moment_noise_model(device, truth["tau_s"], truth["sigma"])[
                    "output_var"
                ]
                assert abs(var / std**2 - 1) < 1e-9
        if effect != "none":
            print(
                f"{effect}: ratio {min(ratios):.2f}–{max(ratios):.2f}, "
                f"τ {min(taus):.2f}–{max(taus):.0f} × 3 samples"
            )
            assert min(ratios) < 2 and max(ratios) > 10  # spread over the range
