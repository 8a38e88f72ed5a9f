"""The paper's identification rules on a sample autocorrelation: `fit_gauss_markov_paper` is
the log-linear rule (15) for the first-order Gauss-Markov model, and `fit_exp_cosine_paper`
takes β from the first zero of the autocorrelation (19) and α by the log-linear rule (21)
for the exponential-cosine model. Both follow the record's dtype, are jit/vmap-safe and
return their result code in `PaperGaussMarkovFit` / `PaperExpCosineFit`.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike

from .models import ExponentialCosine, GaussMarkov
from .record import NoiseFitResult, Scalar, _sample_interval, _throw


class PaperGaussMarkovFit(eqx.Module):
    """Rule (15). **Fields:** `model` (GaussMarkov), `decay_rate` α̂ [1/s], `lags_used`
    (count of lags j ≥ 1 in the sum), `result` (NoiseFitResult)."""

    model: GaussMarkov
    decay_rate: Scalar
    lags_used: Array
    result: NoiseFitResult


class PaperExpCosineFit(eqx.Module):
    """Rules (19)-(21). **Fields:** `model` (ExponentialCosine), `first_zero` τ_β [s],
    `lags_used`, `result`."""

    model: ExponentialCosine
    first_zero: Scalar
    lags_used: Array
    result: NoiseFitResult


def _leading_positive(r, floor: float | Array = 0.0):
    """Mask of lags 1..K before the first r_j ≤ floor (ln r_j must exist: floor ≥ 0)."""
    positive = r[1:] > floor
    return jnp.concatenate([jnp.zeros(1, bool), jnp.cumprod(positive).astype(bool)])


def fit_gauss_markov_paper(
    autocovariance: ArrayLike,
    sample_interval: float,
    *,
    min_correlation: float = 0.0,
    throw: bool = True,
) -> PaperGaussMarkovFit:
    """The paper's rule (15): σ̂² = R_0, α̂ = −Σ_j ln r_j / Σ_j τ_j, r_j = R_j/R_0.

    The sums run over lags j = 1..K of the given autocovariance (K = its length − 1) up to
    the first non-positive r_j. The rule is the paper's (from Σ ln r_j = −α Σ τ_j, eq. 14),
    not the least-squares line through the origin; it weights large lags, whose r_j are
    noisiest, heavily: keep K near τ_c/Δ or below, or stop the sum earlier with
    `min_correlation` (e.g. e⁻¹: lags while r_j > e⁻¹, about one correlation time).

    **Arguments:** `autocovariance`: R_0..R_K from `autocorrelation` [u²];
    `sample_interval`: Δ [s]; `min_correlation`: the sum stops at the first r_j at or below
    it (default 0, the paper's condition r_j > 0); `throw`: raise on failure (else the
    result code).

    **Returns:** `PaperGaussMarkovFit`; τ̂_c = 1/α̂. Jit/vmap-safe.
    """
    _sample_interval("fit_gauss_markov_paper", sample_interval)
    R = jnp.asarray(autocovariance)
    if R.ndim != 1 or R.shape[0] < 2:
        raise ValueError(f"fit_gauss_markov_paper: need R_0..R_K with K ≥ 1, got shape {R.shape}.")
    r = R / R[0]
    lags = jnp.arange(R.shape[0], dtype=R.dtype) * sample_interval
    mask = _leading_positive(r, jnp.maximum(min_correlation, 0.0))
    count = jnp.sum(mask)
    log_r = jnp.log(jnp.where(mask, r, 1.0))
    alpha = -jnp.sum(log_r) / jnp.where(count > 0, jnp.sum(jnp.where(mask, lags, 0.0)), 1.0)
    ok = (count > 0) & (alpha > 0)
    alpha = jnp.where(ok, alpha, 1.0 / sample_interval)
    result = NoiseFitResult.where(ok, NoiseFitResult.successful, NoiseFitResult.no_positive_lags)
    fit = PaperGaussMarkovFit(
        model=GaussMarkov(jnp.sqrt(R[0]), 1.0 / alpha),
        decay_rate=alpha,
        lags_used=count,
        result=result,
    )
    return _throw(result, fit, throw)


def fit_exp_cosine_paper(
    autocovariance: ArrayLike, sample_interval: float, *, throw: bool = True
) -> PaperExpCosineFit:
    """The paper's rules (19)-(21) for R(τ) = σ² e^{−α|τ|} cos βτ.

    σ̂² = R_0; τ_β = the first zero of R (linear interpolation between the bracketing lags);
    β̂ = π/(2 τ_β) (19); α̂ = Σ_j (ln cos β̂τ_j − ln r_j)/Σ_j τ_j (21) over lags 1 ≤ j with
    τ_j < τ_β (so r_j > 0 and |β̂τ_j| < π/2).

    **Returns:** `PaperExpCosineFit`; `no_zero_crossing` when R stays positive over the
    lags given. Jit/vmap-safe.
    """
    _sample_interval("fit_exp_cosine_paper", sample_interval)
    R = jnp.asarray(autocovariance)
    if R.ndim != 1 or R.shape[0] < 3:
        raise ValueError(f"fit_exp_cosine_paper: need R_0..R_K with K ≥ 2, got shape {R.shape}.")
    r = R / R[0]
    lags = jnp.arange(R.shape[0], dtype=R.dtype) * sample_interval
    mask = _leading_positive(r)
    # First non-positive lag j0 (≥ 1): the zero lies between j0 − 1 and j0.
    nonpositive = r[1:] <= 0
    has_zero = jnp.any(nonpositive)
    j0 = 1 + jnp.argmax(nonpositive)
    r_before, r_at = r[j0 - 1], r[j0]
    fraction = r_before / jnp.where(has_zero, r_before - r_at, 1.0)
    first_zero = jnp.where(has_zero, (j0 - 1 + fraction) * sample_interval, lags[-1])
    beta = 0.5 * jnp.pi / first_zero
    mask = mask & (lags < first_zero)
    count = jnp.sum(mask)
    cos_term = jnp.log(jnp.where(mask, jnp.cos(beta * lags), 1.0))
    log_r = jnp.log(jnp.where(mask, r, 1.0))
    alpha = jnp.sum(cos_term - log_r) / jnp.where(
        count > 0, jnp.sum(jnp.where(mask, lags, 0.0)), 1.0
    )
    ok_alpha = (count > 0) & (alpha > 0)
    result = NoiseFitResult.where(
        has_zero, NoiseFitResult.successful, NoiseFitResult.no_zero_crossing
    )
    result = NoiseFitResult.where(ok_alpha | ~has_zero, result, NoiseFitResult.no_positive_lags)
    alpha = jnp.where(ok_alpha, alpha, 1.0 / sample_interval)
    fit = PaperExpCosineFit(
        model=ExponentialCosine(jnp.sqrt(R[0]), alpha, beta),
        first_zero=first_zero,
        lags_used=count,
        result=result,
    )
    return _throw(result, fit, throw)
