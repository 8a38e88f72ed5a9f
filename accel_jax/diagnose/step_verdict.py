"""The old place of `accel_jax.diagnose.step.verdict` (the step verdict):
each name warns and forwards, for one release."""

from .._deprecated import moved_names

__getattr__ = moved_names(
    __name__,
    "accel_jax.diagnose.step.verdict",
    "LOCK_WINDOW evaluate",
    "accel_jax.diagnose.step.assess",
    "fit_entries nested_shortfall nested_failed nested_losers evidence_slack "
    "explains_deterministically NESTED_TOLERANCE NESTED_ABSOLUTE",
    "accel_jax.diagnose.step.nuisance",
    "NUISANCE_ALPHA nuisance_test strained_sentence change_shifts",
)
