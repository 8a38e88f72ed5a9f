"""The old place of `accel_jax.diagnose.step.nuisance` (the nuisances' joint test):
each name warns and forwards, for one release."""

from .._deprecated import moved_names

__getattr__ = moved_names(
    __name__,
    "accel_jax.diagnose.step.nuisance",
    "NUISANCE_ALPHA nuisance_test change_shifts strained_sentence",
)
