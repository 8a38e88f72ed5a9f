"""Writing a diagnosis: the JSON document of the CLI contract. (Its figures are
`accel_jax.report.figures.diagnosis`.)"""

from __future__ import annotations

import os
from pathlib import Path

from .._deprecated import moved_names
from .._io import write_json_atomic
from .base import DiagnosisResult


def write_json(
    result: DiagnosisResult, path: str | os.PathLike, *, source=None, extra: dict | None = None
) -> Path:
    """Write `result.to_dict()` (plus the source file name and `extra`, e.g. the
    provenance) atomically as JSON."""
    payload = result.to_dict()
    if source is not None:
        payload = {"source": str(source), **payload}
    return write_json_atomic(path, {**payload, **(extra or {})})


# Moved in 0.2 (CHANGELOG.md): the figures are presentation.
__getattr__ = moved_names(
    __name__,
    {
        "figure": "accel_jax.report.figures.diagnosis",
        "save_plot": "accel_jax.report.figures.diagnosis",
        "set_figure": "accel_jax.report.figures.diagnosis",
    },
)
