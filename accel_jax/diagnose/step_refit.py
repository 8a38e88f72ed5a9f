"""Moved to `accel_jax.diagnose.step.refit`, the step diagnosis's report of the refit. This
old place keeps its names for one release, each read with a `DeprecationWarning` naming the
new place."""

from .._deprecated import moved_names

# Moved in 0.2 (CHANGELOG.md): the step diagnosis's modules are the subpackage `step/`.
__getattr__ = moved_names(
    __name__,
    {
        "TRANSIENT_FRACTION": "accel_jax.diagnose.step.refit",
        "KNOWN_FIELDS": "accel_jax.diagnose.step.refit",
    },
)
