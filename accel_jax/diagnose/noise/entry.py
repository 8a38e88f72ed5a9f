"""The `noise` kind's entry: `diagnose_noise` prepares each record (`record.prepare`), fits
every candidate of records of one length as one batch (`fit._fit_record`, vmapped in
chunks of `BATCH_CHUNK` records), judges each record (`verdict.evaluate`), and adds the
forward selection of real-sensor effects where the exact verdict leaves a record open and
alone beyond `EXACT_LIMIT` samples (`sensor`). The kind itself is described in the package
`accel_jax.diagnose.noise`.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ..._data import DataError, NoiseData, NominalDevice
from ..._sweep import even_chunk_size, sweep
from ..base import DiagnosisResult, require_float64
from .fit import _bands, _effects, _fit_record
from . import sensor
from .localise import welch
from .record import prepare
from .sensor import EXACT_LIMIT
from .verdict import evaluate

BATCH_CHUNK = 64
"""Records fitted per compiled call (a vmapped batch runs until its slowest fit stops)."""


def diagnose_noise(
    datasets: list[NoiseData], nominal: NominalDevice | None = None
) -> list[DiagnosisResult]:
    """Diagnose static noise records (docs/models.md §5, `noise` kind).

    Records of one length are fitted together (one compilation, every candidate of every
    record vmapped, in chunks of `BATCH_CHUNK` records): Whittle start and exact maximum
    likelihood on the first 2/3 of each record, evidence (2 ln B, BIC scale) against white
    noise, the held-out gap on the last third, and the localisation of the white-noise
    residual in frequency, lag and time. The effects real sensors show beyond those three
    noises (output grid, lines, low-pass, flicker, start-up transient) come from the forward
    selection of `sensor`, which alone diagnoses records longer than `EXACT_LIMIT`
    samples; every result carries the Allan deviation with ±1σ intervals
    (`where["allan"]`).

    **Arguments:**

    - `datasets`: validated `NoiseData` records (e.g. from `read_csv`).
    - `nominal`: ignored (the servo device has no parameter in this kind's nominal model);
        accepted for the common `diagnose` interface.

    **Returns:** one `DiagnosisResult` per record, in order. Float64 (needs x64 enabled;
    a `ValueError` otherwise).
    """
    require_float64("log-likelihoods of thousands of samples are compared to within a unit")
    del nominal
    effects = _effects()
    exact = [i for i, d in enumerate(datasets) if np.asarray(d.a_out).size <= EXACT_LIMIT]
    records = {i: prepare(datasets[i], effects) for i in exact}
    results: list[DiagnosisResult | None] = [None] * len(datasets)
    groups: dict[tuple[int, int], list[int]] = {}
    for i, rec in records.items():
        groups.setdefault((rec.normalised.size, rec.split), []).append(i)
    candidates = jnp.arange(1 + len(effects))
    for (n, split), indices in groups.items():
        normalised = jnp.asarray(np.stack([records[i].normalised for i in indices]))
        guesses = jnp.asarray(np.stack([records[i].guesses for i in indices]))
        mask = jnp.asarray((np.arange(n) < split).astype(np.float64))
        band, n_bands = _bands((n - 1) // 2)
        outputs = sweep(
            _fit_record,
            normalised,
            mask,
            guesses,
            candidates,
            jnp.asarray(band.astype(np.int32)),
            jnp.zeros(n_bands),
            in_axes=(0, None, 0, None, None, None),
            chunk_size=even_chunk_size(len(indices), BATCH_CHUNK),
            desc="diagnose noise",
        )
        outputs = [np.asarray(o) for o in outputs]
        for j, i in enumerate(indices):
            results[i] = evaluate(datasets[i], records[i], effects, [o[j] for o in outputs])
    # Beyond the three noises: the forward selection where the exact verdict leaves it open,
    # on a coarse output grid, and alone on long records (`sensor`).
    done: list[DiagnosisResult] = []
    for data, result in zip(datasets, results, strict=True):
        x = np.asarray(data.a_out, dtype=np.float64)
        dt = float(data.sample_period)
        if result is None:
            try:
                selection = sensor.run_selection(x, dt)
            except ValueError as error:
                raise DataError(f"noise record: {error}") from None
            result = sensor.from_selection(x, np.asarray(data.t), dt, selection, welch)
            result.notes = [*result.notes, *getattr(data, "notes", ())]
        elif sensor.needs_selection(x, result.verdict):
            result = sensor.combine(result, sensor.run_selection(x, dt))
        result.where["allan"] = sensor.allan_summary(x, dt)
        done.append(result)
    return done
