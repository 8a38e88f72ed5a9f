"""Moved to `accel_jax.diagnose.step.assess`, the step diagnosis's assessment of each
candidate. This old place keeps its names for one release, each read with a
`DeprecationWarning` naming the new place."""

from .._deprecated import moved_names

# Moved in 0.2 (CHANGELOG.md): the step diagnosis's modules are the subpackage `step/`.
__getattr__ = moved_names(
    __name__,
    {
        "NOISE_VARIANCE_FACTOR": "accel_jax.diagnose.step.assess",
        "fit_entries": "accel_jax.diagnose.step.assess",
        "NESTED_TOLERANCE": "accel_jax.diagnose.step.assess",
        "NESTED_ABSOLUTE": "accel_jax.diagnose.step.assess",
        "nested_shortfall": "accel_jax.diagnose.step.assess",
        "nested_failed": "accel_jax.diagnose.step.assess",
        "nested_losers": "accel_jax.diagnose.step.assess",
        "evidence_slack": "accel_jax.diagnose.step.assess",
        "explains_deterministically": "accel_jax.diagnose.step.assess",
    },
)
