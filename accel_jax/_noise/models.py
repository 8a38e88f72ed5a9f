"""Noise models — white noise, first-order Gauss-Markov, exponential-cosine, random walk and
their sums — as `eqx.Module`s with positive array fields, each giving its exact discrete
state-space form (no approximation in Δt) and, where stationary, its autocovariance. GM
x_{k+1} = φ x_k + w, φ = e^{−Δ/τ}, var w = σ²(1 − φ²). The exponential-cosine autocovariance
σ² e^{−α|τ|} cos βτ is that of the first component of the 2-D state s_{k+1} = e^{−αΔ}
Rot(βΔ) s_k + w, cov w = σ²(1 − e^{−2αΔ}) I (a damped rotation; the continuous form is ds =
(−α I + β J) s dt + σ√(2α) dW). The paper's second-order shaping filter (17), with
b² = α² + β², is garbled in the source; read as the standard form σ√(2α)(p + b)/(p² + 2αp +
b²) driven by unit white noise it has exactly the autocorrelation (16) (its spectrum is
2ασ²(ω² + b²)/((b² − ω²)² + 4α²ω²), that of (16); tests/test_noise.py checks the two
autocovariances through the filter's Lyapunov covariance). Without the zero at −b, a constant
numerator gives e^{−α|τ|}(cos βτ + (α/β) sin β|τ|) instead. Either way the process
identified is (16), realised here exactly. Random walk x_{k+1} = x_k + w, var w = q
Δ, with a diffuse start. `simulate_noise` draws records from a model and `model_parameters`
lists its parameters as plain floats.
"""

from __future__ import annotations

from typing import cast

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._params import _as_float, _concrete
from .record import Scalar, Series, _sample_interval


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
        r = cast(Array, sum(p[4] for p in parts))  # an array: ≥ 2 components, not the 0 start
        return f, q, h, p0, r

    def autocovariance(self, lag_times):
        return cast(Array, sum(c.autocovariance(lag_times) for c in self.components))


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
