"""Truth records for the real-sensor noise harness, written apart from the diagnosing code.

NumPy and SciPy only (never `accel_jax`): white noise, a Gauss–Markov process (AR(1) by
`scipy.signal.lfilter`), an exponential-cosine process (the damped-rotation recursion),
a random walk (cumulative sum), flicker noise by FFT shaping of white noise (Timmer &
König; two-sided PSD B²/(2π|f|) down to 1/T), the sensor's low-pass (`scipy.signal.butter`
order 2, `sosfilt`, applied to the noise ahead of the ADC), periodic lines, a start-up
transient a e^{−t/τ}, and an ADC grid (rounding to multiples of q with a random offset).
"""

from __future__ import annotations

import math

import numpy as np
from scipy import signal


def flicker(rng: np.random.Generator, n: int, dt: float, b: float) -> np.ndarray:
    """Flicker noise with two-sided PSD S(f) = B²/(2π|f|) (per-sample spectral density
    B²/|ω|), Fourier-synthesised: X_j = √(n f_j / 2)(a + ib)."""
    size = 2 * n  # synthesise twice the length and keep half: no forced periodicity
    omega = 2 * np.pi * np.arange(size // 2 + 1) / size
    dens = np.zeros_like(omega)
    dens[1:] = b**2 / omega[1:]
    coef = np.sqrt(size * dens / 2) * (
        rng.normal(size=omega.size) + 1j * rng.normal(size=omega.size)
    )
    coef[-1] = np.sqrt(size * dens[-1]) * rng.normal()
    return np.fft.irfft(coef, n=size)[:n]


def gauss_markov(rng, n, dt, sigma, tau):
    rho = math.exp(-dt / tau)
    w = rng.normal(size=n) * sigma * math.sqrt(1 - rho**2)
    w[0] = rng.normal() * sigma
    return signal.lfilter([1.0], [1.0, -rho], w)


def exp_cosine(rng, n, dt, sigma, alpha, beta):
    rho, theta = math.exp(-alpha * dt), beta * dt
    c, s = rho * math.cos(theta), rho * math.sin(theta)
    drive = rng.normal(size=(n, 2)) * sigma * math.sqrt(1 - rho**2)
    state = rng.normal(size=2) * sigma
    out = np.empty(n)
    for k in range(n):
        out[k] = state[0]
        state = np.array([c * state[0] - s * state[1], s * state[0] + c * state[1]]) + drive[k]
    return out


def record(rng: np.random.Generator, n: int, dt: float, truth: dict) -> np.ndarray:
    """One record of the composite `truth` (keys: white, gauss_markov=(σ, τ),
    exp_cosine=(σ, α, β), random_walk=q, flicker=B, bandlimit=f_c, white_after_filter=σ_a
    (white noise added after the low-pass), lines=[(f, A)], transient=(a, τ),
    quantization=q, level)."""
    x = truth["white"] * rng.normal(size=n)
    if "gauss_markov" in truth:
        x += gauss_markov(rng, n, dt, *truth["gauss_markov"])
    if "exp_cosine" in truth:
        x += exp_cosine(rng, n, dt, *truth["exp_cosine"])
    if "flicker" in truth:
        x += flicker(rng, n, dt, truth["flicker"])
    if "random_walk" in truth:
        x += np.cumsum(rng.normal(size=n)) * math.sqrt(truth["random_walk"] * dt)
    if "bandlimit" in truth:
        sos = signal.butter(2, truth["bandlimit"], fs=1 / dt, output="sos")
        x = signal.sosfilt(sos, np.concatenate([np.zeros(0), x]))
    if "white_after_filter" in truth:  # a signal chain's own white noise (its ADC's)
        x += truth["white_after_filter"] * rng.normal(size=n)
    t = np.arange(n) * dt
    for f, amp in truth.get("lines", ()):
        x += amp * np.cos(2 * np.pi * f * t + rng.uniform(0, 2 * np.pi))
    if "transient" in truth:
        a, tau = truth["transient"]
        x += a * np.exp(-t / tau)
    x += truth.get("level", 0.0)
    if "quantization" in truth:
        q = truth["quantization"]
        offset = rng.uniform(0, q)
        x = np.round((x - offset) / q) * q + offset
    return x
