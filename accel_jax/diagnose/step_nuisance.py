"""Moved to `accel_jax.diagnose.step.nuisance`, the step diagnosis's joint test of the
nuisances. This old place keeps its names for one release, each read with a
`DeprecationWarning` naming the new place."""

from .._deprecated import moved_names

# Moved in 0.2 (CHANGELOG.md): the step diagnosis's modules are the subpackage `step/`.
__getattr__ = moved_names(
    __name__,
    {
        "NUISANCE_ALPHA": "accel_jax.diagnose.step.nuisance",
        "nuisance_test": "accel_jax.diagnose.step.nuisance",
        "change_shifts": "accel_jax.diagnose.step.nuisance",
        "strained_sentence": "accel_jax.diagnose.step.nuisance",
    },
)
