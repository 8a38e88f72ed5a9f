"""The old place of `accel_jax.diagnose.noise.sensor` (the forward selection of real-sensor
effects): each name warns and forwards, for one release."""

from .._deprecated import moved_names

__getattr__ = moved_names(
    __name__,
    "accel_jax.diagnose.noise.sensor",
    "EXACT_LIMIT CLASSIC needs_selection allan_summary selection_summary combine "
    "from_selection run_selection",
)
