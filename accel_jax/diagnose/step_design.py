"""The old place of `accel_jax.diagnose.step.design` (the next experiment for a lag tie):
each name warns and forwards, for one release."""

from .._deprecated import moved_names

__getattr__ = moved_names(
    __name__,
    "accel_jax.diagnose.step.design",
    "experiment_menu expected_evidence next_experiments",
)
