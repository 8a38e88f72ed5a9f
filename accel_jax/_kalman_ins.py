"""The single-channel INS test bed of docs/models.md §4 (Chernodarov, Patrikeev & Ivanov): a
Kalman filter estimating INS errors diverges — its actual error leaves the ±3σ band its own
covariance predicts — when the sensor-noise models it carries are wrong. The channel is the
Schuler loop with state x = [ΔV, δ, Δa, Δω] (velocity error [m/s], vertical error [rad],
accelerometer error [m/s²], gyro drift [rad/s]):

    ΔV' = −g δ + Δa,          δ' = ΔV/R + Δω,
    Δa' = −Δa/τ_a + σ_a √(2/τ_a) w_a,     Δω' = −Δω/τ_ω + σ_ω √(2/τ_ω) w_ω,

observed at 1 Hz through z = ΔV + v (velocity against an external reference). `INSChannel`
has these Gauss–Markov sensor errors; `_kalman_models.INSNoiseChannel` the same channel with
white, Gauss–Markov or exponential-cosine errors taken from `accel_jax.noise` models. The
filter, the smoother and the consistency statistics are `_kalman`'s.

Precision: float64 is needed (1/R ≈ 1.6e-7 s⁻¹ beside g ≈ 9.8 m/s², gyro variances near
1e-15 rad²/s²).
"""

from __future__ import annotations

from typing import Protocol

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np
from jaxtyping import Array

from ._kalman import (
    LinearGaussianModel,
    Scalar,
    _symmetrise,
    kalman_filter,
    normalised_estimation_error_squared,
    normalised_innovation_squared,
    simulate_linear_gaussian,
)
from ._params import _as_float, _concrete, _shown
from ._static import STANDARD_GRAVITY

EARTH_RADIUS = 6.371e6
"""Mean Earth radius R [m] of the Schuler loop."""


def _positive(name: str, unit: str):
    def check(self):
        value = _concrete(getattr(self, name))
        if value is not None and not (np.all(np.isfinite(value)) and np.all(value > 0)):
            raise ValueError(
                f"{type(self).__name__}.{name} must be positive and finite, got "
                f"{_shown(value)} {unit}."
            )

    return check


_INS_UNITS = {
    "accel_sigma": "m/s²",
    "accel_correlation_time": "s",
    "gyro_sigma": "rad/s",
    "gyro_correlation_time": "s",
    "velocity_noise": "m/s",
    "gravity": "m/s²",
    "radius": "m",
}


def _check_interval(owner: str, sample_interval) -> None:
    concrete = _concrete(sample_interval)
    if concrete is not None and not (np.isfinite(concrete) and concrete > 0):
        raise ValueError(
            f"{owner}.discretise: sample_interval must be positive, got "
            f"{_shown(concrete)} s."
        )


def _discretise(a, diffusion, h, velocity_noise, sample_interval) -> LinearGaussianModel:
    """Van Loan: F = e^{AΔ}, Q = ∫₀^Δ e^{As} D e^{Aᵀs} ds from one block exponential; R = σ_v²."""
    dt = jnp.asarray(sample_interval, a.dtype)
    n = a.shape[0]
    block = jnp.block([[-a, diffusion], [jnp.zeros_like(a), a.T]]) * dt
    e = jsl.expm(block)
    transition = e[n:, n:].T
    process = _symmetrise(transition @ e[:n, n:])
    r = jnp.reshape(velocity_noise**2, (1, 1)).astype(a.dtype)
    return LinearGaussianModel(transition, process, h, r)


def _gauss_markov(sigma, tau):
    """(A_s, D_s) of a Gauss–Markov state: −1/τ and 2σ²/τ."""
    return jnp.reshape(-1 / tau, (1, 1)), jnp.reshape(2 * sigma**2 / tau, (1, 1))


def _generator(gravity, radius, accel, gyro) -> tuple[Array, Array, Array]:
    """(A, D, H) of the channel [ΔV, δ, accelerometer states, gyro states] from each sensor's
    (A_s, D_s, H_s, q): its state drives ΔV (δ) through H_s, its white intensity q directly."""
    (aa, da, ha, qa), (ag, dg, hg, qg) = accel, gyro
    na, n = aa.shape[0], 2 + aa.shape[0] + ag.shape[0]
    dtype = jnp.result_type(aa, ag, radius)
    a = jnp.zeros((n, n), dtype).at[0, 1].set(-gravity).at[1, 0].set(1 / radius)
    a = a.at[0, 2 : 2 + na].set(ha[0]).at[1, 2 + na :].set(hg[0])
    a = a.at[2 : 2 + na, 2 : 2 + na].set(aa).at[2 + na :, 2 + na :].set(ag)
    diffusion = jsl.block_diag(jnp.diag(jnp.stack([qa, qg]).astype(dtype)), da, dg)
    return a, diffusion, jnp.zeros((1, n), dtype).at[0, 0].set(1)


class INSChannel(eqx.Module):
    """Single-channel INS error model (Schuler loop) with Gauss-Markov sensor errors.

    State x = [ΔV [m/s], δ [rad], Δa [m/s²], Δω [rad/s]]; continuous dynamics (docs/models.md §4)

        ΔV' = −g δ + Δa,   δ' = ΔV/R + Δω,
        Δa' = −Δa/τ_a + σ_a √(2/τ_a) w_a,   Δω' = −Δω/τ_ω + σ_ω √(2/τ_ω) w_ω,

    and velocity observations z = ΔV + v, v ~ N(0, σ_v²). The drift coefficients are 1/τ
    and the diffusion coefficients (white-noise intensities) 2σ²/τ.

    **Fields:**

    - `accel_sigma`: σ_a [m/s²], stationary standard deviation of the accelerometer error.
    - `accel_correlation_time`: τ_a [s].
    - `gyro_sigma`: σ_ω [rad/s], stationary standard deviation of the gyro drift.
    - `gyro_correlation_time`: τ_ω [s].
    - `velocity_noise`: σ_v [m/s], standard deviation of the velocity observation noise.
    - `gravity`: g [m/s²] (default 9.80665).
    - `radius`: R [m] (default 6.371e6).
    """

    accel_sigma: Scalar = eqx.field(converter=_as_float)
    accel_correlation_time: Scalar = eqx.field(converter=_as_float)
    gyro_sigma: Scalar = eqx.field(converter=_as_float)
    gyro_correlation_time: Scalar = eqx.field(converter=_as_float)
    velocity_noise: Scalar = eqx.field(converter=_as_float)
    gravity: Scalar = eqx.field(converter=_as_float, default=STANDARD_GRAVITY)
    radius: Scalar = eqx.field(converter=_as_float, default=EARTH_RADIUS)

    def __check_init__(self):
        for name, unit in _INS_UNITS.items():
            _positive(name, unit)(self)

    def continuous(self) -> tuple[Array, Array, Array]:
        """(A, G Q_c Gᵀ, H) of the continuous model: dx/dt = A x + G w, z = H x + v."""
        dtype = jnp.result_type(self.accel_sigma, self.gyro_sigma, self.radius)
        one, zero = jnp.ones((1, 1), dtype), jnp.zeros((), dtype)
        accel = (*_gauss_markov(self.accel_sigma, self.accel_correlation_time), one, zero)
        gyro = (*_gauss_markov(self.gyro_sigma, self.gyro_correlation_time), one, zero)
        return _generator(self.gravity, self.radius, accel, gyro)

    def discretise(self, sample_interval: float = 1.0) -> LinearGaussianModel:
        """Exact discretisation over `sample_interval` [s] (default 1 s, the paper's 1 Hz).

        F = e^{AΔ} and Q = ∫₀^Δ e^{As} G Q_c Gᵀ e^{Aᵀs} ds by Van Loan's block exponential
        (one `jax.scipy.linalg.expm`); R = σ_v². float64 recommended.
        """
        _check_interval("INSChannel", sample_interval)
        return _discretise(*self.continuous(), self.velocity_noise, sample_interval)

    def stationary_sensor_covariance(self) -> Array:
        """diag(σ_a², σ_ω²), the stationary covariance of [Δa, Δω]."""
        return jnp.diag(jnp.stack([self.accel_sigma**2, self.gyro_sigma**2]))


class _Channel(Protocol):
    """What the consistency trial reads of a channel: `INSChannel` or
    `accel_jax._kalman_models.INSNoiseChannel` (which imports this module)."""

    def discretise(self, sample_interval: float = 1.0) -> LinearGaussianModel: ...

    def stationary_sensor_covariance(self) -> Array: ...


def _scale_check(drift_factor, diffusion_factor):
    for name, value in (("drift_factor", drift_factor), ("diffusion_factor", diffusion_factor)):
        concrete = _concrete(value)
        if concrete is not None and not (np.isfinite(concrete) and concrete > 0):
            raise ValueError(
                f"scale_noise_coefficients: {name} must be positive, got {concrete!r}."
            )


def scale_noise_coefficients(
    channel: INSChannel, *, drift_factor: float, diffusion_factor: float
) -> INSChannel:
    """The channel with both sensors' drift (1/τ) multiplied by `drift_factor` and diffusion
    (2σ²/τ) by `diffusion_factor` — the paper's mis-tuned filter has factors of 10 or 1/10.

    τ' = τ/drift_factor, σ'² = σ² · diffusion_factor/drift_factor (so 2σ'²/τ' = 2σ²/τ ·
    diffusion_factor).
    """
    _scale_check(drift_factor, diffusion_factor)
    sigma_scale = jnp.sqrt(jnp.asarray(diffusion_factor) / jnp.asarray(drift_factor))
    return eqx.tree_at(
        lambda c: (
            c.accel_sigma,
            c.accel_correlation_time,
            c.gyro_sigma,
            c.gyro_correlation_time,
        ),
        channel,
        (
            channel.accel_sigma * sigma_scale,
            channel.accel_correlation_time / drift_factor,
            channel.gyro_sigma * sigma_scale,
            channel.gyro_correlation_time / drift_factor,
        ),
    )


def ins_initial_covariance(
    channel: _Channel,
    *,
    velocity_sigma: float = 0.1,
    vertical_sigma: float = 1e-4,
) -> Array:
    """Prior covariance diag(σ_V², σ_δ², σ_a², σ_ω²): initial velocity [m/s] and vertical
    [rad] uncertainty as given, the sensor states at their stationary covariance."""
    sensors = channel.stationary_sensor_covariance()
    dtype = sensors.dtype
    kinematic = jnp.stack(
        [jnp.asarray(velocity_sigma, dtype) ** 2, jnp.asarray(vertical_sigma, dtype) ** 2]
    )
    return jsl.block_diag(jnp.diag(kinematic), sensors)


class ConsistencyTrial(eqx.Module):
    """One Monte Carlo run of `ins_consistency_trial` (T steps).

    **Fields:**

    - `vertical_error`: δ − δ̂ [rad], shape (T,).
    - `vertical_sigma`: √P_δδ [rad] the filter predicts, shape (T,).
    - `nees`: NEES per step (χ²(n), n states, if consistent), shape (T,).
    - `nis`: NIS per step (χ²(1) if consistent), shape (T,).
    - `fraction_outside_3sigma`: share of steps with |δ − δ̂| > 3√P_δδ.
    """

    vertical_error: Array
    vertical_sigma: Array
    nees: Array
    nis: Array
    fraction_outside_3sigma: Scalar


def ins_consistency_trial(
    truth: _Channel,
    assumed: _Channel,
    key: Array,
    *,
    num_steps: int,
    sample_interval: float = 1.0,
    velocity_sigma: float = 0.1,
    vertical_sigma: float = 1e-4,
) -> ConsistencyTrial:
    """Simulate the INS channel with the `truth` noise model and filter it with the
    `assumed` one; vmap over `key` (or `accel_jax.sweep`) for Monte Carlo statistics.

    The truth starts from N(0, P0_truth) and the filter from N(0, P0_assumed), both from
    `ins_initial_covariance`. Either channel is an `INSChannel` or an `INSNoiseChannel`, the
    two with one state layout. float64 required.
    """
    true_model = truth.discretise(sample_interval)
    filter_model = assumed.discretise(sample_interval)
    n = true_model.state_size
    if filter_model.state_size != n:
        raise ValueError(
            f"ins_consistency_trial: the truth has {n} states and the assumed channel "
            f"{filter_model.state_size}; the NEES compares states one to one."
        )
    dtype = true_model.transition.dtype
    p0_true = ins_initial_covariance(
        truth, velocity_sigma=velocity_sigma, vertical_sigma=vertical_sigma
    )
    p0_filter = ins_initial_covariance(
        assumed, velocity_sigma=velocity_sigma, vertical_sigma=vertical_sigma
    )
    states, observations = simulate_linear_gaussian(
        true_model, jnp.zeros(n, dtype), p0_true, num_steps, key=key
    )
    out = kalman_filter(filter_model, observations, jnp.zeros(n, dtype), p0_filter)
    errors = states - out.filtered_means
    vertical_error = errors[:, 1]
    vertical_sigma_k = jnp.sqrt(out.filtered_covariances[:, 1, 1])
    return ConsistencyTrial(
        vertical_error=vertical_error,
        vertical_sigma=vertical_sigma_k,
        nees=normalised_estimation_error_squared(errors, out.filtered_covariances),
        nis=normalised_innovation_squared(out),
        fraction_outside_3sigma=jnp.mean(jnp.abs(vertical_error) > 3 * vertical_sigma_k),
    )
