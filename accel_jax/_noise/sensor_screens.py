"""Model-free screens of a static record (or of a noise model's residual).

Each says whether a record shows something no noise model of the library makes, with the
statistic that says so:

- `detect_quantization`: the values lie on an ADC grid (the step, its share of the
  white noise);
- `detect_saturation`: a pile of samples at the record's extreme, a range limit clipping
  it;
- `_bursts`: impulsive events (robust z above `BURST_Z`);
- `_non_gaussian` / `detect_non_gaussian`: skewness and excess kurtosis far from a
  Gaussian's, with standard errors from the residual's own autocorrelation (a random
  telegraph noise's two levels, heavy tails);
- `_spectral_change` / `detect_spectral_change`: the spectrum changes between the record's
  halves (Hann-tapered periodograms in bands, Beta(k, k) shares, Bonferroni);
- `level_shift_screen` and the Haar scan it shares with the selection's level-shift test
  (`_haar_scan`, `_shift_critical_z`);
- `_drift`: a linear drift in blocks' means.

Float64, NumPy; no fitting.
"""

from __future__ import annotations

import math
import statistics

import numpy as np


QUANTIZATION_SHARE = 0.01
"""The grid's noise q²/12 must be at least this share of the record's short-term variance
(half the variance of its first difference) to be named."""


def detect_quantization(x: np.ndarray) -> dict | None:
    """The ADC grid the values lie on: the smallest spacing q₀ of the distinct values,
    accepted when every distinct value sits within q₀/10 of a multiple of it from the
    lowest, and refined by least squares of the values on their grid indices. None when the
    values are continuous (more than half of them distinct) or fit no grid."""
    x = np.asarray(x, np.float64)
    u = np.unique(x)
    if u.size < 3 or u.size > x.size // 2:
        return None
    scale = max(float(np.max(np.abs(u))), 1e-300)
    gaps = np.diff(u)
    gaps = gaps[gaps > 1e-12 * scale]
    if gaps.size == 0:
        return None
    q0 = float(np.min(gaps))
    k = np.round((u - u[0]) / q0)
    if np.max(np.abs(u - u[0] - k * q0)) > 0.1 * q0:
        return None
    design = np.stack([np.ones_like(k), k], axis=1)
    (offset, q), *_ = np.linalg.lstsq(design, u, rcond=None)
    misfit = float(np.max(np.abs(design @ np.array([offset, q]) - u)))
    return {"step": float(q), "offset": float(offset), "levels": int(u.size), "misfit": misfit}


SATURATION_MIN = 5
"""Samples at an extreme of the record that, piled there, make it a rail."""


def detect_saturation(x: np.ndarray, grid: dict | None = None) -> list:
    """Rails: an extreme of the record (its largest or its smallest value) holding a pile of
    samples that no unimodal noise puts there: the range limit of an ADC or of the sensor's
    electronics, outside the library (clipping flattens the record's distribution, cuts its
    variance and biases every fitted parameter). Continuous values (`grid` None): the
    extreme value repeated at least `SATURATION_MIN` times (continuous noise repeats no
    value). On an output grid (`detect_quantization`, judged from 4 levels on): the extreme
    level holds at least `SATURATION_MIN` samples and more than twice the level next inside
    it — a unimodal noise's tail falls outward, a rail gathers the whole tail beyond it. (On
    a coarse grid a rail close to the mean is not seen: its pile is then no larger than a
    level's share.) Returns one entry per side found: {"side": "high" | "low", "level",
    "count", "fraction", "inner_count" (None for continuous values)}."""
    x = np.asarray(x, np.float64)
    if x.ndim != 1 or x.size == 0 or not np.all(np.isfinite(x)):
        raise ValueError(
            "detect_saturation: the record must be a non-empty 1-D array of finite values"
        )
    found = []
    for side, sign in (("high", 1.0), ("low", -1.0)):
        y = sign * x
        top = float(np.max(y))
        if grid is None:
            count = int(np.sum(y == top))
            inner = None
        else:
            q = grid["step"]
            if grid["levels"] < 4 or not q > 0:
                continue
            count = int(np.sum(y > top - q / 2))
            inner = int(np.sum((y > top - 1.5 * q) & (y <= top - q / 2)))
        if count >= SATURATION_MIN and count > 2 * (inner or 0):
            found.append(
                {
                    "side": side,
                    "level": sign * top,
                    "count": count,
                    "fraction": count / x.size,
                    "inner_count": inner,
                }
            )
    return found


BURST_Z = 8.0
"""A first difference this many robust standard deviations from the median is an impulsive
event (a shock, a glitch): no Gaussian effect of the library makes one (probability
~1e-15 per sample)."""


def _bursts(r: np.ndarray, dt: float) -> list:
    """Impulsive events: runs of first differences beyond `BURST_Z` robust standard
    deviations (MAD), merged when closer than 10 samples; start, end [s] and the peak
    departure from the median level."""
    d = np.diff(r)
    centre = np.median(d)
    spread = 1.4826 * np.median(np.abs(d - centre))
    if not spread > 0:
        return []
    hits = np.flatnonzero(np.abs(d - centre) > BURST_Z * spread)
    if hits.size == 0:
        return []
    groups = np.split(hits, np.flatnonzero(np.diff(hits) > 10) + 1)
    level = np.median(r)
    out = []
    for g in groups[:20]:
        lo, hi = int(g[0]), int(g[-1]) + 1
        out.append(
            {
                "start_s": lo * dt,
                "end_s": hi * dt,
                "peak": float(np.max(np.abs(r[lo : hi + 1] - level))),
            }
        )
    return out


NON_GAUSSIAN_Z = 6.0


NON_GAUSSIAN_SIZE = 0.2
"""The residual is non-Gaussian when its skewness or excess kurtosis stands more than
`NON_GAUSSIAN_Z` standard errors from zero and is at least `NON_GAUSSIAN_SIZE` in size (the
second bar keeps a long record from being called non-Gaussian for a departure no user
would act on)."""


def _non_gaussian(r: np.ndarray, grid_share: float) -> dict:
    """The marginal distribution of the residual r against a Gaussian one: its skewness g₁
    and excess kurtosis g₂, with standard errors for a stationary Gaussian process of r's
    autocorrelation ρ (var g₁ ≈ 6 Σ_h ρ(h)³/n, var g₂ ≈ 24 Σ_h ρ(h)⁴/n, the sums over
    |h| < n/4 of the sample autocorrelation: a correlated record, a slow Gauss–Markov or a
    walk, has far fewer independent values than samples, and a walk's residual is never
    called non-Gaussian). A random telegraph (popcorn) noise, whose Lorentzian spectrum a
    Gauss–Markov process matches exactly, shows here as a negative excess kurtosis (two
    levels); heavy tails too rare for `_bursts` as a positive one.

    Not tested where the output grid's noise is `QUANTIZATION_SHARE` of the white variance
    or more: a coarse grid's values are a discrete distribution whose kurtosis departs from
    a Gaussian's by itself (g₂ up to 0.34 on the harness's quantised records)."""
    if grid_share >= QUANTIZATION_SHARE or r.size < 64:
        return {"tested": False, "significant": False}
    c = r - r.mean()
    n = c.size
    v = float(c @ c) / n
    if not v > 0:
        return {"tested": False, "significant": False}
    g1 = float(np.mean(c**3)) / v**1.5
    g2 = float(np.mean(c**4)) / v**2 - 3.0
    size = 1 << int(math.ceil(math.log2(2 * n)))
    spectrum = np.fft.rfft(c, size)
    rho = np.fft.irfft(spectrum * np.conj(spectrum), size)[: n // 4] / (n * v)
    s3 = 1.0 + 2.0 * float(np.sum(rho[1:] ** 3))
    s4 = 1.0 + 2.0 * float(np.sum(rho[1:] ** 4))
    z1 = g1 / math.sqrt(6.0 * max(abs(s3), 1.0) / n)
    z2 = g2 / math.sqrt(24.0 * s4 / n)
    significant = (abs(z1) > NON_GAUSSIAN_Z and abs(g1) >= NON_GAUSSIAN_SIZE) or (
        abs(z2) > NON_GAUSSIAN_Z and abs(g2) >= NON_GAUSSIAN_SIZE
    )
    return {
        "tested": True,
        "skewness": g1,
        "skewness_z": z1,
        "excess_kurtosis": g2,
        "excess_kurtosis_z": z2,
        "significant": bool(significant),
    }


def detect_non_gaussian(x: np.ndarray, grid: dict | None = None) -> dict:
    """Whether a record's values are far from Gaussian (`_non_gaussian` on x itself): a
    random telegraph noise's two levels, heavy tails. `grid` is the record's output grid
    (`detect_quantization`), whose noise share of the short-term variance (half the variance
    of the first difference) decides whether the test is run at all. Returns {"tested",
    "significant"} and, when tested, "skewness", "skewness_z", "excess_kurtosis",
    "excess_kurtosis_z". The selection tests its residual in the same way
    (`held_out.non_gaussian`); this tests the raw record, so a line, a transient or a step
    in it counts against Gaussianity."""
    x = np.asarray(x, np.float64)
    if x.ndim != 1 or x.size == 0 or not np.all(np.isfinite(x)):
        raise ValueError(
            "detect_non_gaussian: the record must be a non-empty 1-D array of finite values"
        )
    return _non_gaussian(x, grid_noise_share(x, grid))


def grid_noise_share(x: np.ndarray, grid: dict | None) -> float:
    """The output grid's noise q²/12 as a share of the record's short-term variance (half
    the variance of its first difference); 0 without a grid, inf on a constant record."""
    if grid is None:
        return 0.0
    white = float(np.var(np.diff(x))) / 2 if np.size(x) > 1 else 0.0
    return grid["step"] ** 2 / 12 / white if white > 0 else math.inf


SPECTRAL_CHANGE_ALPHA = 1e-4
"""Family-wise false-alarm rate of the spectral-change test (`_spectral_change`)."""


SPECTRAL_CHANGE_SIZE = math.log(2.0)
"""A band's power must change by at least this log ratio (a factor 2) between the record's
halves: a long record is not called non-stationary for a change no user would act on."""


SPECTRAL_CHANGE_SCALES = (16, 64, 256)
"""Band widths of the scan, in (every other) periodogram bins of a half."""


SPECTRAL_CHANGE_SMOOTH = 33
"""Bins of the moving average of the halves' pooled periodogram by which each bin is
standardised (the bands then hold bins of equal expected size)."""


def _spectral_change(r: np.ndarray, dt: float) -> dict:
    """Whether the residual's spectrum changes between the record's first and second half
    (a line or resonance that moves with temperature, a vibration that starts or stops):
    every model of the library is stationary. Each half of the first difference (the
    difference takes a walk's wander and a level shift's step out), Hann-tapered; every
    other periodogram bin (the taper correlates neighbours), each divided by the moving
    average of both halves' (`SPECTRAL_CHANGE_SMOOTH` bins); then bands of
    `SPECTRAL_CHANGE_SCALES` bins: under a stationary spectrum the first half's share of a
    band's sum is Beta(k, k). Significant when the smallest two-sided p, Bonferroni over
    all bands, is below `SPECTRAL_CHANGE_ALPHA` and that band's power changes by a factor
    of at least 2 (`SPECTRAL_CHANGE_SIZE`).

    Calibration (NumPy records, 10⁴ samples): family-wise p < 0.05 in 5.7 % of 300 white,
    7.7 % of walk, 4 % of slow and 4.7 % of fast Gauss–Markov, 7 % of flicker records; on
    the 624 sensor-noise harness truths (lines and transients out) the smallest p is 0.002.
    A line sweeping 1 → 3 Hz at half the white σ is found (p ≈ 3e-10), at a quarter not."""
    from scipy import stats

    d = np.diff(np.asarray(r, np.float64))
    h = d.size // 2
    if h < 4 * (2 * SPECTRAL_CHANGE_SCALES[0] + 4):
        return {"tested": False, "significant": False}
    window = np.hanning(h)
    halves = [d[:h], d[h : 2 * h]]
    if not all(np.ptp(v) > 0 for v in halves):
        # A half without noise (a bare step, a constant stretch): no spectrum to compare.
        return {"tested": False, "significant": False}
    grams = [
        (np.abs(np.fft.rfft(window * (v - v.mean()))) ** 2)[2:-2:2] for v in halves
    ]
    kernel = np.ones(SPECTRAL_CHANGE_SMOOTH)
    pooled = np.convolve((grams[0] + grams[1]) / 2, kernel, mode="same")
    level = pooled / np.convolve(np.ones_like(grams[0]), kernel, mode="same")
    if not np.all(level > 0):
        return {"tested": False, "significant": False}
    a, b = grams[0] / level, grams[1] / level
    bands = []
    for k in SPECTRAL_CHANGE_SCALES:
        m = a.size // k
        if m < 2:
            continue
        sa = a[: m * k].reshape(m, k).sum(axis=1)
        sb = b[: m * k].reshape(m, k).sum(axis=1)
        share = sa / (sa + sb)
        p = 2 * np.minimum(stats.beta.cdf(share, k, k), stats.beta.sf(share, k, k))
        bands.append((k, p, np.log(sb / sa)))
    tests = sum(p.size for _, p, _ in bands)
    k, p, ratio = min(bands, key=lambda band: float(np.min(band[1])))
    j = int(np.argmin(p))
    family = min(float(p[j]) * tests, 1.0)
    # Kept bin i of a half is its periodogram bin 2 + 2i, at (2 + 2i) / (h Δt) Hz.
    low, high = (2 + 2 * j * k) / (h * dt), (2 + 2 * ((j + 1) * k - 1)) / (h * dt)
    return {
        "tested": True,
        "p_family": family,
        "band_Hz": (low, high),
        "log_ratio_second_to_first": float(ratio[j]),
        "bands_tested": int(tests),
        "significant": bool(
            family < SPECTRAL_CHANGE_ALPHA and abs(ratio[j]) >= SPECTRAL_CHANGE_SIZE
        ),
    }


def detect_spectral_change(x: np.ndarray, sample_interval: float = 1.0) -> dict:
    """Whether a record's spectrum changes between its first and second half
    (`_spectral_change` on x itself; the selection tests its residual in the same way,
    `held_out.spectral_change`). Returns {"tested", "significant"} and, when tested,
    "p_family", "band_Hz" (at `sample_interval` seconds per sample),
    "log_ratio_second_to_first" and "bands_tested". On the raw record a start-up transient counts as a change too."""
    x = np.asarray(x, np.float64)
    if x.ndim != 1 or x.size == 0 or not np.all(np.isfinite(x)):
        raise ValueError(
            "detect_spectral_change: the record must be a non-empty 1-D array of finite values"
        )
    if not (math.isfinite(sample_interval) and sample_interval > 0):
        raise ValueError("detect_spectral_change: sample_interval must be a positive number")
    return _spectral_change(x, sample_interval)


LEVEL_SHIFT_ALPHA = 1e-3
"""Family-wise false-alarm rate of the level-shift test (`_level_shift`)."""


SHIFT_SIZE_Z = 3.0
"""A shift's size, measured in the window where it is most precise under the model, must
be this many standard deviations from zero (a spike's falls as 1/w there)."""


def _haar_variance(v: np.ndarray, w: int) -> float:
    """Var(D) of D = mean(x[j : j+w]) − mean(x[j−w : j]) from the variogram V:
    (2/w²) [Σ_{h=1}^{2w−1} min(h, 2w−h) V(h) − 2 Σ_{h=1}^{w−1} (w−h) V(h)]
    (2σ²/w for white noise of variance σ²)."""
    h = np.arange(1, 2 * w)
    across = np.minimum(h, 2 * w - h) @ v[1 : 2 * w]
    within = (w - h[: w - 1]) @ v[1:w]
    return 2.0 / w**2 * float(across - 2 * within)


def _haar_scan(r: np.ndarray, v: np.ndarray, scales: list):
    """The largest |z_w(j)| of the Haar differences of r (less its least-squares line) at
    the dyadic windows `scales`, Var D_w from the variogram v; returns (best: {"z",
    "index", "size", "window"} or None, the cumulative sum of r less its mean)."""
    n = r.size
    # A linear drift moves every D_w(j) alike: it is taken out here (the drift check
    # judges it), and what stands out is localised.
    t = np.arange(n) - (n - 1) / 2
    raw = np.concatenate([[0.0], np.cumsum(r - np.mean(r))])
    c = raw - np.concatenate([[0.0], np.cumsum(t)]) * (t @ r) / (t @ t)
    best = None
    for w in scales:
        var = _haar_variance(v, w)
        if not var > 0:
            continue
        j = np.arange(w, n - w + 1)
        d = ((c[j + w] - c[j]) - (c[j] - c[j - w])) / w
        z = d / math.sqrt(var)
        i = int(np.argmax(np.abs(z)))
        if best is None or abs(z[i]) > abs(best["z"]):
            best = {"z": float(z[i]), "index": int(j[i]), "size": float(d[i]), "window": w}
    return best, raw


def _shift_critical_z(n: int, scales: list) -> float:
    """Bonferroni over Σ_w 2n/w nearly independent positions at `LEVEL_SHIFT_ALPHA`."""
    tests = sum(2 * n / w for w in scales)
    return statistics.NormalDist().inv_cdf(1 - LEVEL_SHIFT_ALPHA / (2 * tests))


SCREEN_BLOCKS = 64
"""The level-shift screen's widest window is n / `SCREEN_BLOCKS` (its robust scale then
rests on at least that many independent windows)."""


def level_shift_screen(x: np.ndarray) -> dict:
    """A model-free screen for a step in the level: the Haar differences D_w(j) of
    `_level_shift` at dyadic windows up to n/`SCREEN_BLOCKS`, each standardised by its own
    robust scale over j (1.4826 × the median absolute deviation): whatever noise the record
    has, a Gauss–Markov process's wander included, sets the scale, and a step, which moves
    D_w at only 2w of the n places, stands out of it. (The record's own variogram or Allan
    variance would not do: at the wide windows where a small step shows, the step itself
    inflates them.) For deciding whether the forward selection, whose level-shift test
    judges against the fitted model, must run; a screen, so a false trigger costs only that
    run. Returns {"z", "critical_z", "index", "significant"}."""
    x = np.asarray(x, np.float64)
    n = x.size
    scales = [1 << k for k in range(2, 40) if SCREEN_BLOCKS << k <= n]
    best = {"z": 0.0, "index": 0}
    t = np.arange(n) - (n - 1) / 2
    c = np.concatenate([[0.0], np.cumsum(x - np.mean(x))])
    c = c - np.concatenate([[0.0], np.cumsum(t)]) * (t @ x) / (t @ t)
    for w in scales:
        j = np.arange(w, n - w + 1)
        d = ((c[j + w] - c[j]) - (c[j] - c[j - w])) / w
        scale = 1.4826 * float(np.median(np.abs(d - np.median(d))))
        if not scale > 0:
            continue
        z = d / scale
        i = int(np.argmax(np.abs(z)))
        if abs(z[i]) > abs(best["z"]):
            best = {"z": float(z[i]), "index": int(j[i])}
    critical = _shift_critical_z(n, scales) if scales else math.inf
    return {**best, "critical_z": float(critical), "significant": bool(abs(best["z"]) > critical)}


DRIFT_T = 8.0


DRIFT_BLOCKS = 32


def _drift(r: np.ndarray, dt: float) -> dict:
    """The least-squares slope of `DRIFT_BLOCKS` block means against time and its t value
    against their own scatter about the line (blocks much longer than the noise's
    correlation: a stationary noise gives |t| ≲ 4, a ramp of a few σ over the record
    |t| in the tens)."""
    usable = r.size // DRIFT_BLOCKS * DRIFT_BLOCKS
    means = r[:usable].reshape(DRIFT_BLOCKS, -1).mean(1)
    centre = (np.arange(DRIFT_BLOCKS) - (DRIFT_BLOCKS - 1) / 2) * usable / DRIFT_BLOCKS * dt
    slope = float(centre @ (means - means.mean()) / (centre @ centre))
    scatter = means - means.mean() - slope * centre
    se = math.sqrt(float(scatter @ scatter) / (DRIFT_BLOCKS - 2) / float(centre @ centre))
    return {"slope_per_s": slope, "t": abs(slope) / se if se > 0 else math.inf}
