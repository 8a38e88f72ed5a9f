"""The maximum-likelihood (GLS) state estimate of the linearised sensing element and its
linearisation error (docs/models.md §2, eqs. 11-17)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._params import _concrete
from .._pendulum import SensingElement
from .disturbances import Scalar, ScalarLike, Series, SeriesLike, State, StateCovariance


def state_basis(ts: SeriesLike, angular_frequency: ScalarLike) -> Float[Array, "n 3"]:
    """The design matrix A of eq. (7): rows (1, sin ωt_i, cos ωt_i), shape (K, 3)."""
    ts = jnp.asarray(ts)
    phase = angular_frequency * ts
    return jnp.stack([jnp.ones_like(ts), jnp.sin(phase), jnp.cos(phase)], axis=-1)


class MLEstimate(eqx.Module):
    """Maximum-likelihood (GLS) estimate of Z = (α_P, α_C, α_S) and its covariance.

    **Fields:**

    - `state`: Ẑ = (α̂_P, α̂_C, α̂_S) [rad], shape (3,), eq. (8)-(9).
    - `covariance`: Ψ = (Aᵀ R⁻¹ A)⁻¹ [rad²], shape (3, 3), eq. (10).
    - `gain`: the weights ι of eq. (9), G = Ψ Aᵀ R⁻¹, shape (3, K): Ẑ = G α*.
    """

    state: State
    covariance: StateCovariance
    gain: Float[Array, "3 n"]

    @property
    def constant_angle(self) -> Scalar:
        """α̂_P [rad]."""
        return self.state[0]

    @property
    def amplitude(self) -> Scalar:
        """Â = sqrt(α̂_C² + α̂_S²) [rad] (step 4 of the compensation)."""
        return jnp.hypot(self.state[1], self.state[2])

    @property
    def phase(self) -> Scalar:
        """φ̂ [rad]: the paper's arcsin / π − arcsin rule of step 4, written as atan2."""
        return jnp.arctan2(self.state[2], self.state[1])


def _prepare_covariance(covariance, n: int, dtype, mask):
    covariance = jnp.asarray(covariance, dtype)
    if covariance.shape not in ((n,), (n, n)):
        raise ValueError(
            f"covariance must have shape ({n},) (variances, rad²) or ({n}, {n}) (matrix, "
            f"rad²) for {n} samples, got {covariance.shape}."
        )
    concrete = _concrete(covariance)
    if concrete is not None:
        diagonal = concrete if concrete.ndim == 1 else np.diagonal(concrete)
        if not np.all(np.isfinite(concrete)) or not np.all(diagonal > 0):
            bad = diagonal[~(diagonal > 0)] if np.all(np.isfinite(concrete)) else "non-finite"
            raise ValueError(
                "covariance must be finite with positive variances (rad²); got variances "
                f"{bad!r}. Add the pickoff noise σ² I (σ > 0): a purely harmonic or "
                "zero R_SE is singular."
            )
    if mask is None:
        return covariance, None
    mask = jnp.asarray(mask, dtype)
    if mask.shape != (n,):
        raise ValueError(f"mask must have shape ({n},), got {mask.shape}.")
    # Masked-out samples get unit variance and no correlation with the rest, and their rows
    # of A and of the data are zeroed: they drop out of Aᵀ R⁻¹ A and Aᵀ R⁻¹ α* exactly.
    if covariance.ndim == 1:
        covariance = jnp.where(mask > 0, covariance, 1.0)
    else:
        covariance = mask[:, None] * covariance * mask[None, :] + jnp.diag(1 - mask)
    return covariance, mask


def _operator(covariance):
    if covariance.ndim == 1:
        return lx.DiagonalLinearOperator(covariance), lx.Diagonal()
    operator = lx.MatrixLinearOperator(covariance, lx.positive_semidefinite_tag)
    return operator, lx.Cholesky()


def _solve_columns(operator, solver, columns):
    # R⁻¹ applied to each column of `columns` (K, m); the factorisation is shared.
    state = solver.init(operator, {})
    return jax.vmap(
        lambda b: lx.linear_solve(operator, b, solver, state=state).value,
        in_axes=1,
        out_axes=1,
    )(columns)


def _normal_solve(normal, rhs):
    operator = lx.MatrixLinearOperator(normal, lx.positive_semidefinite_tag)
    return lx.linear_solve(operator, rhs, lx.Cholesky()).value


def _inverse3(normal):
    operator = lx.MatrixLinearOperator(normal, lx.positive_semidefinite_tag)
    solver = lx.Cholesky()
    state = solver.init(operator, {})
    eye = jnp.eye(normal.shape[0], dtype=normal.dtype)
    inverse = jax.vmap(lambda b: lx.linear_solve(operator, b, solver, state=state).value)(eye)
    return 0.5 * (inverse + inverse.T)


def _check_times(ts):
    ts = jnp.asarray(ts)
    if not jnp.issubdtype(ts.dtype, jnp.floating):
        ts = ts.astype(jnp.result_type(float))
    if ts.ndim != 1 or ts.shape[0] < 3:
        raise ValueError(
            f"ts must be 1-D with at least 3 samples (3 unknowns), got shape {ts.shape}."
        )
    concrete = _concrete(ts)
    if concrete is not None and not np.all(np.isfinite(concrete)):
        raise ValueError("ts must be finite [s].")
    return ts


def _gls_parts(ts, angular_frequency, covariance, mask):
    ts = _check_times(ts)
    omega = _concrete(angular_frequency)
    if omega is not None and (not np.all(np.isfinite(omega)) or not np.all(omega > 0)):
        raise ValueError(f"angular_frequency must be finite and positive, got {omega!r} rad/s.")
    covariance, mask = _prepare_covariance(covariance, ts.shape[0], ts.dtype, mask)
    basis = state_basis(ts, angular_frequency)
    if mask is not None:
        basis = basis * mask[:, None]
    operator, solver = _operator(covariance)
    weighted = _solve_columns(operator, solver, basis)  # R⁻¹ A, (K, 3)
    normal = basis.T @ weighted  # Aᵀ R⁻¹ A, eq. (8)'s B
    normal = 0.5 * (normal + normal.T)
    return ts, mask, basis, weighted, normal


def ml_estimate(
    ts: SeriesLike,
    samples: SeriesLike,
    angular_frequency: ScalarLike,
    covariance: ArrayLike,
    *,
    mask: SeriesLike | None = None,
) -> MLEstimate:
    """Maximum-likelihood estimate of Z = (α_P, α_C, α_S) from pickoff samples, eqs. (8)-(10).

    **Arguments:**

    - `ts`: sample times t_i [s], shape (K,).
    - `samples`: α*_i [rad], shape (K,).
    - `angular_frequency`: ω [rad/s] of the model (2), known a priori (the paper's ω_zm).
    - `covariance`: R [rad²], shape (K,) (independent errors) or (K, K); see
        `error_covariance`.
    - `mask`: optional (K,) weights in {0, 1} selecting the samples used.

    **Returns:** an `MLEstimate` (state, covariance Ψ, gain G with Ẑ = G α*).

    Solves with lineax (Cholesky of R and of the 3×3 normal matrix); jit/vmap/grad-safe.
    """
    ts, mask, basis, weighted, normal = _gls_parts(ts, angular_frequency, covariance, mask)
    samples = jnp.asarray(samples, ts.dtype)
    if samples.shape != ts.shape:
        raise ValueError(f"samples must have the shape of ts {ts.shape}, got {samples.shape}.")
    if mask is not None:
        samples = samples * mask
    psi = _inverse3(normal)
    gain = psi @ weighted.T  # (3, K), eq. (9)'s ι
    state = _normal_solve(normal, weighted.T @ samples)
    return MLEstimate(state=state, covariance=psi, gain=gain)


def column_sum_estimate(
    ts: SeriesLike,
    samples: SeriesLike,
    angular_frequency: ScalarLike,
    covariance: ArrayLike,
) -> MLEstimate:
    """The paper's estimate as printed, eq. (8): B_α Ẑ = C_α with each sample weighted by
    the column sum w_i = Σ_j w_ji of R⁻¹ = [w_ji] (the weights of (8) and of (16)).

    B_α = Aᵀ diag(w) A and C_α = Aᵀ diag(w) α*. For a diagonal R this is `ml_estimate`
    exactly; for a correlated R it is another linear estimator, Ẑ = G α* with
    G = (Aᵀ W A)⁻¹ Aᵀ W, W = diag(w) — unbiased for the linear model (G A = I), but not the
    maximum-likelihood one, so its variance is at least GLS's (Gauss–Markov theorem). The
    returned `covariance` is that estimator's true error covariance G R Gᵀ, not (Aᵀ W A)⁻¹.
    w = R⁻¹ 1 (R is symmetric), which may have negative entries for a correlated R; the
    3×3 system is solved by LU.

    **Arguments:** as `ml_estimate` (no mask).

    **Returns:** an `MLEstimate` (state, covariance G R Gᵀ, gain G).
    """
    ts, _, basis, weighted, _ = _gls_parts(ts, angular_frequency, covariance, None)
    samples = jnp.asarray(samples, ts.dtype)
    if samples.shape != ts.shape:
        raise ValueError(f"samples must have the shape of ts {ts.shape}, got {samples.shape}.")
    column_sums = weighted[:, 0]  # R⁻¹ A's first column: R⁻¹ 1, A's first column being 1
    weighted_basis = basis * column_sums[:, None]  # W A
    normal = basis.T @ weighted_basis  # B_α
    operator = lx.MatrixLinearOperator(normal)
    solver = lx.LU()
    state_ = solver.init(operator, {})
    gain = jax.vmap(
        lambda b: lx.linear_solve(operator, b, solver, state=state_).value, in_axes=1, out_axes=1
    )(weighted_basis.T)  # (3, K)
    r = jnp.asarray(covariance, ts.dtype)
    r_gain = r[:, None] * gain.T if r.ndim == 1 else r @ gain.T
    error_covariance_ = gain @ r_gain
    return MLEstimate(
        state=gain @ samples,
        covariance=0.5 * (error_covariance_ + error_covariance_.T),
        gain=gain,
    )


def linearisation_residual(
    ts: SeriesLike,
    amplitude: ScalarLike,
    phase: ScalarLike,
    *,
    angular_frequency: ScalarLike,
    element: SensingElement,
) -> Series:
    """The neglected terms d_i [rad]: refined motion minus the linear model, first order.

    d_i = (A³/192) sin 3(ωt_i + φ) + A (ω_z − ω) t_i cos(ωt_i + φ) − A ξ t_i sin(ωt_i + φ),
    with ω_z = ω_d (1 − A²/16) and ω the estimator's frequency. In the paper's notation
    (ω = ω0 + Δω): A(ω_z − ω) = −(A³/16) ω0 − A Δω (to first order), i.e. the terms of
    eq. (17) — but with the frequency and damping terms of the opposite sign to the
    third harmonic, as eq. (15) and a direct expansion of eq. (11) give; eq. (17) as printed
    has all four terms positive.
    """
    ts = jnp.asarray(ts)
    omega = angular_frequency
    psi = omega * ts + phase
    offset = element.damped_frequency * (1 - amplitude**2 / 16) - omega
    return jnp.asarray(  # (an array already: ts is one; the arguments may be NumPy's)
        amplitude**3 / 192 * jnp.sin(3 * psi)
        + amplitude * offset * ts * jnp.cos(psi)
        - amplitude * element.decay_rate * ts * jnp.sin(psi)
    )


def linearisation_error(
    ts: SeriesLike,
    amplitude: ScalarLike,
    phase: ScalarLike,
    *,
    angular_frequency: ScalarLike,
    element: SensingElement,
    covariance: ArrayLike,
    mask: SeriesLike | None = None,
) -> State:
    """The paper's analytic linearisation error Δ = (Δ_αP, Δ_αC, Δ_αS) [rad], eqs. (12)-(18).

    Solves B_Δ Δ = C_Δ (16) with B_Δ = Aᵀ R⁻¹ A and C_Δ = Aᵀ R⁻¹ d, d from
    `linearisation_residual` (17) — lineax in place of Cramer's rule (18), same solution.
    Δ_αP predicts (estimate − truth) of the linear ML estimator for a noise-free record of
    the refined motion of amplitude A and phase φ; first order in A³, ξ T_c and
    A² ω0 T_c/16 (T_c = K δ the record length), so it breaks down once A² ω0 T_c/16 or ξ T_c
    is no longer small, and it omits the O(A⁵) terms.

    **Arguments:** `ts` [s]; `amplitude` A [rad]; `phase` φ [rad]; `angular_frequency` ω of
    the estimator [rad/s]; `element` (ω0 [rad/s], ξ [1/s]); `covariance` R [rad²];
    `mask` as in `ml_estimate`.

    **Returns:** Δ, shape (3,), in rad.
    """
    ts, mask, _, weighted, normal = _gls_parts(ts, angular_frequency, covariance, mask)
    residual = linearisation_residual(
        ts, amplitude, phase, angular_frequency=angular_frequency, element=element
    )
    if mask is not None:
        residual = residual * mask
    return _normal_solve(normal, weighted.T @ residual)
