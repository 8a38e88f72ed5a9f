"""Moved to `accel_jax.diagnose.step.joint_verdict`, the step diagnosis's verdict of several
records of one device. This old place keeps its names for one release, each read with a
`DeprecationWarning` naming the new place."""

from .._deprecated import moved_names

# Moved in 0.2 (CHANGELOG.md): the step diagnosis's modules are the subpackage `step/`.
__getattr__ = moved_names(
    __name__,
    {
        "SetDiagnosis": "accel_jax.diagnose.step.joint_verdict",
        "diagnose_step_set": "accel_jax.diagnose.step.joint_verdict",
    },
)
