"""The `vibration` kind's entry: `diagnose_vibration` prepares each table (`table.prepare`),
fits every candidate on all rows and every cross-validation fold of the tables of one size
and one set of candidates as one batch (`fit.fit_tables`), and judges each table
(`verdict.evaluate`). The kind itself is described in the package
`accel_jax.diagnose.vibration`.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ..._data import NominalDevice, VibrationData
from ..base import DiagnosisResult, require_float64
from .effects import vibration_effects
from .fit import fit_tables
from .table import prepare
from .verdict import evaluate


def diagnose_vibration(
    datasets: list[VibrationData], nominal: NominalDevice | None = None
) -> list[DiagnosisResult]:
    """Diagnose vibration tables (docs/models.md §5, `vibration` kind).

    For each table: the exact-expectation design matrix (`accel_jax._vibration`), then the
    nominal model and each available effect fitted to all rows and to every
    cross-validation fold (one vmapped optimistix call for every table with the same
    number of rows), the ranking by evidence (`rank_candidates`), the held-out gap on the
    cross-validated rows, and the localisation of the nominal residual across conditions.

    **Arguments:**

    - `datasets`: validated `VibrationData` tables (e.g. from `read_csv`).
    - `nominal`: ignored (the servo device has no parameter in this kind's nominal model);
        accepted for the common `diagnose` interface.

    **Returns:** one `DiagnosisResult` per table, in order. Float64 (needs x64 enabled;
    a `ValueError` otherwise).
    """
    require_float64("vibration errors are ppm-level differences of O(1 g) outputs")
    del nominal
    effects = vibration_effects()
    tables = [prepare(data, effects) for data in datasets]
    results: dict[int, DiagnosisResult] = {}  # by table, every one in one group
    groups: dict[tuple, list[int]] = {}
    for i, table in enumerate(tables):
        key = (table.design.shape[0], table.candidates)
        groups.setdefault(key, []).append(i)
    for indices in groups.values():
        stack = lambda name, indices=indices: jnp.asarray(  # noqa: E731
            np.stack([getattr(tables[i], name) for i in indices])
        )
        thetas, converged = fit_tables(
            stack("design"), stack("target"), stack("masks"), stack("weights")
        )
        thetas, converged = np.asarray(thetas), np.asarray(converged)
        for j, i in enumerate(indices):
            results[i] = evaluate(datasets[i], tables[i], effects, thetas[j], converged[j])
    return [results[i] for i in range(len(datasets))]
