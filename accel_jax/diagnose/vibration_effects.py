"""The old place of `accel_jax.diagnose.vibration.effects` (the vibration effects): each name
warns and forwards, for one release."""

from .._deprecated import moved_names

__getattr__ = moved_names(
    __name__,
    "accel_jax.diagnose.vibration.effects",
    "NOMINAL_COEFFICIENTS COEFFICIENTS AbstractVibrationEffect K2 K3 K4 K5 Asymmetry "
    "CrossCoupling",
)
