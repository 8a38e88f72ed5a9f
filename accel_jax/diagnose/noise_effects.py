"""The old place of `accel_jax.diagnose.noise.effects` (the noise effects): each name warns and
forwards, for one release."""

from .._deprecated import moved_names

# Read without a warning until noise_fit imports them from noise.effects (its own change).
from .noise.effects import AbstractNoiseEffect, NoiseComponents  # noqa: F401

__getattr__ = moved_names(
    __name__,
    "accel_jax.diagnose.noise.effects",
    "STARTS NoiseComponents AbstractNoiseEffect GaussMarkovNoise ExpCosineNoise RandomWalkNoise",
)
