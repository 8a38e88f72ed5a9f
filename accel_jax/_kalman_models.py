"""The single-channel INS of docs/models.md §4 with a choice of sensor-error model per sensor:
white noise, first-order Gauss–Markov (7)–(8) or exponential-cosine (16)–(17).

`INSChannel` (in `_kalman`) carries Gauss–Markov errors only and keeps its fields, which its
callers set by name; `INSNoiseChannel` takes the sensor errors as `accel_jax.noise` models
(`WhiteNoise`, `GaussMarkov`, `ExponentialCosine`) and builds each sensor's states from that
model's own exact discrete form (`state_space`: output row and stationary covariance) and
the generator of it. With two Gauss–Markov models its matrices, and so the filter's output,
are `INSChannel`'s bit for bit (the same code builds them). The noise models are read, not
imported: `_noise` imports `_kalman`, and an `eqx.Module` field holds any of them.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import jax.scipy.linalg as jsl
from jaxtyping import Array

from ._kalman import LinearGaussianModel, Scalar
from ._kalman_ins import (
    _INS_UNITS,
    EARTH_RADIUS,
    _check_interval,
    _discretise,
    _gauss_markov,
    _generator,
    _positive,
    _scale_check,
)
from ._kalman_ins import scale_noise_coefficients as _scale_ins_channel
from ._params import _as_float
from ._static import STANDARD_GRAVITY

_KINDS = {"white": 0, "gauss_markov": 1, "exp_cosine": 2}
"""The sensor-error models `INSNoiseChannel` takes (their `name`) and their state sizes."""


def _sensor_block(model, sample_interval) -> tuple[Array, Array, Array, Array, Array]:
    """(A_s, D_s, H_s, P_s, q) of one sensor's error model: the generator, diffusion, output
    row and stationary covariance of its state, and the white intensity q [unit²·s] it adds
    to the kinematic state it drives (0 unless white).

    H_s and P_s are the model's own `state_space`; A_s and D_s are the generator whose exact
    discretisation that is (tests/test_kalman_exp_cosine.py checks e^{A_sΔ}, Q_s and P_s
    against `state_space`): Gauss–Markov A = −1/τ_c, D = 2σ²/τ_c; exponential-cosine the
    damped rotation A = −αI + βJ, J = [[0, −1], [1, 0]], D = 2ασ² I (ds = (−αI + βJ) s dt +
    σ√(2α) dW, as `ExponentialCosine` states). White noise of variance σ² per sample at Δ
    has no state and intensity q = σ²Δ (its mean over Δ has variance σ²).
    """
    kind = getattr(model, "name", None)
    if kind not in _KINDS:
        raise ValueError(
            "INSNoiseChannel: a sensor error must be accel_jax.noise's WhiteNoise, GaussMarkov "
            f"or ExponentialCosine, got {model!r}."
        )
    _, _, h, p, _ = model.state_space(sample_interval)
    sigma = model.sigma
    if kind == "white":
        empty = jnp.zeros((0, 0), sigma.dtype)
        return empty, empty, jnp.zeros((1, 0), sigma.dtype), empty, sigma**2 * sample_interval
    if kind == "gauss_markov":
        a, d = _gauss_markov(sigma, model.correlation_time)
    else:
        alpha, beta = model.decay_rate, model.angular_frequency
        a = jnp.stack([jnp.stack([-alpha, -beta]), jnp.stack([beta, -alpha])])
        d = 2 * alpha * sigma**2 * jnp.eye(2, dtype=a.dtype)
    return a, d, h, p, jnp.zeros((), a.dtype)


class INSNoiseChannel(eqx.Module):
    """Single-channel INS error model (Schuler loop) with each sensor's error one of three
    `accel_jax.noise` models:

    - `WhiteNoise(σ)`: σ per sample at the discretisation interval Δ; no state (a velocity
      or angle random walk of intensity σ²Δ).
    - `GaussMarkov(σ, τ_c)` (7): one state, Δ' = −Δ/τ_c + σ√(2/τ_c) w. Both sensors so: the
      matrices and filter output are `INSChannel`'s.
    - `ExponentialCosine(σ, α, β)` (16): R(τ) = σ² e^{−α|τ|} cos βτ; two states, the damped
      rotation of its `state_space`, whose first component has the autocorrelation of the
      paper's shaping filter (17) σ√(2α)(p + b)/(p² + 2αp + b²), b² = α² + β².

    State x = [ΔV [m/s], δ [rad], accelerometer states, gyro states] (white: none); dynamics
    ΔV' = −g δ + Δa, δ' = ΔV/R + Δω with Δa, Δω the first component of their sensor's state
    (or its white noise); observation z = ΔV + v, v ~ N(0, σ_v²). jit/vmap/grad-safe over
    the models' parameters; float64 recommended.

    **Fields:**

    - `accel_error`: the accelerometer error model [m/s²].
    - `gyro_error`: the gyro drift model [rad/s].
    - `velocity_noise`: σ_v [m/s].
    - `gravity`: g [m/s²] (default 9.80665).
    - `radius`: R [m] (default 6.371e6).
    """

    accel_error: eqx.Module
    gyro_error: eqx.Module
    velocity_noise: Scalar = eqx.field(converter=_as_float)
    gravity: Scalar = eqx.field(converter=_as_float, default=STANDARD_GRAVITY)
    radius: Scalar = eqx.field(converter=_as_float, default=EARTH_RADIUS)

    def __check_init__(self):
        for name in ("velocity_noise", "gravity", "radius"):
            _positive(name, _INS_UNITS[name])(self)
        for model in (self.accel_error, self.gyro_error):
            _sensor_block(model, 1.0)

    def sensor_indices(self) -> tuple[int | None, int | None]:
        """The state indices of Δa and Δω (None for a white sensor error)."""
        na = _KINDS[getattr(self.accel_error, "name")]
        ng = _KINDS[getattr(self.gyro_error, "name")]
        return (2 if na else None), (2 + na if ng else None)

    def continuous(self, sample_interval: float = 1.0) -> tuple[Array, Array, Array]:
        """(A, G Q_c Gᵀ, H) of the continuous model: dx/dt = A x + G w, z = H x + v
        (`sample_interval` [s] sets a white sensor error's intensity σ²Δ)."""
        accel = _sensor_block(self.accel_error, sample_interval)
        gyro = _sensor_block(self.gyro_error, sample_interval)
        parts = [(b[0], b[1], b[2], b[4]) for b in (accel, gyro)]
        return _generator(self.gravity, self.radius, *parts)

    def discretise(self, sample_interval: float = 1.0) -> LinearGaussianModel:
        """Exact discretisation over `sample_interval` [s] (Van Loan, as
        `INSChannel.discretise`); R = σ_v²."""
        _check_interval("INSNoiseChannel", sample_interval)
        a, diffusion, h = self.continuous(sample_interval)
        return _discretise(a, diffusion, h, self.velocity_noise, sample_interval)

    def stationary_sensor_covariance(self) -> Array:
        """The stationary covariance of the sensor states, block-diagonal (0 × 0 when both
        errors are white)."""
        blocks = [_sensor_block(m, 1.0)[3] for m in (self.accel_error, self.gyro_error)]
        return jsl.block_diag(*blocks)


def scale_noise_coefficients(channel, *, drift_factor: float, diffusion_factor: float):
    """The channel with both sensors' drift coefficient multiplied by `drift_factor` and
    diffusion (white-noise intensity) by `diffusion_factor` — the paper's mis-tuned filter
    has factors of 10 or 1/10.

    - `INSChannel`, or a `GaussMarkov` error of `INSNoiseChannel`: drift 1/τ, diffusion
      2σ²/τ, so τ' = τ/f_drift and σ'² = σ² f_diffusion/f_drift.
    - `ExponentialCosine`: drift α (the decay of its shaping filter), diffusion 2ασ², so
      α' = α f_drift, σ'² = σ² f_diffusion/f_drift; β is kept.
    - `WhiteNoise`: no drift; its intensity σ²Δ scales by f_diffusion (σ' = σ √f_diffusion).
    """
    if not isinstance(channel, INSNoiseChannel):
        return _scale_ins_channel(
            channel, drift_factor=drift_factor, diffusion_factor=diffusion_factor
        )
    _scale_check(drift_factor, diffusion_factor)
    drift, diffusion = jnp.asarray(drift_factor), jnp.asarray(diffusion_factor)
    ratio = jnp.sqrt(diffusion / drift)

    def scale(model):
        kind = getattr(model, "name")
        if kind == "white":
            return eqx.tree_at(lambda m: m.sigma, model, model.sigma * jnp.sqrt(diffusion))
        if kind == "gauss_markov":
            return eqx.tree_at(
                lambda m: (m.sigma, m.correlation_time),
                model,
                (model.sigma * ratio, model.correlation_time / drift),
            )
        return eqx.tree_at(
            lambda m: (m.sigma, m.decay_rate), model, (model.sigma * ratio, model.decay_rate * drift)
        )

    return eqx.tree_at(
        lambda c: (c.accel_error, c.gyro_error),
        channel,
        (scale(channel.accel_error), scale(channel.gyro_error)),
    )
