"""Time-domain Monte Carlo check of the exact expectation: one synthesised realisation of
the vibration (`synthesize_vibration`, a spectral synthesis on the record's Fourier grid)
and the time average of the indicated acceleration over it
(`time_domain_vibration_error`), whose expectation over the key is `vibration_error`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike

from .._static import StaticTransferFunction, indicated_acceleration
from .environment import VibrationEnvironment


def _matrix_sqrt_psd(cov: Array) -> Array:
    # Symmetric square root via eigh: works for singular covariances (axes with σ = 0),
    # where a Cholesky factorisation does not. Not differentiated (Monte Carlo only).
    values, vectors = jnp.linalg.eigh(cov)
    return vectors * jnp.sqrt(jnp.clip(values, 0.0))[..., None, :]


def synthesize_vibration(
    env: VibrationEnvironment, ts: ArrayLike, *, key: Array, n_tones: int = 64
) -> Array:
    """One realisation of v(t) [g], shape (3, len(ts)).

    Sinusoid: b_i sin(2π f (t + t0) + φ_i) with a random start t0 ~ U(0, 1/f) (so a finite
    record is an unbiased sample of the phase average). Random part: `n_tones` equispaced
    frequencies across `random_band` with independent Gaussian cosine/sine amplitudes of
    covariance Σ/n_tones (a spectral synthesis: exactly Gaussian at every instant with
    covariance Σ, flat spectrum over the band), the tones snapped to multiples of 1/T for
    a record of length T (`ts` uniform). Use a record of whole sine periods for the lowest
    variance.
    """
    ts = jnp.asarray(ts)
    k_t0, k_a, k_b = jax.random.split(key, 3)
    dtype = ts.dtype
    t0 = jax.random.uniform(k_t0, (), dtype) / env.sine_frequency
    sine = env.sine_amplitude[:, None] * jnp.sin(
        2 * jnp.pi * env.sine_frequency * (ts + t0)[None, :] + env.sine_phase[:, None]
    )
    f_low, f_high = env.random_band[0], env.random_band[1]
    freqs = f_low + (f_high - f_low) * (jnp.arange(n_tones, dtype=dtype) + 0.5) / n_tones
    # Snap the tones onto the record's Fourier grid (multiples of 1/T): each then averages
    # to exactly zero over the record, which removes the O(σ/sqrt(n)) variance the linear
    # terms of a_F would otherwise add to a ppm-level time average.
    df = 1.0 / (ts.shape[-1] * (ts[-1] - ts[0]) / jnp.maximum(ts.shape[-1] - 1, 1))
    freqs = jnp.maximum(jnp.round(freqs / df), 1.0) * df
    root = _matrix_sqrt_psd(env.random_covariance) / jnp.sqrt(n_tones)
    za = root @ jax.random.normal(k_a, (3, n_tones), dtype)
    zb = root @ jax.random.normal(k_b, (3, n_tones), dtype)
    phase = 2 * jnp.pi * freqs[:, None] * ts[None, :]
    random = za @ jnp.cos(phase) + zb @ jnp.sin(phase)
    return sine + random


def time_domain_vibration_error(
    tf: StaticTransferFunction,
    env: VibrationEnvironment,
    a3: ArrayLike,
    a1: ArrayLike,
    a2: ArrayLike,
    ts: ArrayLike,
    *,
    key: Array,
    n_tones: int = 64,
) -> Array:
    """Time average of a_F(a + v(t)) − a_F(a) over one synthesised record [g] (scalar
    steady accelerations). Its expectation over `key` is the exact `vibration_error`;
    vmap over keys (or use `accel_jax.sweep`) for a Monte Carlo check."""
    v = synthesize_vibration(env, ts, key=key, n_tones=n_tones)
    out = indicated_acceleration(tf, a3 + v[2], a1 + v[0], a2 + v[1])
    return jnp.mean(out) - indicated_acceleration(tf, a3, a1, a2)
