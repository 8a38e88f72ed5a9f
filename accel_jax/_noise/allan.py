"""The Allan deviation, a cross-check of the autocorrelation and likelihood fits:
`allan_deviation` is the IEEE Std 952 overlapping estimator on a record,
`allan_variance_of_model` the exact Allan variance of a stationary sampled model from its
autocovariance, and `allan_coefficients` fits the standard white, bias-instability and
random-walk coefficients (`AllanCoefficients`) to an Allan deviation.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import equinox as eqx
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, ArrayLike

from .models import AbstractNoiseModel
from .record import _LOG_CLIP, Scalar, _sample_interval, _validate_record


def allan_deviation(
    record: ArrayLike, sample_interval: float, cluster_sizes: Sequence[int]
) -> tuple[Array, Array]:
    """Overlapping Allan deviation of a rate record (e.g. gyro drift [rad/s] or accelerometer
    error [m/s²]).

    With θ_j = Δ Σ_{i<j} x_i (θ_0 = 0, j = 0..N) and τ = mΔ,

        σ²(τ) = Σ_{k=0}^{N−2m} (θ_{k+2m} − 2θ_{k+m} + θ_k)² / (2 τ² (N − 2m + 1)),

    the IEEE Std 952 overlapping estimator (the same as allantools.oadev).

    **Arguments:** `record` x, shape (N,); `sample_interval` Δ [s]; `cluster_sizes`: the
    m's (static ints, 1 ≤ m ≤ (N − 1)/2).

    **Returns:** (τ [s], σ(τ) [record unit]), each of shape (len(cluster_sizes),). Jit-safe;
    the cumulative sum loses ~log10(N) digits, so use float64 for long records.
    """
    x = _validate_record("allan_deviation", record)
    _sample_interval("allan_deviation", sample_interval)
    n = x.shape[0]
    sizes = [int(m) for m in cluster_sizes]
    if not sizes or min(sizes) < 1 or max(sizes) > (n - 1) // 2:
        raise ValueError(
            f"allan_deviation: cluster sizes must be in 1..{(n - 1) // 2} for a record of {n} "
            f"samples, got {list(cluster_sizes)!r}."
        )
    return _allan_deviation(x, sample_interval, tuple(sizes))


@eqx.filter_jit
def _allan_deviation(x, sample_interval, sizes):
    n = x.shape[0]
    theta = jnp.concatenate([jnp.zeros(1, x.dtype), jnp.cumsum(x - jnp.mean(x))]) * sample_interval
    out = []
    for m in sizes:
        d = theta[2 * m :] - 2 * theta[m : n + 1 - m] + theta[: n + 1 - 2 * m]
        tau = m * sample_interval
        out.append(jnp.sum(d**2) / (2 * tau**2 * (n - 2 * m + 1)))
    taus = jnp.asarray(sizes, dtype=x.dtype) * sample_interval
    return taus, jnp.sqrt(jnp.stack(out))


def allan_variance_of_model(
    model: AbstractNoiseModel, sample_interval: float, cluster_sizes: Sequence[int]
) -> Array:
    """Exact Allan variance of a stationary sampled model at τ = mΔ, from its
    autocovariance: σ²(m) = (Var S − Cov(S₁, S₂))/m², S a sum of m consecutive samples,
    Var S = Σ_{|k|<m}(m − |k|)R_k, Cov(S₁,S₂) = Σ_{|k|<m}(m − |k|)R_{k+m}. [unit²]"""
    sizes = tuple(int(m) for m in cluster_sizes)
    if not sizes or min(sizes) < 1:
        raise ValueError(f"allan_variance_of_model: cluster sizes must be ≥ 1, got {sizes!r}.")
    return _allan_variance_of_model(model, sample_interval, sizes)


@eqx.filter_jit
def _allan_variance_of_model(model, sample_interval, sizes):
    acov = model.autocovariance(jnp.arange(2 * max(sizes)) * sample_interval)
    out = []
    for m in sizes:
        weight = m - jnp.abs(jnp.arange(-(m - 1), m))
        var_sum = jnp.sum(weight * acov[jnp.abs(jnp.arange(-(m - 1), m))])
        cov_sums = jnp.sum(weight * acov[jnp.arange(1, 2 * m)])
        out.append((var_sum - cov_sums) / m**2)
    return jnp.stack(out)


class AllanCoefficients(eqx.Module):
    """Standard Allan-variance coefficients, σ²(τ) = N²/τ + (2 ln2/π) B² + K² τ/3.

    **Fields:** `white` N [unit·√s] (angle/velocity random walk, slope −1/2),
    `bias_instability` B [unit] (flat, slope 0, flicker), `random_walk` K [unit/√s] (rate
    random walk, slope +1/2); `slopes`: local log-log slopes of σ(τ) between consecutive τ.
    """

    white: Scalar
    bias_instability: Scalar
    random_walk: Scalar
    slopes: Array


def allan_coefficients(taus: ArrayLike, adev: ArrayLike) -> AllanCoefficients:
    """Fit the standard slopes to an Allan deviation: N, B, K ≥ 0 of
    σ²(τ) = N²/τ + (2 ln 2/π) B² + K²τ/3, least squares on log σ² (optimistix
    Levenberg-Marquardt over log-coefficients, so each stays positive; a term the data do
    not support shrinks towards zero). A white record of σ_x at Δ has N = σ_x √Δ; a random
    walk of intensity q has K = √q."""
    taus = jnp.asarray(taus)
    avar = jnp.asarray(adev) ** 2
    if taus.ndim != 1 or taus.shape != avar.shape or taus.shape[0] < 3:
        raise ValueError(
            f"allan_coefficients: need ≥ 3 matching τ and σ(τ), got shapes {taus.shape}, "
            f"{jnp.shape(adev)}."
        )
    flicker = 2 * math.log(2) / math.pi

    def model(log_c):
        c = jnp.exp(2 * jnp.clip(log_c, -_LOG_CLIP, _LOG_CLIP))
        return c[0] / taus + flicker * c[1] + c[2] * taus / 3

    def residuals(log_c, _):
        return jnp.log(model(log_c)) - jnp.log(avar)

    floor = jnp.min(avar)
    start = jnp.log(jnp.sqrt(jnp.stack([avar[0] * taus[0], floor / 3, 3 * floor / taus[-1]])))
    sol = optx.least_squares(
        residuals,
        optx.LevenbergMarquardt(rtol=1e-10, atol=1e-12),
        start,
        max_steps=512,
        throw=False,
    )
    c = jnp.exp(jnp.clip(sol.value, -_LOG_CLIP, _LOG_CLIP))
    slopes = jnp.diff(jnp.log(jnp.asarray(adev))) / jnp.diff(jnp.log(taus))
    return AllanCoefficients(white=c[0], bias_instability=c[1], random_walk=c[2], slopes=slopes)
