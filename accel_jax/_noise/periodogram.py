"""The periodogram of a static record's first differences, as the sensor analysis's Whittle
likelihood (`spectral`) takes it: tapered (`TAPER`), at full resolution up to
`FULL_RESOLUTION` bins and on geometric bands beyond (`BAND_RATIO`), with the lag weights
of its debiasing correction on their grid (`MID_GRID` for long records) and the bins' and
grid's frequencies (`models.Frequencies`), computed once per record. Float64, on the host
(NumPy) but for the arrays the fits read."""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .models import Frequencies

FULL_RESOLUTION = 1 << 11
"""Up to this many periodogram bins the Whittle likelihood uses every bin."""

BAND_RATIO = 1.003
"""Beyond `FULL_RESOLUTION` bins: the first 256 bins singly, then geometric bands of this
width ratio, each entering as c (ln f̄ + Ī/f̄) with Ī the band's mean periodogram and f̄ the
mean of the expected periodogram over the band's bins (`expected_periodogram` evaluates it
at every bin). Exact where the spectrum is flat across the band: the model's narrowest
feature, a resonance of quality `MAX_QUALITY`, is wider than a band; checked against the
full-resolution likelihood in the tests."""

MID_GRID = 1 << 15
"""Grid of the debiasing correction for banded (long) records."""


class Periodogram(eqx.Module):
    """The periodogram of a differenced record, possibly on bands: mean ω, mean I and the
    number of bins per entry; the Fourier frequencies of its bins (`bins`, `band` the entry
    of each) and of the debiasing correction's grid, each with the sines and cosines the
    spectra need (`Frequencies`, computed once here rather than at every evaluation)."""

    omega: jax.Array
    power: jax.Array
    count: jax.Array
    lag_weight: jax.Array
    bins: jax.Array
    band: jax.Array
    length: int = eqx.field(static=True)
    bin_frequencies: Frequencies
    grid_frequencies: Frequencies

    def __init__(self, omega, power, count, lag_weight, bins, band, length):
        self.omega, self.power, self.count = omega, power, count
        self.lag_weight, self.bins, self.band, self.length = lag_weight, bins, band, length
        size = lag_weight.shape[0]
        self.bin_frequencies = Frequencies.table(bins)
        self.grid_frequencies = Frequencies.table(2 * np.pi * np.arange(size // 2 + 1) / size)

    @property
    def grid(self) -> int:
        return self.lag_weight.shape[0]

    @property
    def n_bins(self) -> float:
        return float(jnp.sum(self.count))


TAPER = 0.2
"""The periodogram tapers y with a Tukey (split cosine bell) window, cosine over 10 % at
each end: its leakage falls off fast, so a steep low-pass's stop band and the lowest
frequencies of a differenced record keep their information (the untapered end effect
2σ²/m swamps λσ² below j ≈ √m/4), for about a tenth of the samples' weight."""


def _autocorrelation(taper: np.ndarray) -> np.ndarray:
    """c(h), h = 0 … m−1: the taper's autocorrelation normalised to c(0) = 1."""
    m = taper.size
    full = np.fft.irfft(np.abs(np.fft.rfft(taper, 2 * m)) ** 2, 2 * m)[:m]
    return full / full[0]


def _lag_weight(taper: np.ndarray, size: int) -> np.ndarray:
    """1 − c(h) on a circular grid of `size` lags, c the taper's normalised autocorrelation
    (lags beyond size/2 dropped)."""
    m = taper.size
    c = _autocorrelation(taper)
    half = size // 2
    lags = np.arange(size)
    lags = np.minimum(lags, size - lags)
    weight = np.ones(size)
    inside = lags < min(m, half + 1)
    weight[inside] = 1 - c[lags[inside]]
    if size < 2 * m:
        weight[~inside] = 0.0  # truncated: the correction's lags stop at size/2
    else:
        weight[~inside] = 1.0  # beyond the record's lags c = 0
    return weight


def _grid(m: int, taper: np.ndarray) -> int:
    """The correction's grid: the power of two ≥ 2m (every lag of the record) for records
    up to 2^14 differences; beyond, the smallest power of two ≥ 2^13 whose half-length lag
    has 1 − c(h) ≤ 0.01 (the taper makes 1 − c grow as h² over the taper's length, so the
    correction's weight at longer lags is small), at most `MID_GRID` (the correction's lags
    then stop at 2^14: the autocovariance of a differenced short-memory or flicker noise is
    negligible there)."""
    full = 1 << (2 * m - 1).bit_length()
    if m <= 1 << 14:
        return full
    c = _autocorrelation(taper)
    size = 1 << 13
    while size < min(full, MID_GRID) and 1 - c[size // 2] > 0.01:
        size *= 2
    return min(size, full, MID_GRID)


@functools.lru_cache(maxsize=8)
def _taper_weight(m: int) -> np.ndarray:
    """`_lag_weight` of the `TAPER` window of m samples on its `_grid` (a function of m
    alone: cached, as a selection takes the periodogram of records of two lengths many
    times)."""
    from scipy.signal.windows import tukey

    taper = tukey(m, TAPER)
    weight = _lag_weight(taper, _grid(m, taper))
    weight.setflags(write=False)
    return weight


def periodogram(x: np.ndarray, *, banded: bool | None = None) -> Periodogram:
    """Tapered periodogram I_j = |Σ w_k y_k e^{−iω_j k}|²/Σ w_k² of y = diff(x) (m samples,
    demeaned, `TAPER`), j = 1..⌈m/2⌉ − 1 (no zero or Nyquist bin), banded (the first 256
    bins singly, then geometric bands) when there are more than `FULL_RESOLUTION` bins (or
    when `banded` says so)."""
    from scipy.signal.windows import tukey

    y = np.diff(np.asarray(x, np.float64))
    m = y.size
    taper = tukey(m, TAPER)
    y = y - np.sum(taper * y) / np.sum(taper)
    power = np.abs(np.fft.rfft(taper * y)[1:]) ** 2 / np.sum(taper**2)
    omega = 2 * np.pi * np.arange(1, power.size + 1) / m
    if m % 2 == 0:  # the Nyquist bin is real: its I/f is χ²₁, not χ²₂/2; leave it out
        power, omega = power[:-1], omega[:-1]
    if banded is None:
        banded = power.size > FULL_RESOLUTION
    if not banded:
        weight = _taper_weight(m)
        omega = jnp.asarray(omega)
        index = jnp.arange(power.size)
        return Periodogram(
            omega, jnp.asarray(power), jnp.ones(power.size), jnp.asarray(weight), omega, index, m
        )
    single = min(256, power.size)
    edges = [0, *range(1, single + 1)]
    while edges[-1] < power.size:
        edges.append(max(edges[-1] + 1, int(math.ceil(edges[-1] * BAND_RATIO))))
    edges[-1] = power.size
    edges = np.asarray(edges)
    counts = np.diff(edges).astype(np.float64)
    sums_p = np.add.reduceat(power, edges[:-1])
    sums_w = np.add.reduceat(omega, edges[:-1])
    weight = _taper_weight(m)
    centre = jnp.asarray(sums_w / counts)
    return Periodogram(
        centre,
        jnp.asarray(sums_p / counts),
        jnp.asarray(counts),
        jnp.asarray(weight),
        centre,
        jnp.arange(counts.size),
        m,
    )
