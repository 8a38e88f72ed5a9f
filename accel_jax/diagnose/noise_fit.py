"""The noise kind's model and fit: white + coloured block + level filtered exactly (a Kalman
filter over the components' state space), the Whittle start on band-averaged
periodograms and the exact-likelihood polish, vmapped over records."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .._noise import _DIFFUSE
from .base import (
    effect_library,
)
from .noise_effects import AbstractNoiseEffect, NoiseComponents

WHITTLE_STEPS = 128
POLISH_STEPS = 64
"""BFGS step budgets of the Whittle start and of the exact-likelihood polish."""

FIT_TOLERANCE = 1e-6
"""rtol = atol of the BFGS fits (on O(1) scaled parameters; the objective is −ln L / n)."""


WHITTLE_BANDS = 64
"""The Whittle start uses the periodogram averaged over this many frequency bands (the
lowest bins one by one, then log-spaced): a start needs the right basin, not the last digit,
and every start of every candidate of every record evaluates it (8 × 4 per record)."""


# --------------------------------------------------------------------------------------
# The model: white + coloured block + level, filtered exactly
# --------------------------------------------------------------------------------------


def _effects() -> list[AbstractNoiseEffect]:
    return [cls() for cls in effect_library("noise").values()]


def _components(z, candidate) -> tuple[jax.Array, NoiseComponents]:
    """White variance and the added processes of candidate `candidate` (0: nominal,
    i: nominal + effect i − 1) at z = [ln σ_w, effect slot]."""
    white = jnp.exp(2 * z[0])
    zero = jnp.zeros_like(white)
    out = NoiseComponents(zero, zero, zero, zero)
    for i, effect in enumerate(_effects(), start=1):
        parts = effect.components(z[1 : 1 + effect.n_params])
        out = jax.tree_util.tree_map(lambda o, p, i=i: jnp.where(candidate == i, p, o), out, parts)
    return white, out


def filter_terms(white, parts: NoiseComponents, record, diffuse):
    """Exact Kalman filter of level + coloured block + white noise on a record.

    State (ℓ, s₁, s₂): ℓ_{k+1} = ℓ_k + √walk·w, (s₁, s₂)_{k+1} = ρ Rot(θ)(s₁, s₂)_k + noise of
    covariance v(1 − ρ²) I (`accel_jax._noise.ExponentialCosine`'s exact discrete form; a
    Gauss–Markov noise at θ = 0), observation x_k = ℓ_k + s₁,k + σ_w w_k. Prior: ℓ diffuse
    (variance `diffuse`), (s₁, s₂) stationary (v I). The covariance update is the standard
    form (P⁺ = P − K S Kᵀ), written out for the six distinct entries.

    **Arguments:** `white` σ_w²; `parts` (`NoiseComponents`); `record` x (n,), centred;
    `diffuse` the level's prior variance.

    **Returns:** (innovations ν_k, their variances S_k, log-likelihood terms), each (n,).
    jit/vmap/grad-safe.
    """
    v, rho, theta, walk = parts.variance, parts.decay, parts.rotation, parts.walk
    a11 = rho * jnp.cos(theta)
    a21 = rho * jnp.sin(theta)
    refresh = v * (1 - rho**2)
    log_2pi = math.log(2 * math.pi)

    def step(carry, x):
        ml, m1, m2, pll, pl1, pl2, p11, p12, p22 = carry
        nu = x - ml - m1
        s = pll + 2 * pl1 + p11 + white
        kl, k1, k2 = (pll + pl1) / s, (pl1 + p11) / s, (pl2 + p12) / s
        ml, m1, m2 = ml + kl * nu, m1 + k1 * nu, m2 + k2 * nu
        pll, pl1, pl2 = pll - kl * kl * s, pl1 - kl * k1 * s, pl2 - kl * k2 * s
        p11, p12, p22 = p11 - k1 * k1 * s, p12 - k1 * k2 * s, p22 - k2 * k2 * s
        # Predict: A = ρ [[cos θ, −sin θ], [sin θ, cos θ]] on (s₁, s₂).
        m1, m2 = a11 * m1 - a21 * m2, a21 * m1 + a11 * m2
        pl1, pl2 = a11 * pl1 - a21 * pl2, a21 * pl1 + a11 * pl2
        t11, t12 = a11 * p11 - a21 * p12, a11 * p12 - a21 * p22
        t21, t22 = a21 * p11 + a11 * p12, a21 * p12 + a11 * p22
        p11 = t11 * a11 - t12 * a21 + refresh
        p12 = t11 * a21 + t12 * a11
        p22 = t21 * a21 + t22 * a11 + refresh
        pll = pll + walk
        log_lik = -0.5 * (log_2pi + jnp.log(s) + nu**2 / s)
        return (ml, m1, m2, pll, pl1, pl2, p11, p12, p22), (nu, s, log_lik)

    zero = jnp.zeros_like(white + v)
    carry = (zero, zero, zero, zero + diffuse, zero, zero, zero + v, zero, zero + v)
    _, (nu, s, log_lik) = jax.lax.scan(step, carry, record)
    return nu, s, log_lik


def _bands(n_frequencies: int) -> tuple[np.ndarray, int]:
    """Band index of each periodogram bin (static): the first bins one by one, then
    log-spaced bands up to the Nyquist frequency."""
    single = min(16, n_frequencies)
    edges = np.unique(
        np.round(np.geomspace(single, n_frequencies, WHITTLE_BANDS - single + 1)).astype(int)
    )
    index = np.arange(n_frequencies)
    band = np.where(index < single, index, single + np.searchsorted(edges, index, side="right") - 1)
    _, band = np.unique(band, return_inverse=True)
    return band, int(band.max()) + 1


def _whittle(z, args):
    """Whittle −ln L per frequency of the differenced record, on band averages: its
    spectrum is (2 − 2 cos ω)(σ_w² + S_c(ω)) + qΔ, S_c = v/2 [P(ω − θ) + P(ω + θ)], P the
    Poisson kernel (1 − ρ²)/(1 − 2ρ cos x + ρ²) — the spectrum of R_k = v ρ^|k| cos kθ."""
    periodogram, omega, counts, candidate = args
    white, parts = _components(z, candidate)
    rho = parts.decay

    def poisson(x):
        return (1 - rho**2) / (1 - 2 * rho * jnp.cos(x) + rho**2)

    theta = parts.rotation
    colored = 0.5 * parts.variance * (poisson(omega - theta) + poisson(omega + theta))
    spectrum = (2 - 2 * jnp.cos(omega)) * (white + colored) + parts.walk
    return jnp.sum(counts * (jnp.log(spectrum) + periodogram / spectrum)) / jnp.sum(counts)


def _negative_log_likelihood(z, args):
    record, weight, candidate, diffuse = args
    white, parts = _components(z, candidate)
    _, _, log_lik = filter_terms(white, parts, record, diffuse)
    return -jnp.sum(weight * log_lik) / jnp.sum(weight)


def _fit_record(record, split_mask, guesses, candidates, band, band_count):
    """Fit every candidate (vmapped) to one normalised, centred record: Whittle start on
    the training part, exact-likelihood polish, then the filter over the whole record."""
    n = record.shape[0]
    train = split_mask
    n_train = jnp.sum(train)
    # Conditional on the first sample: the likelihood terms of samples 1..n_train − 1.
    weight = train * (jnp.arange(n) > 0)
    diffuse = _DIFFUSE * jnp.sum(train * record**2) / n_train
    # Periodogram of the training part's differences (the level drops out), Hann-tapered:
    # differencing spans the spectrum over decades (≈ 0 at ω → 0), and the leakage of an
    # untapered finite record would swamp its low-frequency end. Zero-padded to n − 1.
    index = jnp.arange(n - 1)
    m = n_train - 1
    taper = jnp.where(index < m, 0.5 - 0.5 * jnp.cos(2 * jnp.pi * (index + 0.5) / m), 0.0)
    diff = jnp.diff(record) * taper
    fourier = jnp.fft.rfft(diff)
    periodogram = (jnp.abs(fourier) ** 2 / jnp.sum(taper**2))[1:]
    omega = (2 * jnp.pi * jnp.arange(fourier.shape[0]) / (n - 1))[1:]
    # The band index enters as an argument: computed on the host and embedded as a
    # constant, a million-sample record's index made XLA spend seconds constant-folding
    # (and print warnings about it).
    n_bands = band_count.shape[0]
    counts = jax.ops.segment_sum(jnp.ones_like(omega), band, n_bands)
    periodogram = jax.ops.segment_sum(periodogram, band, n_bands) / counts
    omega = jax.ops.segment_sum(omega, band, n_bands) / counts

    def whittle_fit(guess, candidate):
        start = optx.minimise(
            _whittle,
            optx.BFGS(rtol=FIT_TOLERANCE, atol=FIT_TOLERANCE),
            guess,
            args=(periodogram, omega, counts, candidate),
            max_steps=WHITTLE_STEPS,
            throw=False,
        )
        value = _whittle(start.value, (periodogram, omega, counts, candidate))
        ok = jnp.all(jnp.isfinite(start.value)) & jnp.isfinite(value)
        return jnp.where(ok, start.value, guess), jnp.where(ok, value, jnp.inf)

    def fit_one(guesses, candidate):
        starts, values = jax.vmap(whittle_fit, in_axes=(0, None))(guesses, candidate)
        z0 = starts[jnp.argmin(values)]
        args = (record, weight, candidate, diffuse)
        polish = optx.minimise(
            _negative_log_likelihood,
            optx.BFGS(rtol=FIT_TOLERANCE, atol=FIT_TOLERANCE),
            z0,
            args=args,
            max_steps=POLISH_STEPS,
            throw=False,
        )
        z = polish.value
        white, parts = _components(z, candidate)
        nu, s, log_lik = filter_terms(white, parts, record, diffuse)
        converged = polish.result == optx.RESULTS.successful
        return z, nu, s, jnp.sum(weight * log_lik), converged, polish.stats["num_steps"]

    return jax.vmap(fit_one)(guesses, candidates)
