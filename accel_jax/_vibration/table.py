"""Tables of vibration tests (one row per shaker/tumble test condition): the columns
(`TABLE_COLUMNS` and the optional cross-axis amplitudes), their validation
(`validate_vibration_table`) and CSV reading/writing in the data layer's `vibration`
format, through `accel_jax._data`'s CSV reader and writer; and a vibration environment's band
PSDs (`read_band_spectrum`).
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from .._data import (
    COLUMNS,
    OPTIONAL_COLUMNS,
    UNITS,
    DataError,
    VibrationData,
    _parse_columns,
    _read_text,
    write_csv,
)
from .environment import BandSpectrum

TABLE_COLUMNS = COLUMNS["vibration"]
"""Required columns of a `vibration` CSV table: the input-axis acceleration a_in [g], the
sinusoidal vibration amplitude along the input axis vib_amp [g] and its frequency vib_freq
[Hz], the RMS of the random vibration vib_rms [g] (0 if none) and the mean indicated
acceleration a_out [g]. Optional: vib_amp_oa, vib_amp_pa [g], sinusoidal vibration on the
output and pendulum axes in phase with vib_amp (they make m31, m32 identifiable)."""
_OPTIONAL_COLUMNS = OPTIONAL_COLUMNS["vibration"]
_TABLE_UNITS = UNITS  # column → unit, as for every CSV record


def validate_vibration_table(table: dict) -> dict[str, np.ndarray]:
    """Check a test table (a mapping column → 1-D array) and return float64 NumPy columns.

    Raises ValueError naming the column, the offending value and its unit: missing
    columns, unequal lengths, non-finite values, negative amplitudes/RMS, non-positive
    frequency where a sinusoid is applied.
    """
    missing = [c for c in TABLE_COLUMNS if c not in table]
    if missing:
        raise ValueError(
            f"vibration table: missing column(s) {missing}; required {list(TABLE_COLUMNS)}."
        )
    cols = {
        c: np.atleast_1d(np.asarray(table[c], dtype=np.float64))
        for c in TABLE_COLUMNS + tuple(c for c in _OPTIONAL_COLUMNS if c in table)
    }
    lengths = {c: v.shape for c, v in cols.items()}
    if len(set(lengths.values())) != 1 or len(next(iter(lengths.values()))) != 1:
        raise ValueError(f"vibration table: columns must be 1-D of equal length, got {lengths}.")
    for c, v in cols.items():
        bad = ~np.isfinite(v)
        if c in ("vib_amp", "vib_rms") + _OPTIONAL_COLUMNS:
            bad |= v < 0
        if c == "vib_freq":
            bad |= (cols["vib_amp"] > 0) & ~(v > 0)
        if np.any(bad):
            i = int(np.argmax(bad))
            raise ValueError(
                f"vibration table: column {c!r} row {i} has {float(v[i])!r} {_TABLE_UNITS[c]}; "
                "values must be finite, amplitudes/RMS non-negative, frequencies positive "
                "where a sinusoid is applied."
            )
    return cols


def read_vibration_table(path) -> dict[str, np.ndarray]:
    """Read a `vibration` CSV table (header row with the `TABLE_COLUMNS` names, any order,
    optionally `vib_amp_oa`, `vib_amp_pa`) with the data layer's CSV reader and validate it
    (`validate_vibration_table`).

    A file that cannot be read or parsed (no such file, missing, unknown or duplicated
    columns, rows of the wrong length, non-numeric text) raises `accel_jax.DataError` (a
    `ValueError`) naming the file; bad values raise `validate_vibration_table`'s ValueError.
    """
    path = Path(path)
    _, columns = _parse_columns(_read_text(path), kind="vibration", path=path)
    return validate_vibration_table(columns)


def write_vibration_table(path, table: dict) -> None:
    """Write a validated test table as CSV (the `vibration` format), with the data layer's
    writer (`accel_jax.write_csv`: full float64 precision, atomically)."""
    cols = validate_vibration_table(table)
    write_csv(path, VibrationData(**cols))


def read_band_spectrum(path) -> BandSpectrum:
    """Read a band-PSD CSV (header f_low,f_high,psd[,eta]; Hz, Hz, g²/Hz, 1) as a
    `BandSpectrum`. A file that cannot be read, has no bands, misses a column or holds a
    non-numeric or invalid value raises `accel_jax.DataError` naming the file."""
    try:
        with open(path, newline="") as handle:
            rows = list(csv.DictReader(handle))
    except FileNotFoundError:
        raise DataError(f"{path}: no such file.") from None
    except (OSError, UnicodeDecodeError, csv.Error) as error:
        raise DataError(f"{path}: cannot be read ({error}).") from None
    if not rows:
        raise DataError(f"{path}: no bands (a header f_low,f_high,psd[,eta] and rows).")
    missing = {"f_low", "f_high", "psd"} - set(rows[0])
    if missing:
        raise DataError(
            f"{path}: missing column(s) {sorted(missing)}; expected f_low,f_high,psd[,eta] "
            "(Hz, Hz, g²/Hz, 1)."
        )
    columns = {}
    for name in ("f_low", "f_high", "psd", "eta"):
        if name not in rows[0]:
            continue
        try:
            columns[name] = [float(row[name]) for row in rows]
        except (TypeError, ValueError):
            raise DataError(f"{path}: column {name!r} has a non-numeric value.") from None
    try:
        return BandSpectrum(**columns)
    except ValueError as error:
        raise DataError(f"{path}: {error}") from None
