"""Where the nominal model's residual departs from white noise (`localise`): its spectrum
(`welch`) against the white floor by frequency band, its autocorrelation (Ljung–Box), and
its level and spread over segments of the record."""

from __future__ import annotations

import numpy as np

from ..base import ljung_box
from .state import NoiseRecord


def welch(x: np.ndarray, dt: float):
    """Welch's one-sided PSD of `x` [unit²/Hz] (Hann windows of up to 512 samples, half
    overlapping): (frequencies [Hz], PSD)."""
    n = x.size
    length = int(min(512, 2 ** np.floor(np.log2(max(n // 4, 16)))))
    window = np.hanning(length)
    hop = length // 2
    frames = [x[i : i + length] for i in range(0, n - length + 1, hop)]
    spectra = [np.abs(np.fft.rfft((f - f.mean()) * window)) ** 2 for f in frames]
    psd = 2 * dt * np.mean(spectra, axis=0) / np.sum(window**2)
    return np.fft.rfftfreq(length, dt), psd


def localise(residual: np.ndarray, innovations: np.ndarray, sigma: float, rec: NoiseRecord) -> dict:
    """Where the nominal model's residual departs from white noise: its spectrum against the
    white floor (by frequency band), its autocorrelation (Ljung–Box), and its level and
    spread over segments of the record (a random walk wanders, a stationary noise not)."""
    dt = rec.dt
    freqs, psd = welch(residual, dt)
    floor = 2 * sigma**2 * dt
    f, p = freqs[1:], psd[1:]
    edges = np.geomspace(f[0], f[-1], 9)
    bands = []
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        inside = (f >= lo) & (f <= hi)
        if np.any(inside):
            bands.append(
                {
                    "band_Hz": [float(lo), float(hi)],
                    "psd_over_floor": float(np.mean(p[inside]) / floor),
                }
            )
    above = p > 2 * floor
    segments = []
    n = residual.size
    for k in range(8):
        part = residual[k * n // 8 : (k + 1) * n // 8]
        segments.append(
            {
                "t_start_s": float(k * n // 8 * dt),
                "mean_g": float(np.mean(part)),
                "rms_g": float(np.sqrt(np.mean(part**2))),
                "held_out": bool(k * n // 8 >= rec.split),
            }
        )
    whiteness = ljung_box(innovations, lags=20)
    return {
        "frequency": {
            "noise_floor_g2_per_Hz": floor,
            "bands": bands,
            "peak_excess_Hz": float(f[np.argmax(p / floor)]),
            "peak_excess_ratio": float(np.max(p) / floor),
            "fraction_of_bins_above_2x_floor": float(np.mean(above)),
            "frequency_Hz": freqs.tolist(),
            "psd_g2_per_Hz": psd.tolist(),
        },
        "whiteness": whiteness,
        "time": {"segments": segments},
        "noise_sigma_g": sigma,
    }
