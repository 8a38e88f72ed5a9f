"""Whole-or-nothing output files and result provenance."""

from __future__ import annotations

import dataclasses
import datetime
import json
import os
import tempfile
from pathlib import Path
from typing import Any

import jax
import numpy as np

from ._placement import placement_record
from ._runtime import skipped_xla_flags, usable_cpus


def _atomic_write_bytes(path: Path, data: bytes) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
        # mkstemp creates 0600 files; give the result the permissions a plain open() would.
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _jsonable(value: Any) -> Any:
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    if isinstance(value, jax.Array | np.ndarray | np.generic):
        array = np.asarray(value)
        return array.item() if array.ndim == 0 else array.tolist()
    if isinstance(value, float) and not np.isfinite(value):
        return None if np.isnan(value) else ("inf" if value > 0 else "-inf")
    return value


def field_dict(result, *, unless_none: tuple[str, ...] = ()) -> dict:
    """A typed result (a dataclass) as the plain dict its `to_dict()` returns: every field
    in its order, a value with a `to_dict` as that dict, a tuple or list as a list (each
    item so too), a dict as a copy, anything else as it is; a field named in `unless_none`
    left out when it is None. (JSON-ready once `write_json_atomic` converts arrays.)"""
    out = {}
    for field in dataclasses.fields(result):
        value = getattr(result, field.name)
        if value is None and field.name in unless_none:
            continue
        out[field.name] = _plain(value)
    return out


def _plain(value: Any) -> Any:
    if hasattr(value, "to_dict"):
        return value.to_dict()
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return dict(value)
    return value


def write_json_atomic(path: str | os.PathLike, payload: dict) -> Path:
    """Write `payload` as indented JSON: a temporary file, then a rename (never half a file).

    JAX/NumPy scalars and arrays become numbers and lists; NaN becomes null.
    """
    path = Path(path)
    text = json.dumps(_jsonable(payload), indent=2, sort_keys=False, allow_nan=False)
    _atomic_write_bytes(path, (text + "\n").encode())
    return path


def save_figure_atomic(figure, path: str | os.PathLike, **kwargs) -> Path:
    """Save a matplotlib figure via a temporary file and a rename: as PDF or SVG where the
    path ends in .pdf or .svg, as PNG otherwise."""
    import io

    path = Path(path)
    buffer = io.BytesIO()
    fmt = {".pdf": "pdf", ".svg": "svg"}.get(path.suffix.lower(), "png")
    figure.savefig(buffer, format=fmt, **{"dpi": 120, "bbox_inches": "tight", **kwargs})
    _atomic_write_bytes(path, buffer.getvalue())
    return path


def provenance(*, seeds: dict | None = None, precision: str, extra: dict | None = None) -> dict:
    """The provenance block every result file carries: package version, JAX and device,
    where the work ran (`--device`: plain `jit` calls and the sweeps), precision, the XLA
    options in effect and those the running XLA did not accept, seeds and the date (UTC)."""
    from . import __version__

    block = {
        "accel_jax_version": __version__,
        "jax_version": jax.__version__,
        "devices": [str(d) for d in jax.devices()],
        # --device: where plain jit calls ran and where the sweeps (sharded) ran.
        "placement": placement_record(),
        # CPUs the process could use (a report's side-by-side studies get a share each).
        "cpus": len(usable_cpus()),
        "precision": precision,
        # XLA options change results at the round-off level (e.g. fast-compile in --quick).
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        # The package's options this XLA does not know, left out (never an abort).
        "xla_options_skipped": skipped_xla_flags(),
        "xla_most_optimizations_off": bool(jax.config.read("jax_disable_most_optimizations")),
        "seeds": seeds or {},
        "date_utc": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
    }
    if extra:
        block.update(extra)
    return block
