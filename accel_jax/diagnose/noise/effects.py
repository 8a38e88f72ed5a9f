"""The noise kind's effect library: `AbstractNoiseEffect` (hooks: the coloured part of the
record's noise, `NoiseComponents`) and its final effects `gauss_markov`, `exp_cosine`,
`random_walk`, each exactly white noise at z = 0."""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..base import (
    AbstractEffect,
    register_effect,
)
from .state import NoiseStarts

STARTS = 8
"""Whittle starts per candidate (the `initial_model` guess and a grid, see
`AbstractNoiseEffect.alternative_starts`)."""


_SLOT = 3  # the largest effect's parameter count (exp_cosine)


class NoiseComponents(eqx.Module):
    """The processes added to the white noise, in the record's normalised units (s₀ = 1).

    **Fields:** `variance` v of the coloured block; `decay` ρ = e^{−αΔ} of the block per
    sample; `rotation` θ = βΔ of the block per sample (0: Gauss–Markov); `walk` qΔ, the
    level's increment variance per sample.
    """

    variance: jax.Array
    decay: jax.Array
    rotation: jax.Array
    walk: jax.Array


class AbstractNoiseEffect(AbstractEffect):
    """An effect on a static record. One hook: `components(z)` gives the processes it adds
    (`NoiseComponents`; zero variance and zero walk at z = 0: the nominal model)."""

    kind = "noise"

    def components(self, z) -> NoiseComponents:
        zero = jnp.zeros_like(z[0])
        return NoiseComponents(zero, zero, zero, zero)

    def guess_from(self, model, scale, dt) -> np.ndarray:
        """A start z from `accel_jax._noise.initial_model`'s model of the record."""
        raise NotImplementedError

    def alternative_starts(self, guess: np.ndarray) -> np.ndarray:
        """Further starts for the Whittle fit, shape (STARTS − 1, n_params): the likelihood
        of a correlated noise can have several maxima (in τ_c, in β); the best Whittle fit
        of all starts goes on to the exact polish."""
        return np.repeat(guess[None, :], STARTS - 1, axis=0)

    @property
    def structure(self) -> str:
        """The `accel_jax._noise` structure of nominal + this effect."""
        return f"white+{self.name}"

    def initial_guess(self, context: NoiseStarts) -> np.ndarray:
        """z from `accel_jax._noise.initial_model` of the normalised training record
        (`context`: its `initial_models` by effect name and `dt`)."""
        model = context.initial_models[self.name]
        return self.guess_from(model.components[1], 1.0, context.dt)


@register_effect
class GaussMarkovNoise(AbstractNoiseEffect):
    """+ Gauss–Markov noise: σ = s₀·z₀, τ_c = Δ·e^{−z₁}."""

    name = "gauss_markov"
    parameter_names = ("sigma_g", "correlation_time_s")
    description = "first-order Gauss–Markov (exponentially correlated) noise"

    def components(self, z):
        return NoiseComponents(z[0] ** 2, jnp.exp(-jnp.exp(z[1])), 0 * z[0], 0 * z[0])

    def guess_from(self, model, scale, dt):
        return np.array([float(model.sigma) / scale, math.log(dt / float(model.correlation_time))])

    def alternative_starts(self, guess):
        # τ_c from 1 to 300 samples.
        grid = np.log(1 / np.geomspace(1.0, 300.0, STARTS - 1))
        return np.stack([np.full(STARTS - 1, guess[0]), grid], axis=1)

    def physical(self, z, context):
        return {
            "sigma_g": abs(float(z[0])) * context["scale"],
            "correlation_time_s": context["dt"] / math.exp(float(z[1])),
        }


@register_effect
class ExpCosineNoise(AbstractNoiseEffect):
    """+ exponential-cosine noise: σ = s₀·z₀, α = e^{z₁}/Δ, β = z₂²/Δ."""

    name = "exp_cosine"
    parameter_names = ("sigma_g", "decay_rate_per_s", "angular_frequency_rad_per_s")
    description = "exponential-cosine (damped oscillatory) correlated noise"

    def components(self, z):
        return NoiseComponents(z[0] ** 2, jnp.exp(-jnp.exp(z[1])), z[2] ** 2, 0 * z[0])

    def guess_from(self, model, scale, dt):
        theta = min(float(model.angular_frequency) * dt, 0.9 * math.pi)
        return np.array(
            [float(model.sigma) / scale, math.log(float(model.decay_rate) * dt), math.sqrt(theta)]
        )

    def alternative_starts(self, guess):
        # Periods from 3 to 100 samples, two oscillations per decay time.
        theta = 2 * np.pi / np.geomspace(3.0, 100.0, STARTS - 1)
        return np.stack(
            [np.full(STARTS - 1, guess[0]), np.log(theta / (4 * np.pi)), np.sqrt(theta)], axis=1
        )

    def physical(self, z, context):
        dt = context["dt"]
        theta = float(z[2]) ** 2 % (2 * math.pi)
        theta = min(theta, 2 * math.pi - theta)  # cos θk is even and 2π-periodic in θ
        beta = theta / dt
        return {
            "sigma_g": abs(float(z[0])) * context["scale"],
            "decay_rate_per_s": math.exp(float(z[1])) / dt,
            "angular_frequency_rad_per_s": beta,
            "period_s": 2 * math.pi / beta if beta > 0 else float("inf"),
        }


@register_effect
class RandomWalkNoise(AbstractNoiseEffect):
    """+ random walk of the level: increment RMS per sample √(qΔ) = s₀·z₀."""

    name = "random_walk"
    parameter_names = ("intensity_g2_per_s",)
    description = "random walk of the level (bias instability growing without bound)"

    def components(self, z):
        zero = 0 * z[0]
        return NoiseComponents(zero, zero, zero, z[0] ** 2)

    def guess_from(self, model, scale, dt):
        return np.array([math.sqrt(float(model.intensity) * dt) / scale])

    def alternative_starts(self, guess):
        # Increment RMS from 1e-3 to 0.3 of the record's RMS per sample.
        return np.geomspace(1e-3, 0.3, STARTS - 1)[:, None]

    def physical(self, z, context):
        q = float(z[0]) ** 2 * context["scale"] ** 2 / context["dt"]
        return {
            "intensity_g2_per_s": q,
            "walk_over_record_g": math.sqrt(q * context["duration"]),
        }
