"""Moved to `accel_jax.diagnose.step.inputs`, the step diagnosis's reading of a measured input
as plateaus. This old place keeps its names for one release, each read with a
`DeprecationWarning` naming the new place."""

from .._deprecated import moved_names

# Moved in 0.2 (CHANGELOG.md): the step diagnosis's modules are the subpackage `step/`.
__getattr__ = moved_names(
    __name__,
    {
        "MIN_PLATEAU": "accel_jax.diagnose.step.inputs",
        "STEADY_SIGMAS": "accel_jax.diagnose.step.inputs",
        "MERGE_SIGMAS": "accel_jax.diagnose.step.inputs",
        "STEADY_SHARE": "accel_jax.diagnose.step.inputs",
        "DRIFT_SIGMAS": "accel_jax.diagnose.step.inputs",
        "SPREAD_SIGMAS": "accel_jax.diagnose.step.inputs",
        "DRIFT_SHARE": "accel_jax.diagnose.step.inputs",
        "InputReading": "accel_jax.diagnose.step.inputs",
        "UNCLOCKED_CHANGES": "accel_jax.diagnose.step.inputs",
        "read_input": "accel_jax.diagnose.step.inputs",
        "Clock": "accel_jax.diagnose.step.inputs",
        "CLOCK_TOLERANCE": "accel_jax.diagnose.step.inputs",
        "clock_grid": "accel_jax.diagnose.step.inputs",
        "level_groups": "accel_jax.diagnose.step.inputs",
        "StepInputs": "accel_jax.diagnose.step.inputs",
        "read_inputs": "accel_jax.diagnose.step.inputs",
    },
)
