"""The old place of `accel_jax.diagnose.step.assess` (each candidate's assessment):
each name warns and forwards, for one release."""

from .._deprecated import moved_names

__getattr__ = moved_names(
    __name__,
    "accel_jax.diagnose.step.assess",
    "NOISE_VARIANCE_FACTOR fit_entries NESTED_TOLERANCE NESTED_ABSOLUTE nested_shortfall "
    "nested_failed nested_losers evidence_slack explains_deterministically",
)
