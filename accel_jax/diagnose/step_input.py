"""The old place of `accel_jax.diagnose.step.inputs` (a measured input read as plateaus):
each name warns and forwards, for one release."""

from .._deprecated import moved_names

__getattr__ = moved_names(
    __name__,
    "accel_jax.diagnose.step.inputs",
    "MIN_PLATEAU STEADY_SIGMAS MERGE_SIGMAS STEADY_SHARE DRIFT_SIGMAS SPREAD_SIGMAS DRIFT_SHARE "
    "InputReading UNCLOCKED_CHANGES read_input Clock CLOCK_TOLERANCE clock_grid level_groups "
    "StepInputs read_inputs",
)
