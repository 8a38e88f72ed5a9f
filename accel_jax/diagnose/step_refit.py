"""The old place of `accel_jax.diagnose.step.refit` (the refit's report):
each name warns and forwards, for one release."""

from .._deprecated import moved_names

__getattr__ = moved_names(
    __name__,
    "accel_jax.diagnose.step.refit",
    "TRANSIENT_FRACTION KNOWN_FIELDS",
)
