"""Reading and validating the data a user brings (docs/models.md §5): CSV records and TOML devices.

One experiment per CSV file, a header row, SI units (accelerations in g). The kind of
experiment is inferred from the columns:

- `step`: a closed-loop test-signal record — `t` [s], `u_test` [V], `u_out` [V]; uniform
  sampling, the test voltage held constant between samples; optionally `a_in` [g], a
  piecewise-constant acceleration along the input axis (a tilt or a centrifuge step), with
  or without a test-voltage change;
- `vibration`: one row per shaker/tumble test condition — `a_in` [g], `vib_amp` [g],
  `vib_freq` [Hz], `vib_rms` [g], `a_out` [g]; optionally `vib_amp_oa`, `vib_amp_pa` [g],
  sinusoidal vibration on the output and pendulum axes in phase with `vib_amp` (they make
  the cross-coupling m31, m32 observable);
- `noise`: a static record — `t` [s], `a_out` [g].

Every problem with the input raises one error type, `DataError` (a `ValueError`), whose
message is one line naming the file, the row or column and the value found.

A device file (TOML) gives the nominal `ServoParams` and the relative uncertainty of each
value. Each key is a `ServoParams` field; its value is a number (the value, with the default
uncertainty) or a table `{ value = ..., uncertainty = ... }` (uncertainty relative, e.g.
0.05 for ±5 %). Unknown keys are an error.

All arrays are NumPy float64: this layer runs on the host before any JAX computation.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import math
import os
from pathlib import Path
from typing import Literal, overload

import equinox as eqx
import numpy as np

from ._format import precise
from ._io import _atomic_write_bytes
from ._params import REFERENCE_VALUES, ServoParams

COLUMNS: dict[str, tuple[str, ...]] = {
    "step": ("t", "u_test", "u_out"),
    "vibration": ("a_in", "vib_amp", "vib_freq", "vib_rms", "a_out"),
    "noise": ("t", "a_out"),
}
"""The columns of each kind of record, in the order written by `write_csv`."""

OPTIONAL_COLUMNS: dict[str, tuple[str, ...]] = {
    "step": ("a_in",),
    "vibration": ("vib_amp_oa", "vib_amp_pa"),
    "noise": (),
}
"""Columns a record of each kind may have in addition (written after `COLUMNS` when
present): for `step`, the acceleration along the input axis `a_in` [g] (piecewise
constant: a tilt or centrifuge step); for `vibration`, the in-phase sinusoidal amplitudes
on the output (OA) and pendulum (PA) axes [g], which `accel_jax._vibration` uses for the
cross-coupling terms m31, m32."""

UNITS: dict[str, str] = {
    "t": "s",
    "u_test": "V",
    "u_out": "V",
    "a_in": "g",
    "vib_amp": "g",
    "vib_freq": "Hz",
    "vib_rms": "g",
    "a_out": "g",
    "vib_amp_oa": "g",
    "vib_amp_pa": "g",
}

MIN_SAMPLES: dict[str, int] = {"step": 200, "vibration": 8, "noise": 256}

MAX_MAGNITUDE = 1e30
"""The largest size a record's value may have (in its column's unit): no measurement is
near it, and the fits' squares and sums of values of 1e160 and beyond overflow float64."""
"""The fewest samples (rows) each kind needs: a step record several input changes long, a
vibration table with more rows than the largest effect has parameters, a noise record long
enough for an autocorrelation out to a few correlation times."""

UNCERTAIN_BY_DEFAULT: dict[str, float] = {
    "moment_of_inertia": 0.05,
    "damping": 0.05,
    "stiffness": 0.05,
    "torquer_gain": 0.05,
}
"""Relative (1σ) uncertainty of the reference device's values (docs/models.md §5): J, μ, c and k_dm
are known to ±5 %; the other values are taken as exact."""

# Relative uncertainty above which a log-normal prior of that width is meaningless here.
_MAX_UNCERTAINTY = 1.0
# Relative deviation of the sample spacing from the mean that counts as non-uniform.
_UNIFORM_TOLERANCE = 1e-6


class DataError(ValueError):
    """Bad user input: a CSV record or a device file that cannot be used as it is.

    The message is one line that names the file, the place and the value found.
    """


def _where(path) -> str:
    return str(path) if path is not None else "<data>"


class StepData(eqx.Module):
    """A closed-loop test-signal record.

    **Fields:**

    - `t`: sample times [s], shape (n,), uniform.
    - `u_test`: test voltage U_test [V], shape (n,), held constant from each sample to the next.
    - `u_out`: output voltage U_out [V], shape (n,).
    - `notes`: what reading the record changed or assumed (e.g. timestamps taken as their
        uniform grid), for the diagnosis to report.
    - `a_in`: optional acceleration along the input axis [g], shape (n,), held constant
        from each sample to the next (a tilt or a centrifuge step); None when the record
        has no such column.
    - `input_delay`: the input channels' known delay behind `u_out`'s [s] (a multiplexed
        ADC's skew, an anti-alias filter's group delay, a driver's dead time): the inputs
        act that much earlier than their columns show. None (the default): unknown, and
        for a measured input fitted as a nuisance (where it can take up a lag of the loop
        of about its own size). Not a column: set it in code or with `accel-jax diagnose
        --input-delay`.
    """

    t: np.ndarray
    u_test: np.ndarray
    u_out: np.ndarray
    notes: tuple = eqx.field(static=True, default=())
    a_in: np.ndarray | None = None
    input_delay: float | None = eqx.field(static=True, default=None)
    kind = "step"

    @property
    def sample_period(self) -> float:
        """The (uniform) sample spacing [s]."""
        return float((self.t[-1] - self.t[0]) / (len(self.t) - 1))


class VibrationData(eqx.Module):
    """A table of vibration (shaker or tumble) tests, one row per test condition.

    **Fields:** `a_in` [g] applied along the input axis, `vib_amp` [g] sinusoidal amplitude,
    `vib_freq` [Hz], `vib_rms` [g] random part, `a_out` [g] mean indicated acceleration; each
    shape (rows,). Optional (None when the table has no such column): `vib_amp_oa`,
    `vib_amp_pa` [g], sinusoidal amplitudes on the output and pendulum axes, in phase with
    `vib_amp`.
    """

    a_in: np.ndarray
    vib_amp: np.ndarray
    vib_freq: np.ndarray
    vib_rms: np.ndarray
    a_out: np.ndarray
    vib_amp_oa: np.ndarray | None = None
    vib_amp_pa: np.ndarray | None = None
    kind = "vibration"

    def table(self) -> dict[str, np.ndarray]:
        """The columns as a dict (the optional ones only when present), as
        `accel_jax._vibration`'s table functions take them."""
        names = COLUMNS["vibration"] + OPTIONAL_COLUMNS["vibration"]
        return {c: getattr(self, c) for c in names if getattr(self, c) is not None}


class NoiseData(eqx.Module):
    """A static record: sample times `t` [s] (uniform) and the indicated acceleration
    `a_out` [g], each shape (n,); `notes` as `StepData`'s."""

    t: np.ndarray
    a_out: np.ndarray
    notes: tuple = eqx.field(static=True, default=())
    kind = "noise"

    @property
    def sample_period(self) -> float:
        """The (uniform) sample spacing [s]."""
        return float((self.t[-1] - self.t[0]) / (len(self.t) - 1))


Dataset = StepData | VibrationData | NoiseData
_CLASSES = {"step": StepData, "vibration": VibrationData, "noise": NoiseData}


def infer_kind(columns, *, path=None) -> str:
    """The kind of record whose columns are exactly `columns` (any order).

    Raises `DataError` for unknown columns, duplicates, or a set that matches no kind (the
    message names the closest kind and what it misses).
    """
    columns = [str(c) for c in columns]
    where = _where(path)
    known = set().union(*COLUMNS.values(), *OPTIONAL_COLUMNS.values())
    unknown = [c for c in columns if c not in known]
    if unknown:
        raise DataError(
            f"{where}: unknown column(s) {unknown}; the known columns are "
            + "; ".join(f"{k}: {', '.join(v)}" for k, v in COLUMNS.items())
            + "."
        )
    duplicated = sorted({c for c in columns if columns.count(c) > 1})
    if duplicated:
        raise DataError(f"{where}: duplicated column(s) {duplicated}.")
    given = set(columns)
    for kind, expected in COLUMNS.items():
        if set(expected) <= given <= set(expected) | set(OPTIONAL_COLUMNS[kind]):
            return kind
    # The closest kind: the one sharing most columns (ties broken by fewest extra columns).
    kind = max(COLUMNS, key=lambda k: (len(given & set(COLUMNS[k])), -len(given - set(COLUMNS[k]))))
    missing = [c for c in COLUMNS[kind] if c not in given]
    extra = [c for c in columns if c not in COLUMNS[kind] + OPTIONAL_COLUMNS[kind]]
    detail = f"missing column(s) {missing}" if missing else ""
    if extra:
        detail += ("; " if detail else "") + f"column(s) {extra} do not belong to it"
    raise DataError(
        f"{where}: the columns {columns} match no kind of record; closest is {kind!r} "
        f"({', '.join(COLUMNS[kind])}): {detail}."
    )


JITTER_LIMIT = 0.05
"""Timestamps within this fraction of the sample interval of a uniform grid (e.g. rounded
when the file was written) are taken as that grid, with a note; larger deviations are an
error (the record is not uniformly sampled)."""


def _check_time(t: np.ndarray, where: str) -> tuple[np.ndarray, list[str]]:
    """The uniform grid the times lie on, and notes; `DataError` if they do not.

    The grid is the least-squares line t_0 + kΔ through the timestamps. Deviations of at
    most `JITTER_LIMIT`·Δ (rounding in a CSV, a logger's timestamp jitter) are accepted and
    the grid is used, with a note when they exceed float rounding."""
    spacing = np.diff(t)
    bad = np.flatnonzero(spacing <= 0)
    if bad.size:
        i = int(bad[0])
        raise DataError(
            f"{where}: time must increase strictly; row {i + 3} has "
            f"t = {precise(float(t[i + 1]))} s after t = {precise(float(t[i]))} s."
        )
    k = np.arange(t.size, dtype=np.float64)
    step, start = np.polyfit(k, t, 1)
    grid = start + step * k
    deviation = np.abs(t - grid)
    worst = int(np.argmax(deviation))
    rounding = _UNIFORM_TOLERANCE * step + 8 * np.finfo(np.float64).eps * np.max(np.abs(t))
    if deviation[worst] <= rounding:
        return t, []
    if deviation[worst] > JITTER_LIMIT * step:
        i = int(np.argmax(np.abs(spacing - step)))
        raise DataError(
            f"{where}: sampling must be uniform; row {worst + 2} is "
            f"{float(deviation[worst] / step):.3g} sample intervals off the uniform grid "
            f"(more than {JITTER_LIMIT:.0%}; the spacing between rows {i + 2} and {i + 3} is "
            f"{precise(float(spacing[i]))} s, the mean {precise(float(step))} s). Resample the "
            "record onto a uniform grid."
        )
    note = (
        f"timestamps deviate from a uniform grid by up to {deviation[worst] / step:.1%} of "
        f"the {float(step):.6g} s interval (rounded in the file?); the record is used on the "
        f"grid t = {float(start):.9g} s + k·{float(step):.9g} s"
    )
    return grid, [note]


MAX_INPUT_DELAY_SHARE = 0.05
"""The largest known input delay a step record takes, as a share of its length."""


def check_input_delay(delay, span: float, where: str = "step record") -> float | None:
    """A step record's known input delay [s] (`StepData.input_delay`) as a float, or None;
    `DataError` unless it is finite and at most `MAX_INPUT_DELAY_SHARE` of the record's
    length `span` [s] in size."""
    if delay is None:
        return None
    try:
        value = float(delay)
    except (TypeError, ValueError):
        raise DataError(f"{where}: the input delay {delay!r} is not a number (seconds).") from None
    if not (math.isfinite(value) and abs(value) <= MAX_INPUT_DELAY_SHARE * span):
        raise DataError(
            f"{where}: the input delay {precise(value)} s must be a finite number of at most "
            f"{MAX_INPUT_DELAY_SHARE:g} of the record's {precise(span)} s in size (a channel's "
            "delay is a few samples)."
        )
    return value


def with_input_delay(data: Dataset, delay: float | None, *, path=None) -> Dataset:
    """`data` with its inputs' known delay [s] set (`StepData.input_delay`; None: unset,
    `data` as it is); `DataError` for a record of another kind or a delay `validate`
    refuses."""
    if delay is None:
        return data
    if not isinstance(data, StepData):
        raise DataError(f"{_where(path)}: an input delay is given only for step records.")
    return validate(dataclasses.replace(data, input_delay=delay), path=path)


def validate(data: Dataset, *, path=None) -> Dataset:
    """Check a dataset's values (finite, enough samples, uniform increasing time, non-negative
    vibration amplitudes and frequencies) and return it; raise `DataError` otherwise."""
    where = _where(path)
    kind = data.kind
    columns = COLUMNS[kind] + tuple(
        c for c in OPTIONAL_COLUMNS[kind] if getattr(data, c, None) is not None
    )
    arrays = {c: np.asarray(getattr(data, c), dtype=np.float64) for c in columns}
    lengths = {c: a.shape for c, a in arrays.items()}
    n = len(arrays[columns[0]])
    if any(a.ndim != 1 or len(a) != n for a in arrays.values()):
        raise DataError(f"{where}: columns must be 1-D and of one length, got shapes {lengths}.")
    minimum = MIN_SAMPLES[kind]
    if n < minimum:
        what = "rows" if kind == "vibration" else "samples"
        raise DataError(f"{where}: a {kind!r} record needs at least {minimum} {what}, got {n}.")
    for column, values in arrays.items():
        bad = np.flatnonzero(~np.isfinite(values))
        if bad.size:
            i = int(bad[0])
            raise DataError(
                f"{where}: column {column!r} row {i + 2} is {precise(float(values[i]))} "
                f"{UNITS[column]}; "
                "every value must be a finite number."
            )
        big = np.flatnonzero(np.abs(values) > MAX_MAGNITUDE)
        if big.size:
            i = int(big[0])
            raise DataError(
                f"{where}: column {column!r} row {i + 2} is {precise(float(values[i]))} "
                f"{UNITS[column]}; no value may exceed {precise(MAX_MAGNITUDE)} in size (not a "
                "measurement: check the file's values and units)."
            )
    notes = list(getattr(data, "notes", ()))
    if "t" in arrays:
        arrays["t"], time_notes = _check_time(arrays["t"], where)
        notes += time_notes
    if kind == "vibration":
        for column in ("vib_amp", "vib_freq", "vib_rms") + OPTIONAL_COLUMNS[kind]:
            if column not in arrays:
                continue
            bad = np.flatnonzero(arrays[column] < 0)
            if bad.size:
                i = int(bad[0])
                raise DataError(
                    f"{where}: column {column!r} row {i + 2} is "
                    f"{precise(float(arrays[column][i]))} "
                    f"{UNITS[column]}; it must be non-negative."
                )
    if kind == "step" and np.ptp(arrays["u_test"]) == 0:
        if "a_in" not in arrays:
            raise DataError(
                f"{where}: u_test is constant ({precise(float(arrays['u_test'][0]))} V); a step "
                "record needs at least one change of the test voltage (or an a_in column with "
                "an acceleration step)."
            )
        if np.ptp(arrays["a_in"]) == 0:
            raise DataError(
                f"{where}: u_test and a_in are both constant; a step record needs at least one "
                "change of the test voltage or of the acceleration."
            )
    if kind == "step":
        span = float(arrays["t"][-1] - arrays["t"][0])
        delay = check_input_delay(getattr(data, "input_delay", None), span, where)
        return _CLASSES[kind](**arrays, notes=tuple(notes), input_delay=delay)
    if kind == "noise":
        return _CLASSES[kind](**arrays, notes=tuple(notes))
    return _CLASSES[kind](**arrays)


def parse_csv(text: str, *, kind: str | None = None, path=None) -> Dataset:
    """Parse CSV text (a header row, then numbers) into a validated dataset.

    **Arguments:**

    - `text`: the file's contents.
    - `kind`: `"step"`, `"vibration"` or `"noise"` to force the kind (the columns must then
        be exactly that kind's); `None` infers it from the columns.
    - `path`: the file name, for messages only.

    **Returns:** a `StepData`, `VibrationData` or `NoiseData` (float64 NumPy arrays).

    Raises `DataError` (one line) for an empty file, missing, unknown or duplicated columns,
    rows of the wrong length, non-numeric text, NaN/inf, too few samples, and non-monotonic
    or non-uniform time.
    """
    kind, arrays = _parse_columns(text, kind=kind, path=path)
    return validate(_CLASSES[kind](**arrays), path=path)


def _parse_columns(text: str, *, kind: str | None, path) -> tuple[str, dict[str, np.ndarray]]:
    """The CSV reader behind `parse_csv` (and `accel_jax._vibration.read_vibration_table`):
    the kind of record and its float64 columns (the kind's columns, then its optional ones
    present), after the checks of the text itself (empty file, columns, field counts,
    numbers); `validate`'s checks of the values are the caller's. Raises `DataError`."""
    where = _where(path)
    if kind is not None and kind not in COLUMNS:
        raise DataError(f"unknown kind {kind!r}; choose one of {sorted(COLUMNS)}.")
    lines = [line for line in text.splitlines() if line.strip() and not line.startswith("#")]
    if not lines:
        raise DataError(f"{where}: the file is empty; expected a header row and data rows.")
    header = [name.strip() for name in next(csv.reader(lines[:1]))]
    if kind is None:
        kind = infer_kind(header, path=path)
    else:
        missing = [c for c in COLUMNS[kind] if c not in header]
        extra = [c for c in header if c not in COLUMNS[kind] + OPTIONAL_COLUMNS[kind]]
        if missing or extra:
            raise DataError(
                f"{where}: a {kind!r} record has the columns {list(COLUMNS[kind])}; "
                f"missing {missing}, unexpected {extra}."
            )
        infer_kind(header, path=path)  # duplicates
    if len(lines) < 2:
        raise DataError(f"{where}: only a header row; no data rows.")
    values = _fast_values(lines[1:], len(header))
    if values is None:
        values = _checked_values(list(csv.reader(lines[1:])), header, where)
    arrays = {name: values[:, j] for j, name in enumerate(header)}
    names = COLUMNS[kind] + tuple(c for c in OPTIONAL_COLUMNS[kind] if c in arrays)
    return kind, {c: arrays[c] for c in names}


def _fast_values(lines: list[str], width: int) -> np.ndarray | None:
    """The numbers of plain numeric rows by NumPy's C reader (a 10⁶-row record in under a
    second, against ~4 s field by field), or None for anything else — quoted fields, a
    wrong field count, text — which `_checked_values` then reads and names the fault of."""
    try:
        values = np.loadtxt(lines, delimiter=",", comments=None, ndmin=2, dtype=np.float64)
    except ValueError:
        return None
    return values if values.shape == (len(lines), width) else None


def _checked_values(body: list[list[str]], header: list[str], where: str) -> np.ndarray:
    """The rows' numbers field by field with `float`, the first faulty field named."""
    values = np.empty((len(body), len(header)), dtype=np.float64)
    for i, row in enumerate(body):
        if len(row) != len(header):
            raise DataError(
                f"{where}: row {i + 2} has {len(row)} field(s), the header has {len(header)}."
            )
        for j, field in enumerate(row):
            try:
                values[i, j] = float(field)
            except ValueError:
                raise DataError(
                    f"{where}: column {header[j]!r} row {i + 2} is {field.strip()!r}, not a number."
                ) from None
    return values


def _read_text(path: Path) -> str:
    """The text of a CSV file (UTF-8, with or without the byte-order mark spreadsheet
    programs write); `DataError` if it cannot be read."""
    try:
        return path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise DataError(f"{path}: no such file.") from None
    except UnicodeDecodeError:
        raise DataError(f"{path}: not a text (UTF-8) CSV file.") from None
    except OSError as error:
        raise DataError(f"{path}: cannot be read ({error.strerror}).") from None


@overload
def read_csv(path: str | os.PathLike, *, kind: Literal["step"]) -> StepData: ...
@overload
def read_csv(path: str | os.PathLike, *, kind: Literal["vibration"]) -> VibrationData: ...
@overload
def read_csv(path: str | os.PathLike, *, kind: Literal["noise"]) -> NoiseData: ...
@overload
def read_csv(path: str | os.PathLike, *, kind: str | None = None) -> Dataset: ...
def read_csv(path: str | os.PathLike, *, kind: str | None = None) -> Dataset:
    """Read and validate one experiment from a CSV file (see `parse_csv`); with `kind`
    given, the type checker knows the dataset's class."""
    path = Path(path)
    return parse_csv(_read_text(path), kind=kind, path=path)


def write_csv(path: str | os.PathLike, data: Dataset) -> Path:
    """Write a dataset as CSV (header + rows, full float64 precision), atomically."""
    columns = COLUMNS[data.kind] + tuple(
        c for c in OPTIONAL_COLUMNS[data.kind] if getattr(data, c, None) is not None
    )
    stacked = np.stack([np.asarray(getattr(data, c), dtype=np.float64) for c in columns], 1)
    buffer = io.StringIO()
    buffer.write(",".join(columns) + "\n")
    for row in stacked:
        buffer.write(",".join(repr(float(v)) for v in row) + "\n")
    path = Path(path)
    _atomic_write_bytes(path, buffer.getvalue().encode())
    return path


# --------------------------------------------------------------------------------------
# Device files
# --------------------------------------------------------------------------------------


class NominalDevice(eqx.Module):
    """A nominal device: its `ServoParams` and the relative (1σ) uncertainty of each value.

    **Fields:**

    - `params`: the nominal `ServoParams` (SI units).
    - `uncertainty`: a dict field name → relative 1σ uncertainty (e.g. 0.05); fields not
        listed are taken as exact. A diagnosis treats these as a log-normal prior.
    """

    params: ServoParams
    uncertainty: dict = eqx.field(static=True)

    @classmethod
    def reference(cls, **overrides) -> NominalDevice:
        """The reference device (Raspopov's values, T_dm = T_f = 10 µs) with J, μ, c, k_dm
        known to ±5 %. Any value can be overridden by keyword (taken as known), e.g.
        `NominalDevice.reference(torquer_time_constant=0.0, filter_time_constant=0.0)` for
        the idealised loop the identification methods assume."""
        return cls(ServoParams.reference(**overrides), dict(UNCERTAIN_BY_DEFAULT))


def _load_toml(text: str):
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        import tomli as tomllib  # type: ignore[no-redef]
    return tomllib.loads(text)


def parse_params_toml(text: str, *, path=None) -> NominalDevice:
    """Parse a device file (see the module docstring) into a `NominalDevice`.

    Values not given are the reference device's; uncertainties not given are
    `UNCERTAIN_BY_DEFAULT`'s. Raises `DataError` for invalid TOML, unknown keys, non-numeric
    or non-finite values, a negative or > 100 % uncertainty, and values `ServoParams` rejects.
    """
    where = _where(path)
    try:
        table = _load_toml(text)
    except Exception as error:  # tomllib.TOMLDecodeError
        raise DataError(f"{where}: not valid TOML ({error}).") from None
    unknown = sorted(set(table) - set(REFERENCE_VALUES))
    if unknown:
        raise DataError(
            f"{where}: unknown key(s) {unknown}; valid keys are the ServoParams fields "
            f"{sorted(REFERENCE_VALUES)}."
        )
    values = dict(REFERENCE_VALUES)
    uncertainty = dict(UNCERTAIN_BY_DEFAULT)
    for name, entry in table.items():
        if isinstance(entry, dict):
            extra = sorted(set(entry) - {"value", "uncertainty"})
            if extra:
                raise DataError(
                    f"{where}: unknown key(s) {extra} in {name!r}; use value and uncertainty."
                )
            if "value" in entry:
                values[name] = _number(entry["value"], f"{name}.value", where)
            if "uncertainty" in entry:
                u = _number(entry["uncertainty"], f"{name}.uncertainty", where)
                if not 0 <= u <= _MAX_UNCERTAINTY:
                    raise DataError(
                        f"{where}: {name}.uncertainty = {precise(u)} (relative); it must lie in "
                        f"[0, {_MAX_UNCERTAINTY}]."
                    )
                uncertainty[name] = u
        else:
            values[name] = _number(entry, name, where)
    uncertainty = {k: v for k, v in uncertainty.items() if v > 0}
    try:
        params = ServoParams(**{k: np.float64(v) for k, v in values.items()})
    except ValueError as error:
        raise DataError(f"{where}: {error}") from None
    return NominalDevice(params, uncertainty)


def _number(value, name, where) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise DataError(f"{where}: {name} = {value!r} is not a number.")
    if not math.isfinite(value):
        raise DataError(f"{where}: {name} = {value!r} is not finite.")
    return float(value)


def read_params_toml(path: str | os.PathLike) -> NominalDevice:
    """Read a device file (see `parse_params_toml`)."""
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise DataError(f"{path}: no such file.") from None
    except (OSError, UnicodeDecodeError) as error:
        raise DataError(f"{path}: cannot be read ({error}).") from None
    return parse_params_toml(text, path=path)
