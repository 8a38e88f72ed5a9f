"""The old place of `accel_jax.diagnose.step.effects` (the step effects):
each name warns and forwards, for one release."""

from .._deprecated import moved_names

__getattr__ = moved_names(
    __name__,
    "accel_jax.diagnose.step.effects",
    "AbstractStepEffect TorquerLag OutputFilter OFFSET_PRIOR StopSaturation DisturbanceDrift "
    "ColoredNoise step_effects",
)
