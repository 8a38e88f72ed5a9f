"""Noise models of inertial sensors and their identification (SPEC.md §4).

Chernodarov, Patrikeev & Ivanov identify the noise model of a sensor error from its sample
autocorrelation: the first-order Gauss-Markov (GM) model by a log-linear rule and the
exponential-cosine model by its first zero and a log-linear rule. This module implements

- the sample autocorrelation (11), by FFT;
- the paper's rules (15) and (19)-(21);
- beyond the paper: nonlinear least squares on the autocorrelation (optimistix
  Levenberg-Marquardt), exact maximum likelihood of the discrete-time state-space form (a
  Kalman filter, `accel_jax._kalman.kalman_filter`) with confidence intervals from the
  observed information, and structure selection among white noise, GM, exponential-cosine,
  random walk and their sums by an information criterion, with the residual (standardised
  innovation) autocorrelation and a Ljung-Box test;
- the overlapping Allan deviation and its standard slopes, as a cross-check.

Models are `eqx.Module`s whose fields are positive array leaves (σ [record unit], τ [s],
α [1/s], β [rad/s], q [unit²/s]); records are 1-D arrays sampled every `sample_interval`
seconds, in any unit (g, m/s², rad/s): the parameters carry the record's unit.

Exact discrete forms (no approximation in Δt): GM x_{k+1} = φ x_k + w, φ = e^{−Δ/τ},
var w = σ²(1 − φ²). The exponential-cosine autocovariance σ² e^{−α|τ|} cos βτ is that of the
first component of the 2-D state s_{k+1} = e^{−αΔ} Rot(βΔ) s_k + w, cov w = σ²(1 − e^{−2αΔ}) I
(a damped rotation; the continuous form is ds = (−α I + β J) s dt + σ√(2α) dW). The paper's
second-order shaping filter (17) with b² = α² + β² has the autocorrelation
e^{−α|τ|}(cos βτ + (α/β) sin β|τ|) instead; we realise (16) exactly, which is the model
the paper identifies. Random walk x_{k+1} = x_k + w, var w = q Δ, with a diffuse start.

Precision: float64 for maximum likelihood and structure selection (log-likelihoods of
thousands of samples are compared to within a few units; the random walk's diffuse prior
costs six digits); the autocorrelation and the paper's rules follow the record's dtype.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Float

from ._kalman import LinearGaussianModel, kalman_filter
from ._params import _as_float, _concrete

Scalar = Float[Array, ""]
Series = Float[Array, " n"]

# Clip of the log-parameters during fits: keeps exp() finite (tier 3, never NaN) when a
# component's variance wanders to zero.
_LOG_CLIP = 60.0
# Prior variance of a random walk's start, relative to the record's variance: diffuse
# enough that the conditional likelihood p(z_2..N | z_1) is independent of it to ~1e-6.
_DIFFUSE = 1e6
# z-value of two-sided 95 % confidence intervals.
_Z95 = 1.959963984540054


class NoiseFitResult(eqx.Enumeration):
    """Outcome of a noise-model fit; `successful` or the reason it failed."""

    successful = ""
    no_positive_lags = (
        "No lag j ≥ 1 has a positive normalised autocorrelation r_j: the record looks white; "
        "rule (15)/(21) needs r_j > 0. Use a white-noise model or more samples per τ."
    )
    no_zero_crossing = (
        "The autocorrelation has no zero within the lags given, so β = π/(2 τ_β) (19) is "
        "undefined: ask for more lags or use the Gauss-Markov model."
    )
    not_converged = "The optimiser did not converge within max_steps."


# ---------------------------------------------------------------------------------------
# Record validation and the sample autocorrelation (11)


def _validate_record(name: str, record, *, max_lag: int | None = None, min_samples: int = 8):
    record = jnp.asarray(record)
    if record.ndim != 1:
        raise ValueError(
            f"{name}: the record must be 1-D (one channel), got shape {record.shape}; vmap "
            f"over a batch of records instead."
        )
    n = record.shape[0]
    if max_lag is not None:
        if int(max_lag) < 1:
            raise ValueError(f"{name}: max_lag must be ≥ 1, got {max_lag!r}.")
        if n < 2 * (int(max_lag) + 1):
            raise ValueError(
                f"{name}: a record of {n} samples is too short for {max_lag} lags; at least "
                f"2·(max_lag + 1) = {2 * (int(max_lag) + 1)} samples are needed (R_k is "
                "averaged over N − k products, which must stay at least half the record)."
            )
    if n < min_samples:
        raise ValueError(f"{name}: the record has {n} samples; at least {min_samples} are needed.")
    if not jnp.issubdtype(record.dtype, jnp.floating):
        record = record.astype(jnp.result_type(float))
    concrete = _concrete(record)
    if concrete is not None:
        if not np.all(np.isfinite(concrete)):
            bad = int(np.argmax(~np.isfinite(concrete)))
            raise ValueError(
                f"{name}: sample {bad} of the record is {float(concrete[bad])}; the record must be "
                "finite (drop or interpolate missing samples first)."
            )
        if np.ptp(concrete) == 0:
            raise ValueError(
                f"{name}: the record is constant ({float(concrete[0])} in every sample): its "
                "autocorrelation is zero and no noise model can be identified. Check that the "
                "channel is connected and not saturated or quantised to one level."
            )
    else:
        record = eqx.error_if(
            record, ~jnp.all(jnp.isfinite(record)), f"{name}: the record contains NaN or inf."
        )
        record = eqx.error_if(
            record, jnp.max(record) == jnp.min(record), f"{name}: the record is constant."
        )
    return record


def _sample_interval(name: str, sample_interval):
    concrete = _concrete(sample_interval)
    if concrete is not None and not (
        np.ndim(concrete) == 0 and np.isfinite(concrete) and concrete > 0
    ):
        raise ValueError(
            f"{name}: sample_interval must be a positive number, got "
            f"{np.asarray(concrete).tolist()} s."
        )
    return sample_interval


def autocorrelation(record: ArrayLike, max_lag: int) -> Series:
    """Sample autocovariance R_k of eq. (11), k = 0..max_lag, by FFT.

        R_k = 1/(N − k) Σ_{i=1}^{N−k} (x_i − m)(x_{i+k} − m),   m = mean of the record

    (the unbiased-by-count estimator the paper uses; the mean is the record's own). Zero-
    padding to at least 2N makes the FFT's circular correlation the linear one.

    **Arguments:**

    - `record`: x, shape (N,), any unit u; N ≥ 2(max_lag + 1).
    - `max_lag`: the largest lag k (static int).

    **Returns:** R, shape (max_lag + 1,), in u². Jit/vmap/grad-safe; precision follows the
    record (float32 rounding is ~1e-7 R_0). Bad input (too short, constant, NaN) raises a
    `ValueError` (concrete record) or a runtime error (traced record).
    """
    x = _validate_record("autocorrelation", record, max_lag=max_lag)
    n = x.shape[0]
    size = 1 << (2 * n - 1).bit_length()
    centred = x - jnp.mean(x)
    spectrum = jnp.fft.rfft(centred, n=size)
    raw = jnp.fft.irfft(spectrum * jnp.conj(spectrum), n=size)[: max_lag + 1]
    return raw / (n - jnp.arange(max_lag + 1, dtype=x.dtype))


# ---------------------------------------------------------------------------------------
# Noise models


def _positive_fields(self, units: dict[str, str]):
    for name, unit in units.items():
        value = _concrete(getattr(self, name))
        if value is not None and not (np.all(np.isfinite(value)) and np.all(value > 0)):
            raise ValueError(
                f"{type(self).__name__}.{name} must be positive and finite, got "
                f"{np.asarray(value).tolist()} {unit}."
            )


class AbstractNoiseModel(eqx.Module):
    """A scalar noise process observed every Δ seconds.

    Concrete models give `state_space(Δ)` = (F, Q, H, P0, r): a latent linear Gaussian state
    with stationary (or diffuse) prior P0 and additive white observation variance r; and,
    where stationary, `autocovariance(τ)`. All array fields are positive parameters.
    """

    def state_space(self, sample_interval) -> tuple[Array, Array, Array, Array, Array]:
        raise NotImplementedError

    def autocovariance(self, lag_times) -> Array:
        raise NotImplementedError

    @property
    def name(self) -> str:
        raise NotImplementedError

    @property
    def stationary(self) -> bool:
        return True


class WhiteNoise(AbstractNoiseModel):
    """White noise, R(τ) = σ² δ_{τ,0} (per sample). **Fields:** `sigma`: σ [record unit]."""

    sigma: Scalar = eqx.field(converter=_as_float)

    def __check_init__(self):
        _positive_fields(self, {"sigma": "(record unit)"})

    @property
    def name(self) -> str:
        return "white"

    def state_space(self, sample_interval):
        zero = jnp.zeros((1, 1), self.sigma.dtype)
        return zero, zero, zero, zero, self.sigma**2

    def autocovariance(self, lag_times):
        lag_times = jnp.asarray(lag_times)
        return jnp.where(lag_times == 0, self.sigma**2, 0.0)


class GaussMarkov(AbstractNoiseModel):
    """First-order Gauss-Markov process (7)-(8): Δ' = −Δ/τ_c + σ √(2/τ_c) w.

    R(τ) = σ² e^{−|τ|/τ_c}; α = 1/τ_c. **Fields:** `sigma`: σ [record unit];
    `correlation_time`: τ_c [s].
    """

    sigma: Scalar = eqx.field(converter=_as_float)
    correlation_time: Scalar = eqx.field(converter=_as_float)

    def __check_init__(self):
        _positive_fields(self, {"sigma": "(record unit)", "correlation_time": "s"})

    @property
    def name(self) -> str:
        return "gauss_markov"

    def state_space(self, sample_interval):
        phi = jnp.exp(-sample_interval / self.correlation_time)
        var = self.sigma**2
        f = jnp.reshape(phi, (1, 1))
        q = jnp.reshape(var * -jnp.expm1(-2 * sample_interval / self.correlation_time), (1, 1))
        h = jnp.ones((1, 1), f.dtype)
        return f, q, h, jnp.reshape(var, (1, 1)), jnp.zeros((), f.dtype)

    def autocovariance(self, lag_times):
        return self.sigma**2 * jnp.exp(-jnp.abs(jnp.asarray(lag_times)) / self.correlation_time)


class ExponentialCosine(AbstractNoiseModel):
    """Exponential-cosine process (16): R(τ) = σ² e^{−α|τ|} cos βτ.

    Realised exactly as the first component of a damped rotation (see the module
    docstring). **Fields:** `sigma`: σ [record unit]; `decay_rate`: α [1/s];
    `angular_frequency`: β [rad/s].
    """

    sigma: Scalar = eqx.field(converter=_as_float)
    decay_rate: Scalar = eqx.field(converter=_as_float)
    angular_frequency: Scalar = eqx.field(converter=_as_float)

    def __check_init__(self):
        _positive_fields(
            self, {"sigma": "(record unit)", "decay_rate": "1/s", "angular_frequency": "rad/s"}
        )

    @property
    def name(self) -> str:
        return "exp_cosine"

    def state_space(self, sample_interval):
        decay = jnp.exp(-self.decay_rate * sample_interval)
        angle = self.angular_frequency * sample_interval
        c, s = jnp.cos(angle), jnp.sin(angle)
        f = decay * jnp.array([[c, -s], [s, c]])
        var = self.sigma**2
        eye = jnp.eye(2, dtype=f.dtype)
        q = var * -jnp.expm1(-2 * self.decay_rate * sample_interval) * eye
        h = jnp.array([[1.0, 0.0]], dtype=f.dtype)
        return f, q, h, var * eye, jnp.zeros((), f.dtype)

    def autocovariance(self, lag_times):
        lag_times = jnp.asarray(lag_times)
        return (
            self.sigma**2
            * jnp.exp(-self.decay_rate * jnp.abs(lag_times))
            * jnp.cos(self.angular_frequency * lag_times)
        )


class RandomWalk(AbstractNoiseModel):
    """Random walk x' = √q w (rate random walk for a gyro, velocity random walk for an
    accelerometer's integral): var(x_{k+1} − x_k) = q Δ. Not stationary (no
    autocovariance); its start is diffuse. **Fields:** `intensity`: q [record unit²/s]."""

    intensity: Scalar = eqx.field(converter=_as_float)

    def __check_init__(self):
        _positive_fields(self, {"intensity": "(record unit)²/s"})

    @property
    def name(self) -> str:
        return "random_walk"

    @property
    def stationary(self) -> bool:
        return False

    def state_space(self, sample_interval):
        one = jnp.ones((1, 1), self.intensity.dtype)
        # P0 = −1 flags "diffuse": `_state_space` replaces it by _DIFFUSE × var(record).
        return one, self.intensity * sample_interval * one, one, -one, jnp.zeros((), one.dtype)

    def autocovariance(self, lag_times):
        raise ValueError("RandomWalk is not stationary: it has no autocovariance R(τ).")


class NoiseSum(AbstractNoiseModel):
    """Sum of independent noise processes (block-diagonal state, summed white variance).
    **Fields:** `components`: a tuple of models (not nested sums)."""

    components: tuple

    def __check_init__(self):
        if len(self.components) < 2:
            raise ValueError(f"NoiseSum needs at least two components, got {len(self.components)}.")
        for c in self.components:
            if not isinstance(c, AbstractNoiseModel) or isinstance(c, NoiseSum):
                raise ValueError(f"NoiseSum components must be single noise models, got {c!r}.")

    @property
    def name(self) -> str:
        return "+".join(c.name for c in self.components)

    @property
    def stationary(self) -> bool:
        return all(c.stationary for c in self.components)

    def state_space(self, sample_interval):
        import jax.scipy.linalg as jsl

        parts = [c.state_space(sample_interval) for c in self.components]
        f = jsl.block_diag(*[p[0] for p in parts])
        q = jsl.block_diag(*[p[1] for p in parts])
        h = jnp.concatenate([p[2] for p in parts], axis=1)
        p0 = jsl.block_diag(*[p[3] for p in parts])
        r = sum(p[4] for p in parts)
        return f, q, h, p0, r

    def autocovariance(self, lag_times):
        return sum(c.autocovariance(lag_times) for c in self.components)


def simulate_noise(
    model: AbstractNoiseModel, sample_interval: float, num_samples: int, *, key: Array
) -> Series:
    """One record of `num_samples` samples of the model, exactly in discrete time
    (stationary start; a random walk starts at 0). Jit/vmap-safe over `key`."""
    if int(num_samples) < 1:
        raise ValueError(f"simulate_noise: num_samples must be ≥ 1, got {num_samples!r}.")
    _sample_interval("simulate_noise", sample_interval)
    f, q, h, p0, r = model.state_space(sample_interval)
    p0 = jnp.where(p0 < 0, 0.0, p0)
    n = f.shape[0]
    dtype = f.dtype

    def root(cov):
        vals, vecs = jnp.linalg.eigh(0.5 * (cov + cov.T))
        return vecs * jnp.sqrt(jnp.clip(vals, 0.0))

    k0, kw, kv = jax.random.split(key, 3)
    x0 = root(p0) @ jax.random.normal(k0, (n,), dtype)
    w = jax.random.normal(kw, (num_samples, n), dtype) @ root(q).T
    v = jnp.sqrt(r) * jax.random.normal(kv, (num_samples,), dtype)

    def step(x, w_k):
        return f @ x + w_k, x

    _, states = jax.lax.scan(step, x0, w)
    return states @ h[0] + v


# ---------------------------------------------------------------------------------------
# The paper's rules (15) and (19)-(21)


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


def _leading_positive(r, floor=0.0):
    """Mask of lags 1..K before the first r_j ≤ floor (ln r_j must exist: floor ≥ 0)."""
    positive = r[1:] > floor
    return jnp.concatenate([jnp.zeros(1, bool), jnp.cumprod(positive).astype(bool)])


def _throw(result, value, throw):
    if throw:
        value = result.error_if(value, result != NoiseFitResult.successful)
    return value


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


# ---------------------------------------------------------------------------------------
# Fits in log-parameters: least squares on R, and maximum likelihood


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


# ---------------------------------------------------------------------------------------
# Structure selection


DEFAULT_STRUCTURES: tuple[str, ...] = (
    "white",
    "gauss_markov",
    "exp_cosine",
    "random_walk",
    "white+gauss_markov",
    "white+random_walk",
    "gauss_markov+random_walk",
    "white+exp_cosine",
)
"""Candidate structures `select_noise_model` compares by default."""

_COMPONENTS = ("white", "gauss_markov", "exp_cosine", "random_walk")


def initial_model(structure: str, record: ArrayLike, sample_interval: float) -> AbstractNoiseModel:
    """A starting point for `fit_maximum_likelihood` of a structure ("white",
    "gauss_markov", "exp_cosine", "random_walk" or sums joined by "+"), from the record's
    variance, its increments and the paper's rules on its autocorrelation (lags up to N/8).
    Components of a sum share the variance equally. A host-side helper (NumPy on a concrete
    record), not jittable; `select_noise_model` calls it once per structure."""
    names = structure.split("+")
    unknown = [name for name in names if name not in _COMPONENTS]
    if unknown or len(set(names)) != len(names):
        raise ValueError(
            f"initial_model: unknown or repeated component(s) in {structure!r}; use "
            f"{_COMPONENTS} joined by '+'."
        )
    x = np.asarray(_validate_record("initial_model", record), dtype=float)
    dt = float(sample_interval)
    n = x.shape[0]
    max_lag = max(2, min(n // 8, 2000))
    R = np.asarray(autocorrelation(x, max_lag))
    share = float(R[0]) / len(names)
    r = R / R[0]
    positive = np.cumprod(r[1:] > 0).astype(bool)
    upto = max(1, int(np.sum(positive & (r[1:] > np.exp(-1)))))
    lags = np.arange(1, upto + 1) * dt
    alpha = -np.sum(np.log(np.clip(r[1 : upto + 1], 1e-12, None))) / np.sum(lags)
    tau = float(np.clip(1 / alpha if alpha > 0 else 10 * dt, dt, n * dt))
    first_zero = int(np.argmax(r[1:] <= 0)) + 1 if np.any(r[1:] <= 0) else max_lag
    beta = 0.5 * np.pi / (first_zero * dt)
    increments = np.var(np.diff(x)) / dt
    models = []
    for name in names:
        if name == "white":
            models.append(WhiteNoise(np.sqrt(share)))
        elif name == "gauss_markov":
            models.append(GaussMarkov(np.sqrt(share), tau))
        elif name == "exp_cosine":
            models.append(ExponentialCosine(np.sqrt(share), 1 / tau, beta))
        else:
            models.append(RandomWalk(max(increments / len(names), 1e-300) * 0.1))
    dtype = jnp.result_type(float)
    models = [jax.tree_util.tree_map(lambda v: jnp.asarray(v, dtype), m) for m in models]
    return models[0] if len(models) == 1 else NoiseSum(tuple(models))


def ljung_box(standardised: ArrayLike, num_lags: int, num_parameters: int = 0):
    """Ljung-Box portmanteau test of whiteness on standardised residuals.

    Q = N(N + 2) Σ_{k=1}^{L} ρ_k²/(N − k) ~ χ²(L − p) under whiteness.

    **Returns:** (ρ_1..ρ_L, Q, p-value).
    """
    e = jnp.asarray(standardised)
    n = e.shape[0]
    R = autocorrelation(e, num_lags)
    rho = R[1:] / R[0]
    k = jnp.arange(1, num_lags + 1)
    q = n * (n + 2) * jnp.sum(rho**2 / (n - k))
    dof = max(num_lags - num_parameters, 1)
    p_value = jax.scipy.special.gammaincc(dof / 2, q / 2)
    return rho, q, p_value


class StructureSelection(eqx.Module):
    """Result of `select_noise_model`.

    **Fields:**

    - `chosen`: the structure with the smallest criterion (e.g. "white+gauss_markov").
    - `model`: its fitted model; `fit`: its `NoiseFit` (with confidence bounds).
    - `table`: one dict per structure, best first: structure, num_parameters,
        log_likelihood, aic, bic, delta (criterion − best), converged, ljung_box_p,
        parameters (name → value, with SI units in the name).
    - `fits`: structure → `NoiseFit`.
    - `residual_autocorrelation`: structure → ρ_1..ρ_L of its standardised innovations.
    - `criterion`: "bic" or "aic".
    """

    chosen: str = eqx.field(static=True)
    model: AbstractNoiseModel
    fit: NoiseFit
    table: list = eqx.field(static=True)
    fits: dict
    residual_autocorrelation: dict
    criterion: str = eqx.field(static=True)


def model_parameters(model: AbstractNoiseModel) -> dict[str, float]:
    """Plain floats keyed by component and parameter name, units in the key."""
    units = {
        "sigma": "",
        "correlation_time": "_s",
        "decay_rate": "_per_s",
        "angular_frequency": "_rad_per_s",
        "intensity": "_unit2_per_s",
    }
    components = model.components if isinstance(model, NoiseSum) else (model,)
    out = {}
    for c in components:
        for field, suffix in units.items():
            if hasattr(c, field):
                out[f"{c.name}.{field}{suffix}"] = float(getattr(c, field))
    return out


def select_noise_model(
    record: ArrayLike,
    sample_interval: float,
    *,
    structures: Sequence[str] = DEFAULT_STRUCTURES,
    criterion: str = "bic",
    residual_lags: int = 20,
    max_steps: int = 256,
) -> StructureSelection:
    """Choose the noise structure of a record by maximum likelihood and an information
    criterion — the paper's structure identification, made quantitative.

    Every candidate structure is fitted by `fit_maximum_likelihood` from `initial_model`;
    the smallest BIC (default; or AIC) wins. Fits that ran out of optimiser steps are flagged
    (`converged` False) and still compete: that happens when a redundant parameter runs to
    a boundary, where the criterion's penalty already rules the structure out. The
    standardised innovations of each fit are tested for whiteness (Ljung-Box over
    `residual_lags` lags): a wrong structure leaves correlation in them — the paper's
    warning that a wrong model makes the filter diverge.

    **Arguments:**

    - `record`: x, shape (N,), e.g. a static accelerometer record [g]; N ≥ 4·residual_lags.
    - `sample_interval`: Δ [s].
    - `structures`: candidates, from "white", "gauss_markov", "exp_cosine", "random_walk"
        and their sums joined by "+".
    - `criterion`: "bic" or "aic".

    **Returns:** `StructureSelection`. Not jitted as a whole (one compiled fit per
    structure); float64 recommended (a float32 log-likelihood of 10⁴ samples is only good to
    ~0.1). Bad records (NaN, constant, too short) raise `ValueError`.
    """
    if criterion not in ("bic", "aic"):
        raise ValueError(
            f"select_noise_model: criterion must be 'bic' or 'aic', got {criterion!r}."
        )
    if not structures:
        raise ValueError("select_noise_model: no candidate structures given.")
    x = _validate_record("select_noise_model", record, max_lag=residual_lags)
    _sample_interval("select_noise_model", sample_interval)
    dt = float(sample_interval)
    fits, rhos, rows = {}, {}, []
    for structure in structures:
        init = initial_model(structure, x, dt)
        fit = _fit_ml_jit(init, x, dt, max_steps)
        standardised, _ = _innovations_jit(fit.model, x, dt)
        rho, q, p = ljung_box(standardised[1:], residual_lags, fit.num_parameters)
        fits[structure] = fit
        rhos[structure] = rho
        rows.append(
            {
                "structure": structure,
                "num_parameters": fit.num_parameters,
                "log_likelihood": float(fit.objective),
                "aic": float(fit.aic),
                "bic": float(fit.bic),
                "converged": bool(fit.result == NoiseFitResult.successful),
                "ljung_box_Q": float(q),
                "ljung_box_p": float(p),
                "parameters": model_parameters(fit.model),
            }
        )
    # A fit that ran out of steps is usually a structure with a redundant parameter
    # running to a boundary (a Gauss-Markov τ → 0 on white data, β → 0 of an
    # exponential-cosine on Gauss-Markov data): its likelihood is then that of the simpler
    # structure and the criterion's penalty rules it out, so it still competes (flagged).
    usable = [row for row in rows if np.isfinite(row[criterion])]
    if not usable:
        raise ValueError(
            "select_noise_model: no candidate structure gave a finite likelihood; check the "
            "record's units and sampling."
        )
    best = min(usable, key=lambda row: row[criterion])
    for row in rows:
        row["delta"] = row[criterion] - best[criterion]
    rows.sort(key=lambda row: row[criterion] if np.isfinite(row[criterion]) else np.inf)
    chosen = best["structure"]
    return StructureSelection(
        chosen=chosen,
        model=fits[chosen].model,
        fit=fits[chosen],
        table=rows,
        fits=fits,
        residual_autocorrelation=rhos,
        criterion=criterion,
    )


@eqx.filter_jit
def _fit_ml_jit(init, x, dt, max_steps):
    return fit_maximum_likelihood(init, x, dt, max_steps=max_steps, throw=False)


@eqx.filter_jit
def _innovations_jit(model, x, dt):
    return innovations(model, x, dt)


# ---------------------------------------------------------------------------------------
# Allan deviation


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
