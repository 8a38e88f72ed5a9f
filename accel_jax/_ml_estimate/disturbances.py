"""The disturbance models of the sensing-element record (white, Gauss–Markov, harmonic)
and the error covariance R = σ² I + R_SE they give the estimate."""

from __future__ import annotations

import abc

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray

from .._params import _as_float, _concrete

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
        """Covariance E[δ(t_i) δ(t_j)] in rad² at the sample times `ts` [s], shape (K, K)."""

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


class ExponentialDisturbance(AbstractDisturbance):
    """An exponentially settling disturbance c·e^{−t/τ} with a random amplitude c ~ N(0, s²):
    the paper's deterministic disturbances of "exponential character" (e.g. a thermal or
    electrical transient settling after switch-on), given the random amplitude so that they
    enter the ML covariance like the harmonic one does.

    R_SE,ij = s² e^{−t_i/τ} e^{−t_j/τ} (rank 1: only with σ² > 0 is R invertible); t is the
    record's clock (the transient starts at t = 0).

    **Fields:** `std` s [rad]; `time_constant` τ [s].
    """

    std: Float[Array, ""] = eqx.field(converter=_as_float)
    time_constant: Float[Array, ""] = eqx.field(converter=_as_float)

    def __check_init__(self):
        _check_non_negative("ExponentialDisturbance", "std", self.std, "rad")
        _check_positive("ExponentialDisturbance", "time_constant", self.time_constant, "s")

    def _shape(self, ts):
        return jnp.exp(-jnp.asarray(ts) / self.time_constant)

    def covariance(self, ts):
        shape = self._shape(ts)
        return self.std**2 * shape[:, None] * shape[None, :]

    def sample(self, ts, *, key):
        ts = jnp.asarray(ts)
        return self.std * jax.random.normal(key, (), ts.dtype) * self._shape(ts)


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
