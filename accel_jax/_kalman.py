"""The linear Kalman filter, the Rauch–Tung–Striebel smoother, simulation of a linear
Gaussian model and the consistency statistics (NEES, NIS); the single-channel INS test bed
they are used on is `_kalman_ins` (docs/models.md §4).

The filter is written here as a `jax.lax.scan` (about forty lines) rather than taken from
dynamax: dynamax pulls in tfp-nightly and a web-server stack with our pinned JAX, and the
study needs the Joseph-form update, per-step log-likelihood terms (for the exact maximum
likelihood of `accel_jax._noise`) and NEES/NIS, which are simplest to own. The filter is
jit/vmap/grad-safe; vmap it over Monte Carlo runs (or use `accel_jax.sweep`).

Precision: the filter follows the dtype of its inputs (float64 for the INS model, whose
variances span many decades: `_kalman_ins`).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._params import _as_float, _concrete, _shown

Scalar = Float[Array, ""]
Vector = Float[Array, " n"]
Matrix = Float[Array, "n n"]



def _check_matrix(name: str, value, shape: tuple[int, ...]):
    if jnp.shape(value) != shape:
        raise ValueError(
            f"LinearGaussianModel.{name} must have shape {shape}, got {jnp.shape(value)}."
        )
    concrete = _concrete(value)
    if concrete is not None and not np.all(np.isfinite(concrete)):
        raise ValueError(f"LinearGaussianModel.{name} must be finite, got {concrete!r}.")


class LinearGaussianModel(eqx.Module):
    """A discrete-time linear Gaussian state-space model.

        x_{k+1} = F x_k + w_k,   w_k ~ N(0, Q);      z_k = H x_k + v_k,   v_k ~ N(0, R).

    **Fields:** (units are those of the state and observation)

    - `transition`: F, shape (n, n).
    - `process_covariance`: Q, shape (n, n), symmetric positive semi-definite.
    - `observation`: H, shape (m, n).
    - `observation_covariance`: R, shape (m, m), symmetric positive semi-definite.
    """

    transition: Array = eqx.field(converter=_as_float)
    process_covariance: Array = eqx.field(converter=_as_float)
    observation: Array = eqx.field(converter=_as_float)
    observation_covariance: Array = eqx.field(converter=_as_float)

    def __check_init__(self):
        if jnp.ndim(self.transition) != 2 or jnp.ndim(self.observation) != 2:
            raise ValueError(
                "LinearGaussianModel: transition and observation must be 2-D matrices, got "
                f"shapes {jnp.shape(self.transition)} and {jnp.shape(self.observation)}; vmap "
                "over a batch of models instead of stacking them."
            )
        n = jnp.shape(self.transition)[0]
        m = jnp.shape(self.observation)[0]
        _check_matrix("transition", self.transition, (n, n))
        _check_matrix("process_covariance", self.process_covariance, (n, n))
        _check_matrix("observation", self.observation, (m, n))
        _check_matrix("observation_covariance", self.observation_covariance, (m, m))
        for name in ("process_covariance", "observation_covariance"):
            concrete = _concrete(getattr(self, name))
            if concrete is not None and np.any(np.diag(concrete) < 0):
                raise ValueError(
                    f"LinearGaussianModel.{name} must have a non-negative diagonal (it is a "
                    f"covariance), got diagonal {np.diag(concrete)!r}."
                )

    @property
    def state_size(self) -> int:
        return jnp.shape(self.transition)[0]

    @property
    def observation_size(self) -> int:
        return jnp.shape(self.observation)[0]


class FilterOutput(eqx.Module):
    """Result of `kalman_filter` over T observations (n states, m observations).

    **Fields:**

    - `filtered_means`: x̂_{k|k}, shape (T, n).
    - `filtered_covariances`: P_{k|k}, shape (T, n, n).
    - `predicted_means`: x̂_{k|k−1}, shape (T, n) (the prior at k = 0).
    - `predicted_covariances`: P_{k|k−1}, shape (T, n, n).
    - `innovations`: ν_k = z_k − H x̂_{k|k−1}, shape (T, m).
    - `innovation_covariances`: S_k = H P_{k|k−1} Hᵀ + R, shape (T, m, m).
    - `log_likelihoods`: log N(ν_k; 0, S_k) per step, shape (T,); their sum is the exact
        log-likelihood of the observations under the model and the prior.
    """

    filtered_means: Array
    filtered_covariances: Array
    predicted_means: Array
    predicted_covariances: Array
    innovations: Array
    innovation_covariances: Array
    log_likelihoods: Array

    @property
    def log_likelihood(self) -> Scalar:
        return jnp.sum(self.log_likelihoods)


def _symmetrise(matrix):
    return 0.5 * (matrix + matrix.T)


SMALL_PRODUCT = 16
"""Inner dimensions up to this are multiplied by `_matmul` as outer-product sums."""


def _matmul(a, b):
    """a @ b of small matrices (2-D) as a sum of outer products of a's columns and b's rows
    where the inner dimension is at most `SMALL_PRODUCT`, else `a @ b`. Under vmap with a
    model per batch member (a sweep over models, the in-flight loop's own models per log),
    XLA:CPU (jaxlib 0.10.2) runs a batched `dot` of 6 × 6 matrices one small matrix at a
    time, and a multiply-and-reduce through its YNNPACK fusion, both several times slower
    per step than this elementwise form, which it fuses into vectorised loops over the batch
    (docs/performance.md). The same product to round-off (another summation order)."""
    if a.shape[1] > SMALL_PRODUCT:
        return a @ b
    out = a[:, 0, None] * b[None, 0, :]
    for j in range(1, a.shape[1]):
        out = out + a[:, j, None] * b[None, j, :]
    return out


def kalman_filter(
    model: LinearGaussianModel,
    observations: ArrayLike,
    initial_mean: ArrayLike,
    initial_covariance: ArrayLike,
    observed: ArrayLike | None = None,
) -> FilterOutput:
    """Run the Kalman filter over a record, as one `jax.lax.scan`.

    The prior N(initial_mean, initial_covariance) is the state at the first observation
    (the filter updates with z_0 first, then predicts). The covariance update is the Joseph
    form P⁺ = (I − K H) P (I − K H)ᵀ + K R Kᵀ, which stays symmetric positive semi-definite
    under rounding; S_k is factorised by Cholesky.

    **Arguments:**

    - `model`: a `LinearGaussianModel` (n states, m observations).
    - `observations`: z, shape (T, m) or (T,) when m = 1.
    - `initial_mean`: x̂_{0|−1}, shape (n,).
    - `initial_covariance`: P_{0|−1}, shape (n, n).
    - `observed`: optional, shape (T,): False where z_k is missing (a gap). There the
        filter only predicts (no update: the gain is zero, so x̂_{k|k} = x̂_{k|k−1} and
        P_{k|k} = P_{k|k−1}), ν_k and S_k are the prediction's error (0 where z_k is not
        finite: a missing value may be NaN) and variance, and the step adds nothing to
        the log-likelihood. Default: every step observed.

    **Returns:** a `FilterOutput`. Precision follows the inputs (float64 recommended for
    models whose variances span many decades, such as the INS channel).
    """
    z = jnp.asarray(observations)
    n, m = model.state_size, model.observation_size
    if z.ndim == 1 and m == 1:
        z = z[:, None]
    if z.ndim != 2 or z.shape[1] != m:
        raise ValueError(
            f"kalman_filter: observations must have shape (T, {m}), got {jnp.shape(observations)}."
        )
    if z.shape[0] < 1:
        raise ValueError("kalman_filter: the record has no observations.")
    mean0 = jnp.asarray(initial_mean)
    cov0 = jnp.asarray(initial_covariance)
    if mean0.shape != (n,) or cov0.shape != (n, n):
        raise ValueError(
            f"kalman_filter: initial_mean must have shape ({n},) and initial_covariance "
            f"({n}, {n}), got {mean0.shape} and {cov0.shape}."
        )
    dtype = jnp.result_type(z, mean0, cov0, model.transition)
    F, Q = model.transition.astype(dtype), model.process_covariance.astype(dtype)
    H, R = model.observation.astype(dtype), model.observation_covariance.astype(dtype)
    eye = jnp.eye(n, dtype=dtype)
    log_2pi = jnp.log(2 * jnp.pi).astype(dtype)

    if observed is None:
        seen = jnp.ones(z.shape[0], bool)
    else:
        seen = jnp.asarray(observed).astype(bool)
        if seen.shape != (z.shape[0],):
            raise ValueError(
                f"kalman_filter: observed must have shape ({z.shape[0]},), got {seen.shape}."
            )
    concrete = _concrete(z)
    if concrete is not None:
        seen_now = _concrete(seen)
        check = concrete if seen_now is None else concrete[seen_now]
        if not np.all(np.isfinite(check)):
            index = np.flatnonzero(~np.all(np.isfinite(concrete), axis=1))
            if seen_now is not None:
                index = index[seen_now[index]]
            bad = int(index[0])
            raise ValueError(
                f"kalman_filter: observation {bad} is {_shown(concrete[bad])}; the record "
                "must be finite where it is observed (mark missing samples in `observed`)."
            )

    def step(carry, inputs):
        z_k, seen_k = inputs
        mean, cov = carry
        predicted = _matmul(H, mean[:, None])[:, 0]
        z_k = jnp.where(seen_k | jnp.isfinite(z_k), z_k, predicted)
        innovation = z_k - predicted
        h_cov = _matmul(H, cov)
        s = _symmetrise(_matmul(h_cov, H.T) + R)
        if m == 1:
            # Scalar observation (every model here): plain division, no LAPACK call per
            # step — batched 1×1 Cholesky factorisations dominate the run time otherwise.
            gain = h_cov.T / s[0, 0]
            log_lik = -0.5 * (log_2pi + jnp.log(s[0, 0]) + innovation[0] ** 2 / s[0, 0])
        else:
            chol = jnp.linalg.cholesky(s)
            gain = jsl.cho_solve((chol, True), h_cov).T
            white = jsl.solve_triangular(chol, innovation, lower=True)
            log_lik = -0.5 * (m * log_2pi + jnp.dot(white, white)) - jnp.sum(
                jnp.log(jnp.diagonal(chol))
            )
        gain = jnp.where(seen_k, gain, 0.0)
        log_lik = jnp.where(seen_k, log_lik, 0.0)
        i_kh = eye - _matmul(gain, H)
        cov_post = _symmetrise(
            _matmul(_matmul(i_kh, cov), i_kh.T) + _matmul(_matmul(gain, R), gain.T)
        )
        mean_post = mean + _matmul(gain, innovation[:, None])[:, 0]
        mean_next = _matmul(F, mean_post[:, None])[:, 0]
        cov_next = _symmetrise(_matmul(_matmul(F, cov_post), F.T) + Q)
        out = (mean_post, cov_post, mean, cov, innovation, s, log_lik)
        return (mean_next, cov_next), out

    _, outs = jax.lax.scan(step, (mean0.astype(dtype), cov0.astype(dtype)), (z, seen))
    return FilterOutput(*outs)


class SmootherOutput(eqx.Module):
    """Result of `rts_smoother` over T observations (n states).

    **Fields:**

    - `smoothed_means`: x̂_{k|T}, the mean of the state given the whole record, shape (T, n).
    - `smoothed_covariances`: P_{k|T}, shape (T, n, n).
    """

    smoothed_means: Array
    smoothed_covariances: Array


def rts_smoother(model: LinearGaussianModel, output: FilterOutput) -> SmootherOutput:
    """The Rauch–Tung–Striebel fixed-interval smoother: x̂_{k|T}, P_{k|T} from the filter's
    pass over the whole record (a flight log), as one backward `jax.lax.scan`.

    x̂_{k|T} = x̂_{k|k} + C_k (x̂_{k+1|T} − x̂_{k+1|k}), C_k = P_{k|k} Fᵀ P_{k+1|k}⁻¹,
    P_{k|T} = P_{k|k} + C_k (P_{k+1|T} − P_{k+1|k}) C_kᵀ; at k = T − 1 the smoothed
    estimate is the filtered one. The gain C_k comes from a Cholesky solve with P_{k+1|k}.
    The result is the exact Gaussian conditional mean and covariance of each state given
    all observations (tests/test_kalman.py checks it against dense conditioning).

    **Arguments:**

    - `model`: the `LinearGaussianModel` the filter ran with.
    - `output`: `kalman_filter(model, ...)`'s `FilterOutput`.

    **Returns:** a `SmootherOutput`.
    """
    F = model.transition.astype(output.filtered_means.dtype)
    means, covs = output.filtered_means, output.filtered_covariances
    # P_{k+1|k} and x̂_{k+1|k} for k < T − 1 are the filter's predictions at k + 1.
    next_pred_means = output.predicted_means[1:]
    next_pred_covs = output.predicted_covariances[1:]

    def step(carry, inputs):
        smooth_mean, smooth_cov = carry
        mean, cov, pred_mean, pred_cov = inputs
        chol = jnp.linalg.cholesky(_symmetrise(pred_cov))
        gain = jsl.cho_solve((chol, True), _matmul(F, cov)).T  # P F^T P_pred^{-1}
        new_mean = mean + _matmul(gain, (smooth_mean - pred_mean)[:, None])[:, 0]
        new_cov = _symmetrise(cov + _matmul(_matmul(gain, smooth_cov - pred_cov), gain.T))
        return (new_mean, new_cov), (new_mean, new_cov)

    last = (means[-1], covs[-1])
    _, (early_means, early_covs) = jax.lax.scan(
        step, last, (means[:-1], covs[:-1], next_pred_means, next_pred_covs), reverse=True
    )
    return SmootherOutput(
        jnp.concatenate([early_means, means[-1:]]), jnp.concatenate([early_covs, covs[-1:]])
    )


def simulate_linear_gaussian(
    model: LinearGaussianModel,
    initial_mean: ArrayLike,
    initial_covariance: ArrayLike,
    num_steps: int,
    *,
    key: Array,
) -> tuple[Array, Array]:
    """Draw one trajectory of the model: states (T, n) and observations (T, m).

    x_0 ~ N(initial_mean, initial_covariance); covariances are factorised with an
    eigen-decomposition (clipped at zero) so semi-definite ones (e.g. Q of the INS model,
    which has zero rows for the kinematic states when discretised crudely) are allowed.
    """
    if int(num_steps) < 1:
        raise ValueError(f"simulate_linear_gaussian: num_steps must be ≥ 1, got {num_steps!r}.")
    n, m = model.state_size, model.observation_size
    dtype = model.transition.dtype

    def root(cov):
        vals, vecs = jnp.linalg.eigh(_symmetrise(jnp.asarray(cov, dtype)))
        return vecs * jnp.sqrt(jnp.clip(vals, 0.0))

    k0, kw, kv = jax.random.split(key, 3)
    x0 = jnp.asarray(initial_mean, dtype) + root(initial_covariance) @ jax.random.normal(
        k0, (n,), dtype
    )
    w = jax.random.normal(kw, (num_steps, n), dtype) @ root(model.process_covariance).T
    v = jax.random.normal(kv, (num_steps, m), dtype) @ root(model.observation_covariance).T

    def step(x, w_k):
        return model.transition @ x + w_k, x

    _, states = jax.lax.scan(step, x0, w)
    observations = states @ model.observation.T + v
    return states, observations


def normalised_estimation_error_squared(errors: ArrayLike, covariances: ArrayLike) -> Array:
    """NEES ε_k = e_kᵀ P_k⁻¹ e_k for errors (T, n) and covariances (T, n, n); χ²(n) per step
    when the filter is consistent."""
    errors = jnp.asarray(errors)
    chol = jnp.linalg.cholesky(jnp.asarray(covariances))
    white = jax.vmap(lambda c, e: jsl.solve_triangular(c, e, lower=True))(chol, errors)
    return jnp.sum(white**2, axis=-1)


def normalised_innovation_squared(output: FilterOutput) -> Array:
    """NIS ν_kᵀ S_k⁻¹ ν_k per step, shape (T,); χ²(m) per step when the filter is consistent."""
    return normalised_estimation_error_squared(output.innovations, output.innovation_covariances)
