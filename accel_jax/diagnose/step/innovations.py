"""One-step prediction errors of the step diagnosis's noise models on the fit's block means:
white + Gauss–Markov output noise (`effects.ColoredNoise`; white alone at φ = θ = 0) as an
ARMA(1,1) recursion evaluated by a blocked first-order filter (`innovation_terms`), and
white output noise + a Gauss–Markov moment inside the loop (`effects.MomentNoise`) by the
Kalman filter on the loop's states carried through each block (`moment_noise_terms`; the
package's `accel_jax._kalman.kalman_filter` to round-off, in two passes)."""

from __future__ import annotations

import math
from functools import partial

import jax
import jax.numpy as jnp
from jax.custom_derivatives import SymbolicZero

from ..._kalman import _matmul
from ..._servo import time_constant
from ..._simulate.matrix import expm_minus_identity
from ..._simulate.sequence import loop_system


def innovation_terms(error, phi, theta, log_first, train=None):
    """One-step prediction errors of ARMA(1,1) output noise on the block means
    (n_k − φ n_{k−1} = a_k − θ a_{k−1}: the recursion a_k = e_k − φ e_{k−1} + θ a_{k−1};
    `effects.block_noise`), scaled by σ_a, and ln V₀, V₀ the first block's stationary
    variance over σ_a² (the first error is e₀/√V₀). White noise: φ = θ = ln V₀ = 0.

    With `train` (n,) (1 on the training part's blocks, 0 on the held-out part's;
    default every block: the whole record, one segment), the
    training part's own errors: a held-out block is a gap whose error is never used (its
    innovation is 0), and each training segment starts afresh from the stationary state
    (its first error e/√V₀, ln V₀ counted once per segment): the segments' likelihoods
    taken as independent, exact when a gap is long against the noise's correlation time
    and otherwise leaving out the little the segment before says about the next. Without
    it the held-out part's errors, at the training optimum where its own nuisances are not
    fitted, ran into the training innovations after each gap, where the solver fitted
    them: the held-out data steered the training fit. For white noise the two are the
    same.

    The recursion is a first-order linear filter, evaluated in two levels of matrix
    products (`_first_order_filter`): a small program, which matters because every fit
    differentiates it many times over (a parallel scan compiled 4× slower). The segments'
    restarts are the unbroken filter's output less each restart's carry decayed to the
    block, θ^(k−r+1)·u_{r−1} (exact: the gap's inputs are zero)."""
    scale = jnp.exp(-0.5 * log_first)
    on = jnp.ones(error.shape, bool) if train is None else train > 0
    restart = on & ~jnp.concatenate([jnp.zeros(1, bool), on[:-1]])
    e = jnp.where(on, error, 0.0)
    previous = jnp.concatenate([jnp.zeros(1, e.dtype), e[:-1]])
    b = jnp.where(on, jnp.where(restart, e * scale, e - phi * previous), 0.0)
    u = _first_order_filter(b, theta)
    k = jnp.arange(error.shape[0])
    start = jax.lax.cummax(jnp.where(restart, k, 0))  # each block's segment's restart
    carry = jnp.where(start > 0, u[jnp.maximum(start - 1, 0)], 0.0)
    a = u - jnp.power(theta, (k - start + 1).astype(u.dtype)) * carry
    return jnp.where(on, a, 0.0), log_first * jnp.sum(restart)


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


MIN_BLOCK_COEFFICIENT = 1e-3
"""|φ_block| of a moment noise is kept at least this (its rate −ln|φ|/(mΔ) stays finite)."""


def moment_noise_model(params, dt, m, max_block: int, ratio, phi_block):
    """The block-mean model of white output noise (variance 1 per sample) plus a
    Gauss–Markov moment inside the loop (`effects.MomentNoise`), exactly: (Gᵐ, Σ, P, S_b).

    The moment M̃ (in the scaled loop's units, `_simulate.sequence.loop_system`) is a
    first-order Gauss–Markov process of rate β = −ln|φ_block|/(mΔ) and variance
    `ratio`/g², g the loop's static output per unit moment (so `ratio` is the moment part's
    low-frequency output variance over the white variance). The loop's four states and M̃
    form x' = A x + noise; `P` solves A P + P Aᵀ + Q_c = 0 (Q_c = 2βσ² at M̃; stationary),
    and one sample's map is Φ = e^{AΔ} with process covariance P − Φ P Φᵀ (exact for a
    stationary process; written with F = Φ − I for precision at small AΔ). An ideal lag's
    dummy state (a zero row of A: neither driven nor read) is given a stable pole so that
    the Lyapunov equation is regular; it changes nothing else.

    One block: the state z = [x; s] with s accumulating C x/m over the block's m samples
    (Gm = Gᵐ, G = [[Φ, 0], [C/m, 1]], from s = 0) and the noise Σ = Σ_{i<m} Gⁱ Q_w Gⁱᵀ;
    the block mean is s_m plus the white part's mean (variance 1/m). `S_b` is the loop
    part's stationary block-mean variance and `S_s` one sample's (per unit white
    variance)."""
    a_full, _, c_full = loop_system(params, jnp.ones_like(params.moment_of_inertia))
    a = a_full[:5, :5]
    c = c_full[:5]
    dtype = a.dtype
    idle = jnp.all(a[:4] == 0, axis=1)
    diagonal = jnp.where(idle, -1.0 / time_constant(params), 0.0)
    a = a.at[jnp.arange(4), jnp.arange(4)].add(diagonal)
    phi = jnp.clip(jnp.abs(phi_block), MIN_BLOCK_COEFFICIENT, 1.0 - 1e-12)
    rate = -jnp.log(phi) / (m * dt)
    a = a.at[4, 4].set(-rate)
    static = -c[:4] @ jnp.linalg.solve(a[:4, :4], a[:4, 4])
    variance = ratio / static**2
    q_c = jnp.zeros((5, 5), dtype).at[4, 4].set(2 * rate * variance)
    eye = jnp.eye(5, dtype=dtype)
    kron = jnp.kron(eye, a) + jnp.kron(a, eye)
    p = jnp.linalg.solve(kron, -q_c.reshape(-1)).reshape(5, 5)
    p = 0.5 * (p + p.T)
    f = expm_minus_identity(a * dt)
    q = -(f @ p + p @ f.T + f @ p @ f.T)
    g = jnp.zeros((6, 6), dtype).at[:5, :5].set(eye + f).at[5, :5].set(c / m).at[5, 5].set(1.0)
    q_w = jnp.zeros((6, 6), dtype).at[:5, :5].set(0.5 * (q + q.T))

    def step(j, carry):
        power, total = carry
        on = j < m
        total = jnp.where(on, total + power @ q_w @ power.T, total)
        return jnp.where(on, g @ power, power), total

    power, total = jax.lax.fori_loop(
        0, max_block, step, (jnp.eye(6, dtype=dtype), jnp.zeros((6, 6), dtype))
    )
    lead = power[:, :5]
    joint = lead @ p @ lead.T + total
    return power, total, p, joint[5, 5], c @ p @ c


def moment_noise_terms(
    error, params, dt, m, max_block: int, ratio, phi_block, mask, observed=None
):
    """One-step prediction errors of block means under white output noise plus a
    Gauss–Markov moment inside the loop (`moment_noise_model`), by a Kalman filter from
    the stationary state: (ã, ln V) with ã_k = a_k·√(S_∞/S_k), a_k the innovation, S_k its
    variance (per unit white variance; S_∞ the last block's) and ln V = Σ_k mask_k
    ln(S_k/S_∞) over the blocks `mask` counts, so that −½[n ln(Σ ã²/n) + ln V] is the
    exact profiled log-likelihood, as for `innovation_terms`. With `ratio` 0 it is white
    noise exactly (S_k = 1/m, ã = e).

    With `observed` (n,) (0 on a held-out block): the training part's own errors, the
    held-out blocks gaps the filter predicts across (`kalman_filter`'s `observed`: the
    exact likelihood of the observed blocks); S_∞ is then the least S_k observed (the
    filter's steady state; any reference gives the same profiled ln L) and a gap's ã is 0.
    """
    a, s = moment_kalman(error, params, dt, m, max_block, ratio, phi_block, observed)
    if observed is None:
        last = s[-1]
        return a * jnp.sqrt(last / s), jnp.sum(mask * jnp.log(s / last))
    seen = observed > 0
    last = jnp.min(jnp.where(seen, s, jnp.inf))
    a = jnp.where(seen, a * jnp.sqrt(last / s), 0.0)
    return a, jnp.sum(mask * jnp.log(s / last))


def moment_kalman(error, params, dt, m, max_block: int, ratio, phi_block, observed=None):
    """The innovations a_k and their variances S_k (per unit white variance) of
    `moment_noise_terms`'s Kalman filter: the package's `kalman_filter` on the state
    ξ_k = [x at the end of block k; s_k, block k's loop part], ξ_{k+1} = [Gᵐ]₍:,:5₎ ξ_k[:5] +
    w_k (w ~ N(0, Σ)), observed as s_k + the white part's mean (variance 1/m); its prior is
    the stationary joint of the first block (P through one block, plus Σ). `observed`
    (n,), optional: 0 where a block is a gap (predicted across, not used).

    Computed in two passes: the covariances, gains K_k and S_k, which depend on the model
    alone (`_moment_gains`: the filter's covariance recursion written for an observation of
    one state), then the state means over the record's errors with those gains; the
    one-pass `kalman_filter`'s values to round-off (tests/test_diagnose_step_moment_noise.py).
    The first pass is differentiated only in the directions its few model parameters move
    (`_moment_gains`'s derivative), not in every direction of a fit's parameter vector."""
    dtype = error.dtype
    n = error.shape[0]
    seen = jnp.ones(n, bool) if observed is None else observed > 0
    lead, gains, s = _moment_gains(max_block, n, dtype, params, dt, m, ratio, phi_block, seen)
    transition = jnp.zeros((6, 6), dtype).at[:, :5].set(lead)

    def step(mean, inputs):
        e_k, seen_k, gain = inputs
        predicted = mean[5]
        innovation = jnp.where(seen_k | jnp.isfinite(e_k), e_k, predicted) - predicted
        mean_post = mean + jnp.where(seen_k, gain, 0.0) * innovation
        return _matmul(transition, mean_post[:, None])[:, 0], innovation

    _, a = jax.lax.scan(step, jnp.zeros(6, dtype), (error, seen, gains))
    return a, s


def _moment_gains_of(max_block: int, n: int, dtype, params, dt, m, ratio, phi_block, seen):
    """([Gᵐ]₍:,:5₎, the gains K_k (n, 6), S_k (n,)) of `moment_kalman`'s filter: its
    covariance recursion alone (the covariances do not depend on the data). The observation
    reads the last state, so S_k = P⁻₅₅ + 1/m, K_k = P⁻₍:,5₎/S_k, and the update
    (I − K eᵀ) P⁻ (I − K eᵀ)ᵀ + K Kᵀ/m (Joseph's form) is P⁻ − K P⁻₍5,:₎, as one
    outer product; the prediction Gᵐ P Gᵐᵀ + Σ reads P's first five rows and columns only
    (the last column of the transition is zero)."""
    power, total, p0, _, _ = moment_noise_model(params, dt, m, max_block, ratio, phi_block)
    lead = power[:, :5].astype(dtype)
    total = total.astype(dtype)
    prior = lead @ p0.astype(dtype) @ lead.T + total
    r = jnp.asarray(1.0 / m, dtype)

    def step(cov, seen_k):
        row = cov[5]
        s = row[5] + r
        gain = row / s
        post = jnp.where(seen_k, cov - gain[:, None] * row[None, :], cov)[:5, :5]
        post = 0.5 * (post + post.T)
        predicted = _matmul(_matmul(lead, post), lead.T) + total
        return 0.5 * (predicted + predicted.T), (gain, s)

    _, (gains, s) = jax.lax.scan(step, prior, seen)
    return lead, gains, s


@partial(jax.custom_jvp, nondiff_argnums=(0, 1, 2))
def _moment_gains(max_block: int, n: int, dtype, params, dt, m, ratio, phi_block, seen):
    """`_moment_gains_of`, with a derivative that differentiates the filter's covariance
    pass once per model parameter that moves (a handful: the device's refit z, the moment's
    ratio and φ), then applies that Jacobian to any number of directions. A fit's forward
    Jacobian (`fit.dense_jacobian`) pushes every direction of w (20 or more) through it;
    directions in which nothing here moves cost nothing."""
    return _moment_gains_of(max_block, n, dtype, params, dt, m, ratio, phi_block, seen)


def _moment_gains_jvp(max_block, n, dtype, primals, tangents):
    # (`symbolic_zeros`: an argument that does not depend on what is differentiated has a
    # `SymbolicZero` tangent, so the inner Jacobian is taken only in the others.)
    leaves, tree = jax.tree.flatten(primals)
    moved = jax.tree.leaves(tangents, is_leaf=lambda t: isinstance(t, SymbolicZero))
    live = [
        i for i, (t, v) in enumerate(zip(moved, leaves, strict=True))
        if not isinstance(t, SymbolicZero) and jnp.issubdtype(jnp.result_type(v), jnp.inexact)
    ]

    def of(*values):
        full = list(leaves)
        for i, v in zip(live, values, strict=True):
            full[i] = v
        return _moment_gains_of(max_block, n, dtype, *jax.tree.unflatten(tree, full))

    if not live:
        out = of()
        return out, jax.tree.map(jnp.zeros_like, out)
    out, jacobians = jax.jacfwd(lambda *v: (of(*v),) * 2, argnums=tuple(range(len(live))),
                                has_aux=True)(*(leaves[i] for i in live))[::-1]
    directions = [jnp.asarray(moved[i], leaves[i].dtype) for i in live]

    def apply(jac):
        return sum(
            jnp.tensordot(j, d, axes=jnp.ndim(d)) for j, d in zip(jac, directions, strict=True)
        )

    return out, tuple(apply(jac) for jac in jacobians)


_moment_gains.defjvp(_moment_gains_jvp, symbolic_zeros=True)
