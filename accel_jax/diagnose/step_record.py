"""Moved to `accel_jax.diagnose.step.record`, the step diagnosis's view of a record (`prepare`
now returns a `StepRecord`). This old place keeps its names for one release, each read with
a `DeprecationWarning` naming the new place."""

from .._deprecated import moved_names

# Moved in 0.2 (CHANGELOG.md): the step diagnosis's modules are the subpackage `step/`.
__getattr__ = moved_names(
    __name__,
    {
        "HELD_OUT_EVERY": "accel_jax.diagnose.step.segments",
        "HELD_OUT_FRACTION": "accel_jax.diagnose.step.segments",
        "MAX_CHANGES": "accel_jax.diagnose.step.record",
        "MAX_CLOCKED_CHANGES": "accel_jax.diagnose.step.record",
        "held_out_samples": "accel_jax.diagnose.step.segments",
        "sequence_key": "accel_jax.diagnose.step.segments",
        "segments": "accel_jax.diagnose.step.segments",
        "time_text": "accel_jax.diagnose.step.segments",
        "BLOCK_BUCKET": "accel_jax.diagnose.step.record",
        "MIN_MAX_BLOCK": "accel_jax.diagnose.step.record",
        "BLOCKS_PER_PERIOD": "accel_jax.diagnose.step.record",
        "stack_on_host": "accel_jax.diagnose.step.record",
        "RecordView": "accel_jax.diagnose.step.state",
        "CLOCK_TEXT": "accel_jax.diagnose.step.record",
        "prepare": "accel_jax.diagnose.step.record",
        "STARTS": "accel_jax.diagnose.step.record",
        "prior_sigma_of": "accel_jax.diagnose.step.record",
    },
)
