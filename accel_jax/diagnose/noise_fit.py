"""The old place of `accel_jax.diagnose.noise.fit` (the noise diagnosis's fit): each name
warns and forwards, for one release."""

from .._deprecated import moved_names

__getattr__ = moved_names(
    __name__,
    "accel_jax.diagnose.noise.fit",
    "WHITTLE_STEPS POLISH_STEPS FIT_TOLERANCE WHITTLE_BANDS INTERVAL_LEVEL filter_terms spectrum "
    "model_intervals",
)
