"""The old place of `accel_jax.diagnose.step.joint_verdict` (the joint verdict):
each name warns and forwards, for one release."""

from .._deprecated import moved_names

__getattr__ = moved_names(
    __name__,
    "accel_jax.diagnose.step.joint_verdict",
    "SetDiagnosis diagnose_step_set",
)
