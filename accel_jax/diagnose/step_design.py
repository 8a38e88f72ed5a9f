"""Moved to `accel_jax.diagnose.step.design`, the step diagnosis's next experiment for a lag
tie. This old place keeps its names for one release, each read with a `DeprecationWarning`
naming the new place."""

from .._deprecated import moved_names

# Moved in 0.2 (CHANGELOG.md): the step diagnosis's modules are the subpackage `step/`.
__getattr__ = moved_names(
    __name__,
    {
        "experiment_menu": "accel_jax.diagnose.step.design",
        "expected_evidence": "accel_jax.diagnose.step.design",
        "next_experiments": "accel_jax.diagnose.step.design",
    },
)
