"""The old place of `accel_jax.diagnose.step.joint` (the joint fit of several records):
each name warns and forwards, for one release."""

from .._deprecated import moved_names

__getattr__ = moved_names(
    __name__,
    "accel_jax.diagnose.step.joint",
    "CANDIDATES STOP_SIGMA ACCEL_SIGMA OFFSET_PRIOR STOP_REACH LAG_BOUND LAG_STARTS MAX_STEPS "
    "NOMINAL_MAX_STEPS TOLERANCE N_SHARED N_LAG_STATES SetLayout nominal_stop_voltage PreparedSet "
    "prepare_set stack fit_set shared_values release_lag_states",
    "accel_jax.diagnose.step.joint_verdict",
    "SetDiagnosis diagnose_step_set",
    "accel_jax.diagnose.step.design",
    "experiment_menu expected_evidence next_experiments",
    "accel_jax.report.figures.diagnosis",
    "set_figure",
)
