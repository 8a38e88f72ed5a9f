"""Run the studies for the report: resumable (cached by inputs and code), never
destroying earlier output unless asked (`force`), with progress bars.

Each study writes its folder `ROOT/<study>/` (ROOT is the report folder's parent) and a
marker `.accel_jax_run.json` there: the run's cache key and whether the study finished.
A second run with the same key skips finished studies (an interrupted run resumes where it
stopped); a folder holding a finished run with a different key (other options or other
code) is left alone and reported, unless `force` replaces it.
"""

from __future__ import annotations

import concurrent.futures
import hashlib
import importlib.util
import inspect
import json
import multiprocessing
import os
import shutil
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import jax

from .._io import _atomic_write_bytes
from .._progress import bar, show_progress
from .._runtime import usable_cpus
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


def _write_marker(folder: Path, key: str, complete: bool, seconds: float | None = None) -> None:
    body = json.dumps({"key": key, "complete": complete, "seconds": seconds}).encode()
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


def _run_study(
    name: str,
    studies_dir: Path,
    folder: Path,
    key: str,
    quick: bool,
    params_fields: dict | None,
    progress: bool,
    position: int | None = None,
) -> float:
    """Run one study into `folder` (marker first 'unfinished', then 'complete'); return
    its wall time [s]. Runs in the report's process or in a worker process."""
    module = load_study(name, studies_dir)
    extra = {}
    if params_fields is not None and "params" in inspect.signature(module.run).parameters:
        from .._params import ServoParams

        extra["params"] = ServoParams(**params_fields)
    with show_progress(progress, label=name, position=position):
        _, elapsed = _run_marked(module.run, folder, key, quick, extra)
    return elapsed


def _run_marked(run, folder: Path, key: str, quick: bool, extra: dict) -> tuple[dict, float]:
    """`run(folder, quick=quick, **extra)` between an 'unfinished' and a 'complete' marker;
    returns its result and wall time [s]."""
    started = time.perf_counter()
    folder.mkdir(parents=True, exist_ok=True)
    _write_marker(folder, key, complete=False)
    result = run(folder, quick=quick, **extra)
    elapsed = time.perf_counter() - started
    _write_marker(folder, key, complete=True, seconds=elapsed)
    return result, elapsed


def run_study(
    name: str, run, folder: Path, key: str, *, quick: bool, force: bool, **extra
) -> tuple[dict, bool]:
    """One study run from its own script (`report._study.study_main`), with the report's
    rules: a folder holding the same run (same `key`) is reused, one holding another run is
    refused unless `force` (`ReportError`). Returns (the result dict, whether cached)."""
    plan = _plan(folder, key, force)
    if plan == "cached":
        return json.loads((folder / "result.json").read_text()), True
    if plan == "replace":
        shutil.rmtree(folder)
    result, _ = _run_marked(run, folder, key, quick, extra)
    return result, False


_WORKER_POSITION: int | None = None


def worker_cpus(slot: int, jobs: int, cpus: Sequence[int]) -> list[int] | None:
    """The CPUs worker `slot` (1..jobs) of `jobs` side-by-side study processes is pinned
    to: every jobs-th CPU from its own (disjoint shares, all CPUs used), or `None` (not
    pinned) for a single job or fewer CPUs than jobs.

    Pinned, each process's XLA thread pool is sized to its share and the processes do not
    compete for cores. Measured on the 2-core CPU (cold `report --quick`, three pairs run
    back to back): 106.9 / 88.3 / 116.7 s pinned against 112.1 / 113.2 / 141.5 s not, with
    197 / 165 / 217 against 207 / 208 / 263 CPU-s: the same work costs less CPU time when
    two processes' thread pools do not oversubscribe the two cores."""
    if jobs < 2 or len(cpus) < jobs or not 1 <= slot <= jobs:
        return None
    return list(cpus[slot - 1 :: jobs])


def _init_worker(x64: bool, lock, positions, jobs: int = 1) -> None:
    """A worker process: the parent's float64 setting, the shared terminal lock for the
    bars, a terminal line of its own below the overall bar, and its share of the CPUs
    (`worker_cpus`; set before JAX starts its backend, whose thread pool follows it)."""
    global _WORKER_POSITION
    jax.config.update("jax_enable_x64", x64)
    from tqdm.auto import tqdm

    tqdm.set_lock(lock)
    _WORKER_POSITION = positions.get()
    share = worker_cpus(_WORKER_POSITION, jobs, usable_cpus())
    if share is not None and hasattr(os, "sched_setaffinity"):
        try:
            os.sched_setaffinity(0, share)
        except OSError:  # not permitted here: run unpinned
            pass


def _run_study_in_worker(*args) -> float:
    return _run_study(*args, position=_WORKER_POSITION)


# Memory budgeted per study process (a margin: the whole quick report, all studies in one
# process, peaked at 2.8 GB resident); the default never runs more processes than fit.
_MEMORY_PER_JOB = 4 * 2**30


def _physical_memory() -> int | None:
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (AttributeError, ValueError, OSError):
        return None


def default_jobs(n_studies: int) -> int:
    """Studies run side by side: one process per CPU core up to 4 (each study is mostly
    single-threaded Python tracing and XLA compilation) and as many as fit in memory at
    4 GiB each; one on a GPU or TPU (every process would claim the accelerator's memory)."""
    if jax.default_backend() != "cpu":
        return 1
    jobs = min(n_studies, len(usable_cpus()), 4)
    memory = _physical_memory()
    if memory is not None:
        jobs = min(jobs, memory // _MEMORY_PER_JOB)
    return max(1, jobs)


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
    jobs: int | None = 1,
    typical_seconds: dict[str, float] | None = None,
) -> Path:
    """Run `studies` (skipping those cached), then write `out_dir/index.html`.

    `params` (a `ServoParams`) is passed to the studies whose `run` takes a `params`
    argument (the others use their papers' devices); `params_label` names it in the cache
    key and the report. `jobs` > 1 runs that many studies at a time, each in its own
    process (`None`: `default_jobs`); the results are those of running them one by one
    (each study seeds its own random numbers). Side by side, the longest start first: as
    long as the study took last time in this folder (its marker), else
    `typical_seconds[name]`, else in the given order.

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
    if jobs is not None and not (isinstance(jobs, int) and jobs >= 1):
        raise ReportError(f"jobs must be a positive whole number, got {jobs!r}.")
    options = {"quick": bool(quick)}
    params_fields = None
    if params is not None:
        params_fields = {k: float(v) for k, v in params.as_dict().items()}
        options["params"] = params_fields
    plans = {}
    for name in studies:
        key = cache_key(name, Path(studies_dir) / f"{name}.py", options)
        plans[name] = (key, _plan(root / name, key, force))  # checks every folder first
    if progress:
        echo = _above_the_bars(echo)
    todo = []
    for name in studies:
        if plans[name][1] == "cached":
            echo(f"[{name}] up to date (cached; --force recomputes)")
        else:
            todo.append(name)
    jobs = min(default_jobs(len(todo)) if jobs is None else jobs, max(1, len(todo)))
    if jobs > 1:
        todo = _longest_first(todo, root, typical_seconds or {})

    def task(name):
        key, plan = plans[name]
        if plan == "replace":
            shutil.rmtree(root / name)
        if params_fields is not None:
            echo(f"[{name}] on {params_label or 'the given device'}")
        echo(f"[{name}] running{' (quick)' if quick else ''} ...")
        return (name, studies_dir, root / name, key, quick, params_fields, progress)

    with show_progress(progress), bar(len(studies), "studies", unit="study") as overall:
        overall.update(len(studies) - len(todo))
        if jobs == 1:
            for name in todo:
                elapsed = _run_study(*task(name))
                echo(f"[{name}] done in {elapsed:.0f} s")
                overall.update(1)
        else:
            _run_parallel(todo, task, jobs, echo, overall)
    return build_report(
        [root / name for name in studies], index, title=REPORT_TITLE, quick=bool(quick)
    )


REPORT_TITLE = "accel_jax design-study report"


def _above_the_bars(echo: Callable[[str], None]) -> Callable[[str], None]:
    """`echo` that clears this process's progress bars first and redraws them after, so
    that a message is a line of its own above the bars, not text glued to one."""
    from tqdm.auto import tqdm

    def say(message: str) -> None:
        with tqdm.external_write_mode():
            echo(message)

    return say


def _longest_first(names: list[str], root: Path, typical_seconds: dict[str, float]) -> list[str]:
    """The studies ordered longest first (a stable sort: unknown durations keep their order
    after the known ones), so that the longest does not start last."""

    def expected(name):
        marker = _read_marker(root / name) or {}
        seconds = marker.get("seconds") or typical_seconds.get(name)
        return -float(seconds) if isinstance(seconds, (int, float)) else 0.0

    return sorted(names, key=expected)


def _run_parallel(todo, task, jobs, echo, overall) -> None:
    """Run the studies `jobs` at a time in spawned worker processes (JAX is not fork-safe);
    on an error or an interrupt, cancel what has not started and re-raise."""
    from tqdm.auto import tqdm

    context = multiprocessing.get_context("spawn")
    positions = context.Queue()
    for slot in range(jobs):
        positions.put(slot + 1)  # line 0 is the overall bar
    echo(f"running {len(todo)} studies, {jobs} at a time (one process each)")
    # One terminal lock for this process's bar and the workers' (tqdm's own is made in
    # the fork context, which a spawned process cannot share).
    lock, previous_lock = context.RLock(), tqdm.get_lock()
    tqdm.set_lock(lock)
    executor = concurrent.futures.ProcessPoolExecutor(
        max_workers=jobs,
        mp_context=context,
        initializer=_init_worker,
        initargs=(bool(jax.config.jax_enable_x64), lock, positions, jobs),
    )
    waiting, running = list(todo), {}
    try:
        while waiting or running:
            while waiting and len(running) < jobs:  # submitted only when a process is free
                name = waiting.pop(0)
                running[executor.submit(_run_study_in_worker, *task(name))] = name
            done, _ = concurrent.futures.wait(
                running, return_when=concurrent.futures.FIRST_COMPLETED
            )
            for future in done:
                name = running.pop(future)
                try:
                    elapsed = future.result()
                except concurrent.futures.process.BrokenProcessPool as error:
                    raise ReportError(
                        f"the process running {name} died before it finished (out of "
                        "memory?); finished studies are kept: run the same command again, "
                        "with --jobs 1 if it recurs."
                    ) from error
                echo(f"[{name}] done in {elapsed:.0f} s")
                overall.update(1)
    except BaseException:
        executor.shutdown(wait=False, cancel_futures=True)
        raise
    finally:
        tqdm.set_lock(previous_lock)
    executor.shutdown(wait=True)
