"""Moved to `accel_jax.diagnose.step.joint`, the step diagnosis's joint fit of several records
of one device. This old place keeps its names for one release, each read with a
`DeprecationWarning` naming the new place."""

from .._deprecated import moved_names

# Moved in 0.2 (CHANGELOG.md): the step diagnosis's modules are the subpackage `step/`.
__getattr__ = moved_names(
    __name__,
    {
        "CANDIDATES": "accel_jax.diagnose.step.joint",
        "STOP_SIGMA": "accel_jax.diagnose.step.joint",
        "ACCEL_SIGMA": "accel_jax.diagnose.step.joint",
        "OFFSET_PRIOR": "accel_jax.diagnose.step.joint",
        "STOP_REACH": "accel_jax.diagnose.step.joint",
        "LAG_BOUND": "accel_jax.diagnose.step.joint",
        "LAG_STARTS": "accel_jax.diagnose.step.joint",
        "MAX_STEPS": "accel_jax.diagnose.step.joint",
        "NOMINAL_MAX_STEPS": "accel_jax.diagnose.step.joint",
        "TOLERANCE": "accel_jax.diagnose.step.joint",
        "N_SHARED": "accel_jax.diagnose.step.joint",
        "N_LAG_STATES": "accel_jax.diagnose.step.joint",
        "SetLayout": "accel_jax.diagnose.step.joint",
        "nominal_stop_voltage": "accel_jax.diagnose.step.joint",
        "PreparedSet": "accel_jax.diagnose.step.joint",
        "prepare_set": "accel_jax.diagnose.step.joint",
        "stack": "accel_jax.diagnose.step.joint",
        "fit_set": "accel_jax.diagnose.step.joint",
        "shared_values": "accel_jax.diagnose.step.joint",
        "release_lag_states": "accel_jax.diagnose.step.joint",
        "SetDiagnosis": "accel_jax.diagnose.step.joint_verdict",
        "diagnose_step_set": "accel_jax.diagnose.step.joint_verdict",
        "experiment_menu": "accel_jax.diagnose.step.design",
        "expected_evidence": "accel_jax.diagnose.step.design",
        "next_experiments": "accel_jax.diagnose.step.design",
        "set_figure": "accel_jax.report.figures.diagnosis",
    },
)
