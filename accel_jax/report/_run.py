"""Run the studies for the report: resumable (cached by inputs and code), never
destroying earlier output unless asked (`force`), with progress bars.

Each study writes its folder `ROOT/<study>/` (ROOT is the report folder's parent) and a
marker `.accel_jax_run.json` there: the run's cache key and whether the study finished.
A second run with the same key skips finished studies (an interrupted run resumes where it
stopped); a folder holding a finished run with a different key (other options or other
code) is left alone and reported, unless `force` replaces it.
"""

from __future__ import annotations

import hashlib
import importlib.util
import inspect
import json
import shutil
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import jax

from .._io import _atomic_write_bytes
from .._progress import bar, show_progress
from ._html import REPORT_MARKER, build_report

MARKER = ".accel_jax_run.json"


class ReportError(Exception):
    """A report cannot be written as asked (the message says why and what to do)."""


def _package_dir() -> Path:
    return Path(__file__).resolve().parent.parent


def code_fingerprint(study_file: Path) -> str:
    """SHA-256 over the package's Python sources and the study script."""
    digest = hashlib.sha256()
    for path in sorted(_package_dir().rglob("*.py")) + [Path(study_file)]:
        digest.update(path.name.encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()


def cache_key(name: str, study_file: Path, options: dict) -> str:
    """The key a study's results are cached under: its inputs and the code that ran."""
    from .. import __version__

    payload = {
        "study": name,
        "options": options,
        "code": code_fingerprint(study_file),
        "accel_jax": __version__,
        "jax": jax.__version__,
        "x64": bool(jax.config.jax_enable_x64),
    }
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()


def load_study(name: str, folder: Path):
    """Import `folder/<name>.py` as a module (studies are scripts, not package modules)."""
    path = Path(folder) / f"{name}.py"
    if not path.exists():
        raise ReportError(f"study script not found: {path}")
    spec = importlib.util.spec_from_file_location(f"accel_jax_study_{name}", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def _read_marker(folder: Path) -> dict | None:
    try:
        return json.loads((folder / MARKER).read_text())
    except (OSError, ValueError):
        return None


def _write_marker(folder: Path, key: str, complete: bool) -> None:
    body = json.dumps({"key": key, "complete": complete}).encode()
    _atomic_write_bytes(folder / MARKER, body)


def _plan(folder: Path, key: str, force: bool) -> str:
    """'run', 'cached' or raise: what to do with one study's folder."""
    if not folder.exists():
        return "run"
    if not folder.is_dir():
        raise ReportError(f"{folder} exists and is not a folder; move it or choose another --out.")
    if force:
        return "replace"
    marker = _read_marker(folder)
    if marker is not None and marker.get("key") == key:
        return "cached" if marker.get("complete") and (folder / "result.json").exists() else "run"
    if marker is None and not any(folder.iterdir()):
        return "run"
    if marker is None:
        raise ReportError(
            f"{folder} exists and was not written by accel-jax report; move it, choose "
            "another --out, or pass --force to replace it."
        )
    raise ReportError(
        f"{folder} holds results of a different run (other options or code); pass --force "
        "to replace them, or choose another --out."
    )


def run_report(
    out_dir: Path,
    *,
    studies: Sequence[str],
    studies_dir: Path,
    quick: bool = False,
    force: bool = False,
    progress: bool = True,
    echo: Callable[[str], None] = print,
    params=None,
    params_label: str | None = None,
) -> Path:
    """Run `studies` (skipping those cached), then write `out_dir/index.html`.

    `params` (a `ServoParams`) is passed to the studies whose `run` takes a `params`
    argument (the others use their papers' devices); `params_label` names it in the cache
    key and the report.

    Raises `ReportError` (nothing deleted, nothing half-written) when an existing folder
    would have to be replaced and `force` is false; a study's own `ValueError` propagates.
    """
    out_dir = Path(out_dir)
    root = out_dir.parent
    index = out_dir / "index.html"
    if out_dir.exists() and not out_dir.is_dir():
        raise ReportError(f"--out {out_dir} exists and is not a folder.")
    if index.exists() and not force and REPORT_MARKER not in index.read_text(errors="replace"):
        raise ReportError(
            f"{index} exists and was not written by accel-jax report; pass --force to "
            "replace it, or choose another --out."
        )
    options = {"quick": bool(quick)}
    if params is not None:
        options["params"] = {k: float(v) for k, v in params.as_dict().items()}
    plans = {}
    for name in studies:
        key = cache_key(name, Path(studies_dir) / f"{name}.py", options)
        plans[name] = (key, _plan(root / name, key, force))  # checks every folder first
    study_dirs = []
    with show_progress(progress), bar(len(studies), "studies", unit="study") as overall:
        for name in studies:
            key, plan = plans[name]
            folder = root / name
            study_dirs.append(folder)
            if plan == "cached":
                echo(f"[{name}] up to date (cached; --force recomputes)")
                overall.update(1)
                continue
            if plan == "replace":
                shutil.rmtree(folder)
            module = load_study(name, studies_dir)
            echo(f"[{name}] running{' (quick)' if quick else ''} ...")
            started = time.perf_counter()
            folder.mkdir(parents=True, exist_ok=True)
            _write_marker(folder, key, complete=False)
            extra = {}
            if params is not None and "params" in inspect.signature(module.run).parameters:
                extra["params"] = params
                echo(f"[{name}] on {params_label or 'the given device'}")
            with show_progress(progress, label=name):
                module.run(folder, quick=quick, **extra)
            _write_marker(folder, key, complete=True)
            echo(f"[{name}] done in {time.perf_counter() - started:.0f} s")
            overall.update(1)
    return build_report(study_dirs, index, title="accel_jax design-study report")
