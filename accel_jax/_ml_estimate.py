"""Maximum-likelihood state estimate of the sensing element, its linearisation error and
the paper's compensation (SPEC.md §2, Bezvesilna & Podchashinskyi, eqs. 2-18).

Pickoff samples α*_i = α(t_i) + δ_α(t_i), t_i = i·δ, i = 1..K. The linear model (2)

    α(t) = α_P + α_C sin ωt + α_S cos ωt,   Z = (α_P, α_C, α_S),   α_C = A cos φ, α_S = A sin φ

is linear in Z, so the maximum-likelihood estimate with Gaussian errors of covariance
R = σ² I + R_SE is the generalised least-squares solution

    Ẑ = (Aᵀ R⁻¹ A)⁻¹ Aᵀ R⁻¹ α*          (8)-(9): linear in the samples,
    Ψ = (Aᵀ R⁻¹ A)⁻¹                      (10): its error covariance,

with A = [1, sin ωt_i, cos ωt_i] (7). Note: the paper writes the normal matrix (8) with
column-summed weights w_i = Σ_j w_ji, which equals Aᵀ R⁻¹ A only for a diagonal R; this
module uses Aᵀ R⁻¹ A itself (the likelihood equation (3) exactly).

The linearisation error. For a record of the refined (cubic / sine) motion, first order in
A³, ξt and the frequency error, the samples differ from the linear model by (derived here
from eq. 11; it fixes the signs printed in eq. 17, see `linearisation_error`)

    d_i = (A³/192) sin 3(ωt_i + φ) + A (ω_z − ω) t_i cos(ωt_i + φ) − A ξ t_i sin(ωt_i + φ),

ω_z = ω_d (1 − A²/16) the frequency of the motion and ω the estimator's frequency; the linear
estimator's error is Δ = (Aᵀ R⁻¹ A)⁻¹ Aᵀ R⁻¹ d (eqs. 12-16), Δ_αP its first component (18).
The compensation (patent UA 86005, steps 1-5) evaluates Δ at Â = |(α̂_C, α̂_S)|,
φ̂ = atan2(α̂_S, α̂_C) and subtracts Δ_αP.

Beyond the paper: `fit_sensing_element`, a weighted nonlinear least-squares fit (optimistix
Levenberg–Marquardt through a diffrax solve of the exact sine equation) of α_P and the
initial state, the reference estimator.

Covariances: every estimator takes `covariance`, either shape (K,) — the variances of
independent errors (a diagonal R, solved in O(K)) — or shape (K, K), a full R (Cholesky).
An optional `mask` of shape (K,) (1 = use, 0 = ignore) restricts the estimate to a subset
of the samples with a fixed array shape, so that one compiled function runs over records of
different length K (see `accel_jax._pendulum.record_mask`). Linear solves use lineax.
Precision follows the inputs; the study and tests use float64 (the biases are 1e-10…1e-5 rad).
"""

from __future__ import annotations

import abc

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray

from ._params import _as_float, _concrete
from ._pendulum import Restoring, SensingElement, solve_sensing_element

Scalar = Float[Array, ""]
ScalarLike = Float[ArrayLike, ""]
Series = Float[Array, " n"]
SeriesLike = Float[ArrayLike, " n"]
Matrix = Float[Array, "n n"]
State = Float[Array, " 3"]
StateCovariance = Float[Array, "3 3"]


# --- error models -------------------------------------------------------------------------


def _check_non_negative(owner: str, name: str, value, unit: str) -> None:
    value = _concrete(value)
    if value is not None and (not np.all(np.isfinite(value)) or not np.all(value >= 0)):
        raise ValueError(f"{owner}.{name} must be finite and non-negative, got {value!r} {unit}.")


def _check_positive(owner: str, name: str, value, unit: str) -> None:
    value = _concrete(value)
    if value is not None and (not np.all(np.isfinite(value)) or not np.all(value > 0)):
        raise ValueError(f"{owner}.{name} must be finite and positive, got {value!r} {unit}.")


class AbstractDisturbance(eqx.Module):
    """A zero-mean Gaussian disturbance of the sensing element, R_SE in R = σ² I + R_SE."""

    @abc.abstractmethod
    def covariance(self, ts: SeriesLike) -> Matrix:
        """Covariance E[δ(t_i) δ(t_j)] [rad²] at the sample times `ts` [s], shape (K, K)."""

    @abc.abstractmethod
    def sample(self, ts: SeriesLike, *, key: PRNGKeyArray) -> Series:
        """One realisation δ(t_i) [rad] at `ts` [s] with exactly this covariance."""


class WhiteDisturbance(AbstractDisturbance):
    """Independent errors of standard deviation `std` [rad]: R_SE = std² I."""

    std: Float[Array, ""] = eqx.field(converter=_as_float)

    def __check_init__(self):
        _check_non_negative("WhiteDisturbance", "std", self.std, "rad")

    def covariance(self, ts):
        ts = jnp.asarray(ts)
        return self.std**2 * jnp.eye(ts.shape[0], dtype=ts.dtype)

    def sample(self, ts, *, key):
        ts = jnp.asarray(ts)
        return self.std * jax.random.normal(key, ts.shape, ts.dtype)


class GaussMarkovDisturbance(AbstractDisturbance):
    """First-order Gauss–Markov (exponentially correlated) disturbance.

    R_SE,ij = std² exp(−|t_i − t_j| / correlation_time).

    **Fields:** `std` [rad]; `correlation_time` τ [s] (> 0).
    """

    std: Float[Array, ""] = eqx.field(converter=_as_float)
    correlation_time: Float[Array, ""] = eqx.field(converter=_as_float)

    def __check_init__(self):
        _check_non_negative("GaussMarkovDisturbance", "std", self.std, "rad")
        _check_positive("GaussMarkovDisturbance", "correlation_time", self.correlation_time, "s")

    def covariance(self, ts):
        ts = jnp.asarray(ts)
        lag = jnp.abs(ts[:, None] - ts[None, :])
        return self.std**2 * jnp.exp(-lag / self.correlation_time)

    def sample(self, ts, *, key):
        # Exact discretisation (AR(1) on the actual gaps), stationary start.
        ts = jnp.asarray(ts)
        noise = jax.random.normal(key, ts.shape, ts.dtype)
        rho = jnp.exp(-jnp.diff(ts) / self.correlation_time)

        def step(previous, inputs):
            r, w = inputs
            current = r * previous + jnp.sqrt(1 - r**2) * w
            return current, current

        first = noise[0]
        _, rest = jax.lax.scan(step, first, (rho, noise[1:]))
        return self.std * jnp.concatenate([first[None], rest])


class HarmonicDisturbance(AbstractDisturbance):
    """A harmonic disturbance a sin(Ω t + θ) with uniformly random phase θ.

    R_SE,ij = (a²/2) cos Ω(t_i − t_j) (rank 2: only with σ² > 0 is R invertible). The
    paper names it as the effect of a non-stationary thermal state and of periodic motion
    near the pendulum frequency.

    **Fields:** `amplitude` a [rad]; `angular_frequency` Ω [rad/s].
    """

    amplitude: Float[Array, ""] = eqx.field(converter=_as_float)
    angular_frequency: Float[Array, ""] = eqx.field(converter=_as_float)

    def __check_init__(self):
        _check_non_negative("HarmonicDisturbance", "amplitude", self.amplitude, "rad")
        _check_non_negative(
            "HarmonicDisturbance", "angular_frequency", self.angular_frequency, "rad/s"
        )

    def covariance(self, ts):
        ts = jnp.asarray(ts)
        lag = ts[:, None] - ts[None, :]
        return 0.5 * self.amplitude**2 * jnp.cos(self.angular_frequency * lag)

    def sample(self, ts, *, key):
        ts = jnp.asarray(ts)
        theta = jax.random.uniform(key, (), ts.dtype, 0.0, 2 * jnp.pi)
        return self.amplitude * jnp.sin(self.angular_frequency * ts + theta)


def error_covariance(
    ts: SeriesLike, pickoff_std: ScalarLike, disturbance: AbstractDisturbance | None = None
) -> Matrix:
    """R = σ² I_K + R_SE [rad²], eq. (5): pickoff noise plus sensing-element disturbance.

    **Arguments:** `ts` [s], shape (K,); `pickoff_std` σ [rad]; `disturbance` or `None`.

    **Returns:** R, shape (K, K).
    """
    _check_non_negative("error_covariance", "pickoff_std", pickoff_std, "rad")
    if disturbance is not None and not isinstance(disturbance, AbstractDisturbance):
        raise ValueError(
            f"disturbance must be an AbstractDisturbance or None, got {type(disturbance)!r}."
        )
    ts = jnp.asarray(ts)
    r = jnp.asarray(pickoff_std, ts.dtype) ** 2 * jnp.eye(ts.shape[0], dtype=ts.dtype)
    if disturbance is not None:
        r = r + disturbance.covariance(ts)
    return r


# --- the ML (GLS) estimate ------------------------------------------------------------------


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
    return (
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


class CompensatedEstimate(eqx.Module):
    """Result of the paper's compensation algorithm (steps 1-5).

    **Fields:**

    - `constant_angle`: α̂_P − Δ_αP [rad], the compensated estimate (step 5).
    - `correction`: Δ_αP [rad] (step 4), evaluated at Â, φ̂ from the ML estimate.
    - `estimate`: the uncompensated `MLEstimate` (step 3).
    """

    constant_angle: Scalar
    correction: Scalar
    estimate: MLEstimate


def compensate_linearisation(
    ts: SeriesLike,
    samples: SeriesLike,
    *,
    angular_frequency: ScalarLike,
    element: SensingElement,
    covariance: ArrayLike,
    mask: SeriesLike | None = None,
) -> CompensatedEstimate:
    """The compensation algorithm (patent UA 86005), steps 1-5.

    1) R⁻¹, ω, Δω = ω − ω_d, δ, K are given a priori (`covariance`, `angular_frequency`,
    `element`, `ts`); 2) the samples; 3) Ẑ by eqs. (8)-(9); 4) Δ_αP by eqs. (16)-(18) at
    Â = sqrt(α̂_C² + α̂_S²), φ̂ = atan2(α̂_S, α̂_C); 5) α̂_P ← α̂_P − Δ_αP.

    **Arguments:** as `ml_estimate`, plus `element` (ω0 [rad/s], ξ [1/s]).

    **Returns:** a `CompensatedEstimate` (angles in rad).
    """
    estimate = ml_estimate(ts, samples, angular_frequency, covariance, mask=mask)
    delta = linearisation_error(
        ts,
        estimate.amplitude,
        estimate.phase,
        angular_frequency=angular_frequency,
        element=element,
        covariance=covariance,
        mask=mask,
    )
    return CompensatedEstimate(
        constant_angle=estimate.constant_angle - delta[0],
        correction=delta[0],
        estimate=estimate,
    )


# --- the nonlinear fit ------------------------------------------------------------------------


class NonlinearFit(eqx.Module):
    """Weighted nonlinear least-squares fit of the sensing-element motion.

    **Fields:**

    - `constant_angle`: α̂_P [rad].
    - `initial_angle`: α̂_zm(0) [rad]; `initial_rate`: α̂_zm'(0) [rad/s].
    - `covariance`: Gauss–Newton covariance of (α_P, α_zm(0), α_zm'(0)/ω0) [rad²],
        (Jᵀ R⁻¹ J)⁻¹ at the solution, shape (3, 3).
    - `result`: optimistix's `RESULTS` code; `num_steps`: Levenberg–Marquardt steps.
    """

    constant_angle: Scalar
    initial_angle: Scalar
    initial_rate: Scalar
    covariance: StateCovariance
    result: optx.RESULTS
    num_steps: Array


def _whitener(covariance, mask):
    if covariance.ndim == 1:
        scale = 1 / jnp.sqrt(covariance)
        return lambda r: r * scale
    chol = jnp.linalg.cholesky(covariance)
    return lambda r: jax.scipy.linalg.solve_triangular(chol, r, lower=True)


@eqx.filter_jit
def _fit(
    element,
    ts,
    samples,
    covariance,
    mask,
    guess,
    rtol,
    atol,
    *,
    restoring,
    max_steps,
    throw,
    ode_rtol,
    ode_atol,
    ode_max_steps,
):
    whiten = _whitener(covariance, mask)
    omega0 = element.natural_frequency

    def model(params):
        # Under vmap, optimistix evaluates both branches of its accept/reject choices, so a
        # finished element can carry non-finite trial values; a NaN initial state would make
        # the adaptive solve shrink its step until max_steps and stall the whole batch.
        params = jnp.where(jnp.isfinite(params), params, 0.0)
        alpha_p, angle0, scaled_rate0 = params
        solution = solve_sensing_element(
            element,
            angle0,
            scaled_rate0 * omega0,
            ts,
            restoring=restoring,
            adjoint=diffrax.ForwardMode(),
            rtol=ode_rtol,
            atol=ode_atol,
            max_steps=ode_max_steps,
            throw=False,
        )
        return alpha_p + solution.angle

    def whitened(params):
        r = samples - model(params)
        if mask is not None:
            r = r * mask
        return whiten(r)

    # optimistix's Cauchy test compares the change of each residual with atol + rtol·|r|:
    # multiplying the whitened residuals by a typical σ puts them back in radians, where
    # atol means the same as for the parameters (and the argmin is unchanged).
    variances = covariance if covariance.ndim == 1 else jnp.diagonal(covariance)
    scale = jnp.sqrt(jnp.mean(variances))

    def residuals(params, args):
        return scale * whitened(params)

    solver = optx.LevenbergMarquardt(rtol=rtol, atol=atol)
    solution = optx.least_squares(residuals, solver, guess, max_steps=max_steps, throw=throw)
    params = solution.value
    jac = jax.jacfwd(whitened)(params)
    covariance3 = _inverse3(jac.T @ jac)
    return NonlinearFit(
        constant_angle=params[0],
        initial_angle=params[1],
        initial_rate=params[2] * omega0,
        covariance=covariance3,
        result=solution.result,
        num_steps=solution.stats["num_steps"],
    )


def fit_sensing_element(
    ts: SeriesLike,
    samples: SeriesLike,
    element: SensingElement,
    *,
    covariance: ArrayLike,
    initial_guess: MLEstimate | None = None,
    restoring: Restoring = "sine",
    mask: SeriesLike | None = None,
    rtol: float = 1e-9,
    atol: float = 1e-12,
    max_steps: int = 64,
    ode_rtol: float = 1e-12,
    ode_atol: float = 1e-15,
    ode_max_steps: int = 16384,
    throw: bool = True,
) -> NonlinearFit:
    """Fit α_P and the initial state (α_zm(0), α_zm'(0)) of eq. (1) to pickoff samples.

    Minimises ‖L⁻¹(α* − α_P − α_zm(t; α_zm(0), α_zm'(0)))‖², R = L Lᵀ, with optimistix's
    Levenberg–Marquardt; α_zm is a diffrax solve of eq. (1) (forward-mode sensitivities)
    with the element's ω0 and ξ known a priori (as the paper assumes of ω and ξ). For
    Gaussian errors this is the maximum-likelihood estimate of the nonlinear model: the
    reference against which the linear estimator and its compensation are judged.

    **Arguments:**

    - `ts` [s], `samples` [rad], `covariance` [rad²], `mask`: as in `ml_estimate`
        (ts ≥ 0: the motion is parametrised by its state at t = 0).
    - `element`: ω0 [rad/s], ξ [1/s].
    - `initial_guess`: an `MLEstimate` at ω = ω_d to start from (α_zm(0) = α̂_S,
        α_zm'(0) = ω_d α̂_C − ξ α̂_S); `None` computes it.
    - `restoring`: the model's right-hand side (`"sine"` by default).
    - `rtol`, `atol`: Levenberg–Marquardt tolerances on the parameters [rad];
        `max_steps`: its step limit (Python int).
    - `ode_rtol`, `ode_atol`: tolerances of the inner diffrax solve [rad];
        `ode_max_steps`: its step limit (a failed inner solve gives NaN residuals and a
        failed fit, never a silent number).
    - `throw`: raise if the fit fails; with `False` the code is in `result`.

    **Returns:** a `NonlinearFit`.

    Precision: float64 expected (errors of 1e-12 rad are resolved).

    On the CPU, a vmapped batch of these fits needs jaxlib 0.10.2's XLA:CPU scheduler
    workaround, which `import accel_jax` sets (see `accel_jax._runtime`).
    """
    if not (isinstance(max_steps, int) and max_steps > 0):
        raise ValueError(f"max_steps must be a positive Python int, got {max_steps!r}.")
    omega_d = element.damped_frequency
    if initial_guess is None:
        initial_guess = ml_estimate(ts, samples, omega_d, covariance, mask=mask)
    elif not isinstance(initial_guess, MLEstimate):
        raise ValueError(f"initial_guess must be an MLEstimate or None, got {initial_guess!r}.")
    ts = _check_times(ts)
    covariance_, mask_ = _prepare_covariance(covariance, ts.shape[0], ts.dtype, mask)
    samples = jnp.asarray(samples, ts.dtype)
    if samples.shape != ts.shape:
        raise ValueError(f"samples must have the shape of ts {ts.shape}, got {samples.shape}.")
    z = initial_guess.state
    guess = jnp.stack(
        [z[0], z[2], (omega_d * z[1] - element.decay_rate * z[2]) / element.natural_frequency]
    ).astype(ts.dtype)
    return _fit(
        element,
        ts,
        samples,
        covariance_,
        mask_,
        guess,
        rtol,
        atol,
        restoring=restoring,
        max_steps=max_steps,
        throw=throw,
        ode_rtol=ode_rtol,
        ode_atol=ode_atol,
        ode_max_steps=ode_max_steps,
    )
