"""The vibration diagnosis's typed state of one table (host side, NumPy): what
`table.prepare` reads from it (`VibrationTable`).

A frozen dataclass: a stage that changes one makes a new one with `dataclasses.replace`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import numpy as np


@dataclasses.dataclass(frozen=True, eq=False)
class VibrationTable:
    """One table as the fit sees it (`table.prepare`).

    **Fields:** `design` the exact-expectation design matrix, rows × `COEFFICIENTS`, per ppm
    of each coefficient; `target` (a_out − a_in) in ppm of 1 g; `masks` one row per
    candidate, 1 where a coefficient is free; `weights` one row per fit, 1 where a row is
    fitted (first all rows, then one row per cross-validation fold, which leaves its rows
    out); `candidates` the candidates' names, "nominal" first; `free` the design columns
    each available effect frees beyond the nominal's; `nominal_columns` the nominal's
    columns (the bias, and the scale factor where the table can tell it from the bias);
    `fold_of_row` each row's cross-validation fold; `unavailable` why each effect the table
    cannot show is left out, by name; `notes` what the reader is told about the table.
    """

    design: np.ndarray
    target: np.ndarray
    masks: np.ndarray
    weights: np.ndarray
    candidates: tuple[str, ...]
    free: Mapping[str, list[int]]
    nominal_columns: tuple[int, ...]
    fold_of_row: np.ndarray
    unavailable: Mapping[str, str]
    notes: tuple[str, ...]

    @property
    def folds(self) -> int:
        """The number of cross-validation folds."""
        return len(self.weights) - 1
