"""Run the studies for the report: resumable (cached by inputs and code), never
destroying earlier output unless asked (`force`), with progress bars.

Each study writes its folder `ROOT/<study>/` (ROOT is the report folder's parent) and a
marker `.accel_jax_run.json` there: the run's cache key and whether the study finished.
A second run with the same key skips finished studies (an interrupted run resumes where it
stopped); a folder holding a finished run with a different key (other options or other
code) is left alone and reported, unless `force` replaces it.

A study that raises (or whose process dies) does not take the report down: it is marked
failed in its marker with a one-line reason, its traceback goes to `error.log` in its
folder, the other studies finish, the page is written with the study shown as failed,
and `run_report` then raises `StudiesFailed` (the CLI: a summary and exit status 1).
"""

from __future__ import annotations

import hashlib
import importlib.util
import inspect
import json
import multiprocessing
import os
import shutil
import sys
import time
import traceback
from collections.abc import Callable, Sequence
from pathlib import Path

import jax
import numpy as np

from .._io import _atomic_write_bytes
from .._placement import apply_device
from .._progress import bar, show_progress
from .._runtime import REPORT_CPUS_ENV, usable_cpus
from ._html import REPORT_MARKER, build_report

MARKER = ".accel_jax_run.json"


class ReportError(Exception):
    """A report cannot be written as asked (the message says why and what to do)."""


class StudiesFailed(ReportError):
    """Some studies raised or their process died. The others finished and the page was
    written (`index`) with these marked failed; `failures` is `{study: one-line reason}`,
    each study's traceback in `<study>/error.log`."""

    def __init__(self, index: Path, failures: dict[str, str], root: Path):
        self.index, self.failures, self.root = index, dict(failures), root
        lines = [
            f"  {name}: {why} (log: {root / name / ERROR_LOG})" for name, why in failures.items()
        ]
        super().__init__(
            f"{len(failures)} stud{'y' if len(failures) == 1 else 'ies'} failed; the report "
            f"marks {'it' if len(failures) == 1 else 'them'} and shows the rest "
            f"({index}):\n" + "\n".join(lines)
        )


ERROR_LOG = "error.log"


def one_line(error: BaseException, limit: int = 300) -> str:
    """An exception as one line: its type and the first line of its message."""
    text = str(error).strip().splitlines()
    line = f"{type(error).__name__}: {text[0]}" if text else type(error).__name__
    return line if len(line) <= limit else line[: limit - 1] + "…"


def _record_failure(folder: Path, key: str, reason: str, log: str | None) -> None:
    """Mark a study failed (marker: unfinished, with the reason) and write its log."""
    folder.mkdir(parents=True, exist_ok=True)
    if log is not None:
        _atomic_write_bytes(folder / ERROR_LOG, log.encode())
    _write_marker(folder, key, complete=False, failed=reason)


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
        "x64": _x64(),
    }
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()


def _x64() -> bool:
    """Whether JAX computes in float64 here (the setting, as `jax.enable_x64` leaves it)."""
    return bool(jax.dtypes.canonicalize_dtype(np.float64) == np.float64)


def load_study(name: str, folder: Path):
    """Import `folder/<name>.py` as a module (studies are scripts, not package modules)."""
    path = Path(folder) / f"{name}.py"
    if not path.exists():
        raise ReportError(f"study script not found: {path}")
    spec = importlib.util.spec_from_file_location(f"accel_jax_study_{name}", path)
    if spec is None or spec.loader is None:
        raise ReportError(f"study script cannot be loaded as a module: {path}")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def _read_marker(folder: Path) -> dict | None:
    try:
        return json.loads((folder / MARKER).read_text())
    except (OSError, ValueError):
        return None


def _write_marker(
    folder: Path,
    key: str,
    complete: bool,
    seconds: float | None = None,
    failed: str | None = None,
) -> None:
    marker = {"key": key, "complete": complete, "seconds": seconds}
    if failed is not None:
        marker["failed"] = failed
    _atomic_write_bytes(folder / MARKER, json.dumps(marker).encode())


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


def _init_worker(x64: bool, lock, slot: int, jobs: int = 1) -> None:
    """A study process: the parent's float64 setting and device choice (inherited through
    `ACCEL_JAX_DEVICE`), the shared terminal lock for the bars, and its share of the CPUs
    (`worker_cpus`; set before JAX starts its backend, whose thread pool follows it)."""
    cpus = usable_cpus()
    share = worker_cpus(slot, jobs, cpus)
    # The report's CPUs, for the study's child processes (`_runtime.report_cpus`).
    os.environ.setdefault(REPORT_CPUS_ENV, ",".join(map(str, cpus)))
    if share is not None and hasattr(os, "sched_setaffinity"):
        try:
            os.sched_setaffinity(0, share)
        except OSError:  # not permitted here: run unpinned
            pass
    apply_device(latency_bound=False, shared=jobs > 1)
    jax.config.update("jax_enable_x64", x64)
    from tqdm.auto import tqdm

    tqdm.set_lock(lock)


def _study_process(args: tuple, slot: int, jobs: int, x64: bool, lock, conn) -> None:
    """The body of one side-by-side study process: run the study, send the parent
    `("done", seconds)` or `("failed", one-line reason)` (the traceback written to the
    study's `error.log` here). An interrupt ends it quietly: the parent handles it."""
    try:
        _init_worker(x64, lock, slot, jobs)
        elapsed = _run_study(*args, position=slot)
        conn.send(("done", elapsed))
    except KeyboardInterrupt:
        pass
    except Exception as error:
        folder = Path(args[2])
        try:
            folder.mkdir(parents=True, exist_ok=True)
            _atomic_write_bytes(folder / ERROR_LOG, traceback.format_exc().encode())
        except OSError:
            pass
        conn.send(("failed", one_line(error)))
    finally:
        conn.close()


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
    4 GiB each. The same on a GPU host: there the studies' latency-bound work runs on the
    host's cores (`apply_device`), and the processes share the accelerator without any
    claiming its memory up front (`XLA_PYTHON_CLIENT_PREALLOCATE=false`)."""
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
    would have to be replaced and `force` is false. A study that raises or whose process
    dies is marked failed (`ERROR_LOG` in its folder) while the others run on; the page is
    written with it shown failed, then `StudiesFailed` is raised.
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
    options: dict[str, object] = {"quick": bool(quick)}
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

    failures: dict[str, str] = {}

    def finished(name: str, outcome: str, value) -> None:
        if outcome == "done":
            echo(f"[{name}] done in {value:.0f} s")
        else:
            failures[name] = value
            _record_failure(root / name, plans[name][0], value, log=None)
            echo(f"[{name}] FAILED: {value} (log: {root / name / ERROR_LOG})")

    with show_progress(progress), bar(len(studies), "studies", unit="study") as overall:
        overall.update(len(studies) - len(todo))
        if jobs == 1:
            for name in todo:
                args = task(name)
                try:
                    finished(name, "done", _run_study(*args))
                except Exception as error:  # the study's fault: recorded, the rest runs on
                    _atomic_write_bytes(
                        _ensure(root / name) / ERROR_LOG, traceback.format_exc().encode()
                    )
                    finished(name, "failed", one_line(error))
                overall.update(1)
        else:
            _run_parallel(todo, task, jobs, echo, overall, finished, lambda n: root / n)
    index = build_report(
        [root / name for name in studies], index, title=REPORT_TITLE, quick=bool(quick)
    )
    if failures:
        raise StudiesFailed(index, failures, root)
    return index


def _ensure(folder: Path) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    return folder


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


def _run_parallel(todo, task, jobs, echo, overall, finished, task_folder) -> None:
    """Run the studies `jobs` at a time, each in a spawned process of its own (JAX is not
    fork-safe; one process per study, so that a process that dies names its study), and
    call `finished(name, "done", seconds)` or `finished(name, "failed", reason)` for each.
    On an interrupt or an error of the runner itself, stop every study process and
    re-raise (finished studies are kept)."""
    from multiprocessing.connection import wait

    from tqdm.auto import tqdm

    context = multiprocessing.get_context("spawn")
    echo(f"running {len(todo)} studies, {jobs} at a time (one process each)")
    # One terminal lock for this process's bar and the workers' (tqdm's own is made in
    # the fork context, which a spawned process cannot share).
    lock, previous_lock = context.RLock(), tqdm.get_lock()
    tqdm.set_lock(lock)
    x64 = _x64()
    waiting, running = list(todo), {}
    free = list(range(1, jobs + 1))  # terminal line of each slot (0 is the overall bar)
    try:
        while waiting or running:
            while waiting and free:
                name, slot = waiting.pop(0), free.pop(0)
                receive, send = context.Pipe(duplex=False)
                process = context.Process(
                    target=_study_process,
                    args=(task(name), slot, jobs, x64, lock, send),
                    name=f"accel_jax study {name}",
                )
                process.start()
                send.close()
                running[process.sentinel] = (name, process, receive, slot)
            for sentinel in wait(list(running)):
                name, process, receive, slot = running.pop(sentinel)
                message = None
                try:
                    if receive.poll():
                        message = receive.recv()
                except (EOFError, OSError):
                    message = None
                receive.close()
                process.join()
                free.append(slot)
                if message is None:
                    code = process.exitcode
                    how = f"killed by signal {-code}" if code and code < 0 else f"exit {code}"
                    reason = f"its process died before it finished ({how}; out of memory?)"
                    folder = _ensure(task_folder(name))
                    _atomic_write_bytes(folder / ERROR_LOG, (reason + "\n").encode())
                    finished(name, "failed", reason)
                else:
                    finished(name, *message)
                overall.update(1)
    except BaseException:
        for name, process, receive, _ in running.values():
            process.terminate()
        for name, process, receive, _ in running.values():
            process.join(timeout=10)
            if process.is_alive():
                process.kill()
            receive.close()
        raise
    finally:
        tqdm.set_lock(previous_lock)
