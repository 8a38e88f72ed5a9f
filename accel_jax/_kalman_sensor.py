"""The in-flight filter's sensor-error model and the paper's rules on a window of its
estimates (docs/models.md §4.4): `SensorErrorModel` (R(τ) = σ² e^{−α|τ|} cos βτ as a damped
rotation, β = 0 the first-order Gauss–Markov model), the six-state INS channel built from
two of them (`online_channel`), a masked window's autocovariance (11), and both structures'
parameters from an autocovariance by rules (15) and (19)–(21) (`structure_candidates`).
`_kalman_online.identify_in_flight` runs the loop that uses them. float64 (the caller's
setting).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike

from ._kalman import LinearGaussianModel, Scalar
from ._kalman_ins import EARTH_RADIUS, _discretise, _generator
from ._noise.paper import fit_exp_cosine_paper, fit_gauss_markov_paper
from ._noise.record import NoiseFitResult
from ._params import _as_float, _concrete
from ._static import STANDARD_GRAVITY


class SensorErrorModel(eqx.Module):
    """One sensor's error in the in-flight filter: R(τ) = σ² e^{−α|τ|} cos βτ, β = 0 being
    the first-order Gauss–Markov model (τ_c = 1/α).

    **Fields:** `sigma` σ [sensor unit]; `decay_rate` α [1/s]; `angular_frequency` β
    [rad/s] (≥ 0).
    """

    sigma: Scalar = eqx.field(converter=_as_float)
    decay_rate: Scalar = eqx.field(converter=_as_float)
    angular_frequency: Scalar = eqx.field(converter=_as_float, default=0.0)

    def __check_init__(self):
        for name, low in (("sigma", 0.0), ("decay_rate", 0.0)):
            value = _concrete(getattr(self, name))
            if value is not None and not (np.all(np.isfinite(value)) and np.all(value > low)):
                raise ValueError(f"SensorErrorModel.{name} must be positive, got {value!r}.")
        beta = _concrete(self.angular_frequency)
        if beta is not None and not (np.all(np.isfinite(beta)) and np.all(beta >= 0)):
            raise ValueError(f"SensorErrorModel.angular_frequency must be ≥ 0, got {beta!r}.")

    @classmethod
    def gauss_markov(cls, sigma, correlation_time) -> SensorErrorModel:
        return cls(sigma, 1.0 / jnp.asarray(correlation_time, float), 0.0)

    def autocovariance(self, lag_times) -> Array:
        lag_times = jnp.abs(jnp.asarray(lag_times))
        return (
            self.sigma**2
            * jnp.exp(-self.decay_rate * lag_times)
            * jnp.cos(self.angular_frequency * lag_times)
        )

    def generator(self) -> tuple[Array, Array, Array, Array]:
        """(A_s, D_s, H_s, q) of the two-state block: −αI + βJ, 2ασ² I, [1, 0], 0."""
        alpha, beta = self.decay_rate, self.angular_frequency
        a = jnp.stack([jnp.stack([-alpha, -beta]), jnp.stack([beta, -alpha])])
        d = 2 * alpha * self.sigma**2 * jnp.eye(2, dtype=a.dtype)
        h = jnp.array([[1.0, 0.0]], dtype=a.dtype)
        return a, d, h, jnp.zeros((), a.dtype)

    def transition(self, lag_time) -> Array:
        """Φ_s(τ) = e^{−ατ} [[cos βτ, −sin βτ], [sin βτ, cos βτ]]."""
        c, s = jnp.cos(self.angular_frequency * lag_time), jnp.sin(self.angular_frequency * lag_time)
        return jnp.exp(-self.decay_rate * lag_time) * jnp.array([[c, -s], [s, c]])


def online_channel(
    accel: SensorErrorModel,
    gyro: SensorErrorModel,
    velocity_noise,
    sample_interval: float = 1.0,
    *,
    gravity=STANDARD_GRAVITY,
    radius=EARTH_RADIUS,
) -> LinearGaussianModel:
    """The discrete six-state channel [ΔV, δ, a₁, a₂, ω₁, ω₂] (exact, Van Loan) with the two
    sensor blocks of `SensorErrorModel`; z = ΔV + v, R = σ_v². The same generator and
    discretisation as `INSNoiseChannel` (tests check the two agree)."""
    a, d, h = _generator(
        jnp.asarray(gravity, float), jnp.asarray(radius, float), accel.generator(), gyro.generator()
    )
    return _discretise(a, d, h, jnp.asarray(velocity_noise, float), sample_interval)


def _window_autocovariance(x, count, max_lag):
    """Centred autocovariance (11) of the masked window x (zeros outside), count samples."""
    size = x.shape[0]
    mask = jnp.arange(size) >= size - count
    mean = jnp.sum(jnp.where(mask, x, 0.0)) / count
    centred = jnp.where(mask, x - mean, 0.0)
    fft_size = 1 << (2 * size - 1).bit_length()
    spectrum = jnp.fft.rfft(centred, n=fft_size)
    raw = jnp.fft.irfft(spectrum * jnp.conj(spectrum), n=fft_size)[: max_lag + 1]
    lags = jnp.arange(max_lag + 1, dtype=x.dtype)
    return raw / jnp.maximum(count - lags, 1.0), centred


def structure_candidates(
    autocovariance: ArrayLike, lag_time: float, shape: ArrayLike | None = None
) -> tuple[SensorErrorModel, SensorErrorModel, Array, Array]:
    """The two structures' parameters from an autocovariance by the paper's rules.

    Gauss–Markov by rule (15) over the lags while r_j > e⁻¹; exponential-cosine by rules
    (19)–(21), its α and β from `shape` when given (the autocovariance of the estimates
    alone, whose zero crossing the shrinkage correction would move), its σ² from
    `autocovariance`'s R_0. `autocovariance`: R_0..R_K of a series sampled every `lag_time`
    s.

    **Returns:** (gauss_markov, exp_cosine, gm_ok, ec_ok). Jit/vmap-safe.
    """
    R = jnp.asarray(autocovariance)
    gm = fit_gauss_markov_paper(R, lag_time, min_correlation=float(np.exp(-1)), throw=False)
    ec = fit_exp_cosine_paper(R if shape is None else jnp.asarray(shape), lag_time, throw=False)
    gm_ok = gm.result == NoiseFitResult.successful
    ec_ok = ec.result == NoiseFitResult.successful
    gm_model = SensorErrorModel(gm.model.sigma, gm.decay_rate, jnp.zeros_like(gm.decay_rate))
    ec_model = SensorErrorModel(jnp.sqrt(R[0]), ec.model.decay_rate, ec.model.angular_frequency)
    return gm_model, ec_model, gm_ok, ec_ok
