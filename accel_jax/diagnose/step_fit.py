"""The old place of `accel_jax.diagnose.step.fit` (the step fit):
each name warns and forwards, for one release."""

from .._deprecated import moved_names

__getattr__ = moved_names(
    __name__,
    "accel_jax.diagnose.step.fit",
    "REFIT_FIELDS REFIT_BOUND BARRIER GAIN_SIGMA TIMING_PRIOR TIMING_LIMIT DELAY_PRIOR_SIGMA "
    "DELAY_LIMIT SLOT StepContext n_timing timing_terms refitted_device unpack moment_jumps "
    "predict innovation_terms FIT_TOLERANCE BATCH_CHUNK STOP_FIT_MAX_STEPS FIT_MAX_STEPS "
    "CONVERGED_DECREMENT HELD_OUT_ITERATIONS dense_jacobian fit_linear fit_nonlinear",
)
