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
from .discover import discover_table, weigh
from .effects import vibration_effects
from .fit import fit_tables
from .table import MAX_FOLDS, padded_rows, prepare
from .verdict import evaluate


def _padded(table, name: str, rows: int) -> np.ndarray:
    """A table's fit input `name` padded to `rows` rows (zero rows, of weight 0 in every
    fit) and, for the weightings, to the largest fold count (copies of the all-rows one):
    tables of several sizes share one compiled fit."""
    x = getattr(table, name)
    if name == "design":
        return np.pad(x, ((0, rows - x.shape[0]), (0, 0)))
    if name == "target":
        return np.pad(x, (0, rows - x.shape[0]))
    if name == "weights":
        x = np.pad(x, ((0, 0), (0, rows - x.shape[1])))
        return np.concatenate([x, np.repeat(x[:1], 1 + MAX_FOLDS - x.shape[0], axis=0)])
    return x


def diagnose_vibration(
    datasets: list[VibrationData], nominal: NominalDevice | None = None, *, discover=False
) -> list[DiagnosisResult]:
    """Diagnose vibration tables (docs/models.md §5, `vibration` kind).

    For each table: the exact-expectation design matrix (`accel_jax._vibration`), then the
    nominal model and each available effect fitted to all rows and to every
    cross-validation fold (one vmapped optimistix call for the tables of one set of
    candidates whose rows pad to one power of two, `table.padded_rows`), the ranking by
    evidence (`rank_candidates`), the held-out gap on the cross-validated rows, and the
    localisation of the nominal residual across conditions.

    **Arguments:**

    - `datasets`: validated `VibrationData` tables (e.g. from `read_csv`).
    - `nominal`: ignored (the servo device has no parameter in this kind's nominal model);
        accepted for the common `diagnose` interface.
    - `discover`: also look for a missing term in every table (True or "all": the same
        here; `vibration.discover`), which can make the verdict `unexplained` where terms
        beyond the library fit the table better than the named effect (`discover.weigh`).

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
        key = (padded_rows(table.design.shape[0]), table.candidates)
        groups.setdefault(key, []).append(i)
    for (rows, _), indices in groups.items():

        def stack(name, indices=indices, rows=rows):
            return jnp.asarray(np.stack([_padded(tables[i], name, rows) for i in indices]))

        thetas, converged = fit_tables(
            stack("design"), stack("target"), stack("masks"), stack("weights")
        )
        thetas, converged = np.asarray(thetas), np.asarray(converged)
        for j, i in enumerate(indices):
            results[i] = evaluate(datasets[i], tables[i], effects, thetas[j], converged[j])
    if discover:
        for i, result in results.items():
            floor = float(result.remaining_gap["noise_floor_g"]) ** 2
            weigh(result, discover_table(datasets[i], tables[i], floor), effects)
    return [results[i] for i in range(len(datasets))]
