"""One-step prediction errors of the step diagnosis's noise model, white + Gauss–Markov
output noise averaged over the fit's blocks (`effects.ColoredNoise`; white alone at
φ = θ = 0), as an ARMA(1,1) recursion evaluated by a blocked first-order filter."""

from __future__ import annotations

import math

import jax.numpy as jnp


def innovation_terms(error, phi, theta, log_first):
    """One-step prediction errors of ARMA(1,1) output noise on the block means
    (n_k − φ n_{k−1} = a_k − θ a_{k−1}: the recursion a_k = e_k − φ e_{k−1} + θ a_{k−1};
    `effects.block_noise`), scaled by σ_a, and ln V₀, V₀ the first block's stationary
    variance over σ_a² (the first error is e₀/√V₀). White noise: φ = θ = ln V₀ = 0.

    The recursion is a first-order linear filter, evaluated in two levels of matrix
    products (`_first_order_filter`): a small program, which matters because every fit
    differentiates it many times over (a parallel scan compiled 4× slower)."""
    first = error[:1] * jnp.exp(-0.5 * log_first)
    b = jnp.concatenate([first, error[1:] - phi * error[:-1]])
    return _first_order_filter(b, theta), log_first


def _first_order_filter(b, theta):
    """a_k = b_k + θ a_{k−1} (a_0 = b_0), |θ| < 1, for a 1-D b of length n.

    In blocks of B samples (B the power of two ≥ √n, at least 16): within each block a
    lower-triangular Toeplitz matrix of θ^0 … θ^{B−1}; across blocks, the values at the
    blocks' ends by a second such matrix in θ^B, carried into each block by θ^{i+1}. Only
    non-negative powers of θ appear (no cancellation); memory O(n), work O(n√n)."""
    n = b.shape[0]
    size = max(16, 1 << math.ceil(math.log2(math.sqrt(n))))
    blocks = -(-n // size)
    rows = jnp.pad(b, (0, blocks * size - n)).reshape(blocks, size)

    def powers(base, count):  # base^0 … base^(count−1), by products (any sign of base)
        rest = jnp.cumprod(jnp.full(count - 1, base, b.dtype))
        return jnp.concatenate([jnp.ones(1, b.dtype), rest])

    def lower_toeplitz(values):
        k = jnp.arange(values.shape[0])
        lag = k[:, None] - k[None, :]
        return jnp.where(lag >= 0, values[jnp.maximum(lag, 0)], 0.0)

    within = powers(theta, size + 1)  # θ^0 … θ^B
    local = rows @ lower_toeplitz(within[:size]).T
    ends = lower_toeplitz(powers(within[size], blocks)) @ local[:, -1]
    carried = jnp.concatenate([jnp.zeros(1, b.dtype), ends[:-1]])
    return (local + within[1:][None, :] * carried[:, None]).reshape(-1)[:n]
