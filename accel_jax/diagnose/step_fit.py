"""Moved to `accel_jax.diagnose.step.fit`, the step diagnosis's fit: the candidates'
parameters, prediction and least-squares fit (JAX). This old place keeps its names for one
release, each read with a `DeprecationWarning` naming the new place."""

from .._deprecated import moved_names

# Moved in 0.2 (CHANGELOG.md): the step diagnosis's modules are the subpackage `step/`.
__getattr__ = moved_names(
    __name__,
    {
        "REFIT_FIELDS": "accel_jax.diagnose.step.fit",
        "REFIT_BOUND": "accel_jax.diagnose.step.fit",
        "BARRIER": "accel_jax.diagnose.step.fit",
        "GAIN_SIGMA": "accel_jax.diagnose.step.fit",
        "TIMING_PRIOR": "accel_jax.diagnose.step.fit",
        "TIMING_LIMIT": "accel_jax.diagnose.step.fit",
        "DELAY_PRIOR_SIGMA": "accel_jax.diagnose.step.fit",
        "DELAY_LIMIT": "accel_jax.diagnose.step.fit",
        "SLOT": "accel_jax.diagnose.step.fit",
        "StepContext": "accel_jax.diagnose.step.fit",
        "n_timing": "accel_jax.diagnose.step.fit",
        "timing_terms": "accel_jax.diagnose.step.fit",
        "refitted_device": "accel_jax.diagnose.step.fit",
        "unpack": "accel_jax.diagnose.step.fit",
        "moment_jumps": "accel_jax.diagnose.step.fit",
        "predict": "accel_jax.diagnose.step.fit",
        "innovation_terms": "accel_jax.diagnose.step.fit",
        "FIT_TOLERANCE": "accel_jax.diagnose.step.fit",
        "BATCH_CHUNK": "accel_jax.diagnose.step.fit",
        "STOP_FIT_MAX_STEPS": "accel_jax.diagnose.step.fit",
        "FIT_MAX_STEPS": "accel_jax.diagnose.step.fit",
        "CONVERGED_DECREMENT": "accel_jax.diagnose.step.fit",
        "HELD_OUT_ITERATIONS": "accel_jax.diagnose.step.fit",
        "dense_jacobian": "accel_jax.diagnose.step.fit",
        "fit_linear": "accel_jax.diagnose.step.fit",
        "fit_nonlinear": "accel_jax.diagnose.step.fit",
    },
)
