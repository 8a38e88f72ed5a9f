"""Moved to `accel_jax.diagnose.step.effects`, the step diagnosis's effects. This old place
keeps its names for one release, each read with a `DeprecationWarning` naming the new
place."""

from .._deprecated import moved_names

# Moved in 0.2 (CHANGELOG.md): the step diagnosis's modules are the subpackage `step/`.
__getattr__ = moved_names(
    __name__,
    {
        "AbstractStepEffect": "accel_jax.diagnose.step.effects",
        "TorquerLag": "accel_jax.diagnose.step.effects",
        "OutputFilter": "accel_jax.diagnose.step.effects",
        "OFFSET_PRIOR": "accel_jax.diagnose.step.effects",
        "StopSaturation": "accel_jax.diagnose.step.effects",
        "DisturbanceDrift": "accel_jax.diagnose.step.effects",
        "ColoredNoise": "accel_jax.diagnose.step.effects",
        "step_effects": "accel_jax.diagnose.step.effects",
    },
)
