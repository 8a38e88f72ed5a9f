"""The old place of `accel_jax.diagnose.noise.effects` (the noise effects): each name warns and
forwards, for one release."""

from .._deprecated import moved_names

__getattr__ = moved_names(
    __name__,
    "accel_jax.diagnose.noise.effects",
    "STARTS NoiseComponents AbstractNoiseEffect GaussMarkovNoise ExpCosineNoise RandomWalkNoise",
)
