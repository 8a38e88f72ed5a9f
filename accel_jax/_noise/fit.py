"""Fits of a noise model in its log-parameters: `fit_autocorrelation_least_squares` (optimistix
Levenberg-Marquardt on R_j, eq. 18) and `fit_maximum_likelihood` (BFGS on the exact Gaussian
likelihood of the discrete-time state-space form `_state_space`, filtered by
`accel_jax._kalman.kalman_filter`; its standardised `innovations` and `log_likelihood` are
public too). Both return a `NoiseFit` with 95 % confidence intervals from the covariance of
the log-parameters.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, ArrayLike

from .._kalman import LinearGaussianModel, kalman_filter
from .models import AbstractNoiseModel
from .record import (
    _LOG_CLIP,
    NoiseFitResult,
    Scalar,
    _sample_interval,
    _throw,
    _validate_record,
)

# Prior variance of a random walk's start, relative to the record's variance: diffuse
# enough that the conditional likelihood p(z_2..N | z_1) is independent of it to ~1e-6.
_DIFFUSE = 1e6

# z-value of two-sided 95 % confidence intervals.
_Z95 = 1.959963984540054


def _to_log(model):
    leaves, treedef = jax.tree_util.tree_flatten(model)
    return jnp.log(jnp.stack([jnp.asarray(leaf) for leaf in leaves])), treedef


def _from_log(log_params, treedef):
    # tree_unflatten bypasses __init__/__check_init__: the clipped exponent is positive.
    values = jnp.exp(jnp.clip(log_params, -_LOG_CLIP, _LOG_CLIP))
    return jax.tree_util.tree_unflatten(treedef, list(values))


class NoiseFit(eqx.Module):
    """A least-squares or maximum-likelihood fit of a noise model.

    **Fields:**

    - `model`: the fitted model (same structure as the initial one).
    - `lower`, `upper`: the same model with every parameter at its 95 % confidence bound,
        exp(log θ̂ ∓ 1.96 se(log θ̂)) (the fit is in log-parameters, so intervals are
        asymmetric and positive).
    - `log_covariance`: covariance of the log-parameters (leaf order of `model`).
    - `objective`: the final objective — log-likelihood for ML (conditional on the first
        sample), sum of squared residuals [u⁴] for least squares.
    - `num_parameters`: number of fitted parameters k.
    - `num_samples`: the number of terms in the objective.
    - `result`: `NoiseFitResult`.
    """

    model: AbstractNoiseModel
    lower: AbstractNoiseModel
    upper: AbstractNoiseModel
    log_covariance: Array
    objective: Scalar
    num_parameters: int = eqx.field(static=True)
    num_samples: int = eqx.field(static=True)
    result: NoiseFitResult

    @property
    def aic(self) -> Scalar:
        """Akaike's criterion −2 log L + 2k (ML fits)."""
        return -2 * self.objective + 2 * self.num_parameters

    @property
    def bic(self) -> Scalar:
        """Schwarz's criterion −2 log L + k ln N (ML fits)."""
        return -2 * self.objective + self.num_parameters * math.log(self.num_samples)


def _bounds(log_params, covariance, treedef):
    se = jnp.sqrt(jnp.clip(jnp.diagonal(covariance), 0.0))
    return _from_log(log_params - _Z95 * se, treedef), _from_log(log_params + _Z95 * se, treedef)


def fit_autocorrelation_least_squares(
    initial: AbstractNoiseModel,
    autocovariance: ArrayLike,
    sample_interval: float,
    *,
    max_steps: int = 256,
    throw: bool = True,
) -> NoiseFit:
    """Nonlinear least squares (18) on the whole autocorrelation: minimise
    Σ_j (R_j − R_model(τ_j))² over the model's log-parameters (optimistix
    Levenberg-Marquardt), j = 0..K.

    `initial` sets the structure and the starting point (e.g. from the paper's rules). The
    intervals use the Gauss-Newton covariance s² (JᵀJ)⁻¹ with s² the residual variance; the
    R_j errors are strongly correlated, so these intervals are optimistic (too narrow) —
    use `fit_maximum_likelihood` for calibrated ones. Jit/vmap-safe.
    """
    _sample_interval("fit_autocorrelation_least_squares", sample_interval)
    if not initial.stationary:
        raise ValueError(
            f"fit_autocorrelation_least_squares: {initial.name} has no autocovariance."
        )
    R = jnp.asarray(autocovariance)
    lags = jnp.arange(R.shape[0], dtype=R.dtype) * sample_interval
    scale = R[0]
    log0, treedef = _to_log(initial)

    def residuals(log_params, _):
        return (_from_log(log_params, treedef).autocovariance(lags) - R) / scale

    solver = optx.LevenbergMarquardt(rtol=1e-10, atol=1e-12)
    sol = optx.least_squares(residuals, solver, log0, max_steps=max_steps, throw=False)
    ok = sol.result == optx.RESULTS.successful
    jac = jax.jacfwd(residuals)(sol.value, None)
    res = residuals(sol.value, None)
    k, n = log0.shape[0], R.shape[0]
    s2 = jnp.sum(res**2) / max(n - k, 1)
    cov = s2 * jnp.linalg.pinv(jac.T @ jac)
    lower, upper = _bounds(sol.value, cov, treedef)
    result = NoiseFitResult.where(ok, NoiseFitResult.successful, NoiseFitResult.not_converged)
    fit = NoiseFit(
        model=_from_log(sol.value, treedef),
        lower=lower,
        upper=upper,
        log_covariance=cov,
        objective=jnp.sum(res**2) * scale**2,
        num_parameters=k,
        num_samples=n,
        result=result,
    )
    return _throw(result, fit, throw)


def _state_space(model: AbstractNoiseModel, sample_interval, record_variance):
    f, q, h, p0, r = model.state_space(sample_interval)
    diffuse = _DIFFUSE * record_variance
    p0 = jnp.where(p0 < 0, diffuse, p0)
    dtype = jnp.result_type(f, record_variance)
    lgm = LinearGaussianModel(
        f.astype(dtype), q.astype(dtype), h.astype(dtype), jnp.reshape(r, (1, 1)).astype(dtype)
    )
    return lgm, p0.astype(dtype)


def innovations(model: AbstractNoiseModel, record: ArrayLike, sample_interval: float):
    """Kalman-filter the mean-removed record under the model.

    **Returns:** (standardised innovations ν_k/√S_k, shape (N,), and per-step
    log-likelihood terms, shape (N,)). Under the right model the standardised innovations
    are white N(0, 1); structure left in them says the model is wrong.
    """
    x = jnp.asarray(record)
    centred = x - jnp.mean(x)
    variance = jnp.mean(centred**2)
    lgm, p0 = _state_space(model, sample_interval, variance)
    out = kalman_filter(lgm, centred, jnp.zeros(lgm.state_size, centred.dtype), p0)
    standardised = out.innovations[:, 0] / jnp.sqrt(out.innovation_covariances[:, 0, 0])
    return standardised, out.log_likelihoods


def log_likelihood(model: AbstractNoiseModel, record: ArrayLike, sample_interval: float) -> Scalar:
    """Exact Gaussian log-likelihood of the mean-removed record, conditional on its first
    sample: log p(x_2..x_N | x_1) (so stationary and random-walk models compare on equal
    terms; the random walk's diffuse start drops out). float64 recommended."""
    _, terms = innovations(model, record, sample_interval)
    return jnp.sum(terms[1:])


_ML_TOLERANCE = 1e-6  # BFGS rtol and atol on the log-parameters


def fit_maximum_likelihood(
    initial: AbstractNoiseModel,
    record: ArrayLike,
    sample_interval: float,
    *,
    max_steps: int = 512,
    throw: bool = True,
) -> NoiseFit:
    """Exact maximum likelihood of a noise model on a record (BFGS on the log-parameters,
    optimistix), with 95 % intervals from the inverse observed information (autodiff
    Hessian of −log L in the log-parameters).

    **Arguments:**

    - `initial`: the structure and starting point (`GaussMarkov`, `NoiseSum`, …).
    - `record`: x, shape (N,), any unit u; the sample mean is removed.
    - `sample_interval`: Δ [s].
    - `max_steps`, `throw`: optimiser budget; raise on failure (else the result code).
      The fit counts as converged when BFGS stops on its step tolerance, or when the point
      it returns is a minimum to that tolerance by a Newton step on the exact Hessian
      (positive definite, every log-parameter within 1e-6 relative of the Newton point).

    **Returns:** `NoiseFit` with `objective` = log p(x_2..N | x_1). Jit/vmap-safe; float64
    recommended. Bad records raise a `ValueError`.
    """
    x = _validate_record("fit_maximum_likelihood", record)
    _sample_interval("fit_maximum_likelihood", sample_interval)
    n = x.shape[0]
    log0, treedef = _to_log(initial)

    def negative(log_params, _):
        return -log_likelihood(_from_log(log_params, treedef), x, sample_interval) / n

    solver = optx.BFGS(rtol=_ML_TOLERANCE, atol=_ML_TOLERANCE)
    sol = optx.minimise(negative, solver, log0, max_steps=max_steps, throw=False)
    hess = jax.hessian(negative)(sol.value, None) * n
    hess = 0.5 * (hess + hess.T)
    cov = jnp.linalg.pinv(hess)
    # BFGS stops on two small consecutive steps. At the optimum of a smooth likelihood its
    # line search can keep rejecting steps whose decrease is below round-off, and it then
    # runs out of steps where it stands (seen: 1 of 6 exp-cosine records, with XLA's
    # backend optimisation off). So the point also counts as converged when it is a
    # minimum by a second test: a positive-definite Hessian and a Newton step smaller than
    # the solver's own tolerance in every log-parameter.
    newton_step = cov @ (jax.grad(negative)(sol.value, None) * n)
    stationary = jnp.all(jnp.linalg.eigvalsh(hess) > 0) & jnp.all(
        jnp.abs(newton_step) <= _ML_TOLERANCE * (1 + jnp.abs(sol.value))
    )
    ok = (sol.result == optx.RESULTS.successful) | stationary
    lower, upper = _bounds(sol.value, cov, treedef)
    result = NoiseFitResult.where(ok, NoiseFitResult.successful, NoiseFitResult.not_converged)
    fit = NoiseFit(
        model=_from_log(sol.value, treedef),
        lower=lower,
        upper=upper,
        log_covariance=cov,
        objective=-negative(sol.value, None) * n,
        num_parameters=log0.shape[0],
        num_samples=n - 1,
        result=result,
    )
    return _throw(result, fit, throw)
