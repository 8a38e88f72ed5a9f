"""The old place of `accel_jax.diagnose.step.record` (a step record's preparation):
each name warns and forwards, for one release."""

from .._deprecated import moved_names

__getattr__ = moved_names(
    __name__,
    "accel_jax.diagnose.step.segments",
    "HELD_OUT_EVERY HELD_OUT_FRACTION held_out_samples sequence_key segments time_text",
    "accel_jax.diagnose.step.record",
    "MAX_CHANGES MAX_CLOCKED_CHANGES BLOCK_BUCKET MIN_MAX_BLOCK BLOCKS_PER_PERIOD stack_on_host "
    "CLOCK_TEXT prepare STARTS prior_sigma_of",
    "accel_jax.diagnose.step.state",
    "RecordView",
)
