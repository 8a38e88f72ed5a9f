"""Process-level settings: the XLA:CPU deadlock workaround (applied at `import accel_jax`),
XLA log level, compile-time options, and the CPUs and threads a process spreads
independent work over (where work runs, `--device`, is `_placement`; the persistent
compilation cache is `_cache`).

**No option can abort a process.** XLA parses `XLA_FLAGS` once, when JAX starts its
backend, and aborts the process (a fatal "Unknown flag in XLA_FLAGS") on any option its
build does not know, whatever the backend: jaxlib 0.11 no longer has the fast-compile
option below. So every option the package adds goes through `accepted_xla_flags` first:
known-good for the jaxlib versions in `XLA_OPTIONS_SEEN_ACCEPTED`, otherwise decided once by
starting XLA with the option in a subprocess (`_probe_xla_flags`, about half a second), the
answer kept per jaxlib version in `~/.cache/accel_jax/xla_options.json`. An option the
running XLA rejects is skipped; `skipped_xla_flags` (recorded in every result's provenance)
says which and why.

Not part of the public namespace: the entry points (the `accel-jax` CLI, the study
scripts, the tests, the benchmarks) import what they need from here.

**The deadlock.** XLA:CPU in jaxlib 0.10.2 deadlocks intermittently — every thread idle,
the caller waiting forever — when it runs a vmapped batch of nested `while` loops (a
Levenberg–Marquardt fit whose residual solves an adaptive diffrax ODE, as in the
sensing-element study; the noise study's batched maximum-likelihood fits) with its
concurrency-optimised scheduler. Seen on the 2-core CPU machine: chunks of 8 to 32 such
fits hung after compiling in about half of the runs; with the scheduler off, 16 repeated
runs completed (32 fits in 9 s). The flag only changes how XLA orders independent
instructions, not what it computes (every result of the test suite and the studies is the
same with and without it).

So `import accel_jax` adds `CPU_SCHEDULER_FLAG` to `XLA_FLAGS` — the one process-level
setting the package makes on import — when all of these hold: JAX has not started its
backend yet (XLA reads `XLA_FLAGS` once, at start-up), the user has not set the option
themselves (either value is respected), and the user has not opted out with
`ACCEL_JAX_XLA_WORKAROUND=off`. When JAX had already started its CPU backend without the
flag, the import warns once instead (nothing can be changed then). This reaches every
process that can hit the deadlock — the CLI, each study run as a script, a user's own
script — without a call anyone can forget.
"""

from __future__ import annotations

import contextlib
import functools
import os
from pathlib import Path

CPU_SCHEDULER_FLAG = "--xla_cpu_enable_concurrency_optimized_scheduler=false"

OPT_OUT_ENV = "ACCEL_JAX_XLA_WORKAROUND"
"""Set to `off` (or `0`, `no`, `false`) to keep `import accel_jax` from touching `XLA_FLAGS`."""


def _scheduler_option_set() -> bool:
    """Whether `XLA_FLAGS` already sets the scheduler option (to either value)."""
    return "xla_cpu_enable_concurrency_optimized_scheduler" in os.environ.get("XLA_FLAGS", "")


def _opted_out() -> bool:
    return os.environ.get(OPT_OUT_ENV, "").strip().lower() in ("0", "off", "no", "false")


def apply_cpu_workarounds() -> bool:
    """Add `CPU_SCHEDULER_FLAG` to `XLA_FLAGS` unless the user set that option already or
    opted out (`ACCEL_JAX_XLA_WORKAROUND=off`).

    Effective only before JAX initialises its backend (the first computation); returns
    whether the environment was changed. Called by `import accel_jax` (see the module
    docstring); the entry points need not call it again.
    """
    if _scheduler_option_set() or _opted_out():
        return False
    if not accepted_xla_flags([CPU_SCHEDULER_FLAG]):
        return False  # this XLA does not know the option (recorded by accepted_xla_flags)
    flags = os.environ.get("XLA_FLAGS", "")
    os.environ["XLA_FLAGS"] = f"{flags} {CPU_SCHEDULER_FLAG}".strip()
    return True


def apply_at_import() -> str:
    """What `import accel_jax` does about the deadlock; returns what happened:
    `"applied"`, `"user"` (the user set the option or opted out), `"too_late"` (JAX's
    backend had started without the flag: a one-time `RuntimeWarning` on the CPU), or
    `"not_accepted"` (the running XLA does not know the option: nothing added, recorded in
    `skipped_xla_flags`)."""
    if _scheduler_option_set() or _opted_out():
        return "user"
    if _backend_started():
        _warn_too_late()
        return "too_late"
    return "applied" if apply_cpu_workarounds() else "not_accepted"


def _warn_too_late() -> None:
    import warnings

    import jax

    if jax.default_backend() != "cpu":
        return
    warnings.warn(
        "accel_jax was imported after JAX started its CPU backend, so it could not set "
        f"XLA_FLAGS={CPU_SCHEDULER_FLAG}: jaxlib 0.10.2's concurrency-optimised scheduler "
        "can deadlock on a vmapped batch of the nested-loop fits (fit_sensing_element, "
        "the noise maximum-likelihood fits; every thread idle, the call never returns). "
        "Import accel_jax before the first JAX computation, or set the flag in the "
        f"environment (or {OPT_OUT_ENV}=off to silence this).",
        RuntimeWarning,
        stacklevel=4,
    )


def quiet_xla_logs() -> bool:
    """Keep XLA's C++ log lines (e.g. "Constant folding an instruction is taking > 1s")
    off the user's terminal: `TF_CPP_MIN_LOG_LEVEL=3` unless the user set the variable.
    Errors still reach the user as Python exceptions. JAX sets the variable to 1 when it is
    imported, if unset, and XLA reads it at its first log line: so this works before any
    computation, and it respects a value the user set before `import accel_jax`. Returns
    whether the environment was changed."""
    import accel_jax

    if accel_jax._USER_SET_XLA_LOG_LEVEL:
        return False
    os.environ["TF_CPP_MIN_LOG_LEVEL"] = "3"
    return True


FAST_COMPILE_FLAGS = (
    "--xla_cpu_use_fusion_emitters=false",
    "--xla_backend_optimization_level=2",
)
"""XLA options for compile-bound runs on the CPU (figures: docs/report.md).

- `--xla_cpu_use_fusion_emitters=false`: XLA:CPU's older loop emitters. On the 2-core CPU
  a quarter to a third less compile time for the quick studies, the same run time. It does
  not change what a GPU computes, but XLA parses it whatever the backend, and jaxlib 0.11
  no longer knows it: added only where `accepted_xla_flags` says the running XLA accepts it.
- `--xla_backend_optimization_level=2` (XLA's default is 3): LLVM's -O2 pipeline instead of
  -O3. The step diagnosis's largest program (a compliant-contact fit) compiled in 55.5 s
  instead of 63–65 s at the same run time on the 2-core CPU. It
  also steers a GPU backend's code generation, not measured there: so it is added only
  where no JAX backend plugin is installed (`_gpu_plugin_installed`)."""

CPU_ONLY_FAST_COMPILE = frozenset({"xla_backend_optimization_level"})
"""The `FAST_COMPILE_FLAGS` options left out where a GPU backend may be present."""


def _gpu_plugin_installed() -> bool:
    """Whether a JAX backend plugin (a GPU's) is installed: JAX finds them as `jax_plugins`
    entry points or modules of the `jax_plugins` namespace package."""
    import pkgutil
    from importlib import metadata, util

    try:
        spec = util.find_spec("jax_plugins")
        places = (spec.submodule_search_locations or []) if spec is not None else []
        found = any(pkgutil.iter_modules(places))
        return found or bool(list(metadata.entry_points(group="jax_plugins")))
    except (ImportError, ValueError):
        return False


def _backend_started() -> bool:
    try:
        from jax._src import xla_bridge

        return bool(xla_bridge.backends_are_initialized())
    except (ImportError, AttributeError):  # a JAX without this (private) query
        return False


def apply_fast_compile() -> list[str]:
    """Add `FAST_COMPILE_FLAGS` to `XLA_FLAGS` (each unless the user set that option, and
    only those the running XLA accepts: `accepted_xla_flags`), for this process and the
    processes it starts (the report's workers, the blind diagnosis); returns the flags
    added. Nothing is added once JAX has started its backend (the flags would not apply
    here, and `XLA_FLAGS`, which `provenance` records, would then claim them)."""
    if _backend_started():
        return []
    flags = os.environ.get("XLA_FLAGS", "")
    wanted = [f for f in FAST_COMPILE_FLAGS if f.split("=")[0] not in flags]
    if wanted and _gpu_plugin_installed():
        wanted = [f for f in wanted if xla_option_name(f) not in CPU_ONLY_FAST_COMPILE]
    added = accepted_xla_flags(wanted) if wanted else []
    if added:
        os.environ["XLA_FLAGS"] = " ".join([flags, *added]).strip()
    return added


@contextlib.contextmanager
def fast_compile(enabled: bool = True):
    """Inside the block, compile with most of XLA's optimisations off (JAX's
    `jax_disable_most_optimizations`: LLVM at -O0, no expensive passes) on the CPU backend;
    elsewhere, or with `enabled` false, a no-op. For work that compiles many programs and
    runs each a few times. Measured on the 2-core CPU with `FAST_COMPILE_FLAGS`: one
    vmapped scale-factor identification compiles in 0.6 s instead of 1.9 s and runs in
    66 ms instead of 13 ms; the quick scale-factor study, with its one-off parts inside,
    takes 42 CPU-s instead of 59. Results agree to round-off. Programs compiled inside stay
    compiled that way for the rest of the process, and programs compiled before keep their
    optimisation inside (JAX's in-memory cache does not key on the option; checked)."""
    import jax

    if not enabled or jax.default_backend() != "cpu":
        yield
        return
    previous = jax.config.read("jax_disable_most_optimizations")
    jax.config.update("jax_disable_most_optimizations", True)
    try:
        yield
    finally:
        jax.config.update("jax_disable_most_optimizations", previous)


def fast_compile_when_quick(run):
    """Decorate a study's `run(out_dir, *, quick=False, ...)` so that a quick run compiles
    inside `fast_compile` (for studies whose quick run is compile-bound throughout)."""

    @functools.wraps(run)
    def wrapper(out_dir, *, quick: bool = False, **options):
        with fast_compile(quick):
            return run(out_dir, quick=quick, **options)

    return wrapper


def usable_cpus() -> list[int]:
    """The CPUs this process may run on (its affinity mask where the OS has one)."""
    if hasattr(os, "sched_getaffinity"):
        return sorted(os.sched_getaffinity(0))
    return list(range(os.cpu_count() or 1))


REPORT_CPUS_ENV = "ACCEL_JAX_REPORT_CPUS"
"""The CPUs of the whole report (comma-separated), set by the report for its study processes
before it pins each to its share (`report._run.worker_cpus`)."""


def report_cpus() -> list[int]:
    """The CPUs of the run this process belongs to: those the report had before it pinned
    each study to its share of them (`REPORT_CPUS_ENV`), else this process's own
    (`usable_cpus`). For a study's run-bound child processes, which may still be running
    when the other studies have finished and left their CPUs idle."""
    text = os.environ.get(REPORT_CPUS_ENV, "").strip()
    if text:
        try:
            cpus = sorted({int(c) for c in text.split(",")})
        except ValueError:
            cpus = []
        if cpus and all(c >= 0 for c in cpus):
            return cpus
    return usable_cpus()


BACKGROUND_THREADS = "accel_jax-background"
"""The name prefix of the threads of `thread_map` and `in_background`."""


def thread_map(fn, items) -> list:
    """`[fn(item) for item in items]`, the calls spread over as many threads as the process
    has CPUs (`usable_cpus`; one thread, in the caller, for a pinned job or a single item).
    For independent work that is mostly compiled JAX calls: an XLA:CPU call runs on one
    core and releases the GIL, so two such calls run side by side. The results are the
    same as in one thread, to the bit (the same calls, in another order), and come back in
    `items`' order; the first exception raised is raised here. Each worker runs under the
    caller's x64 setting (`jax.enable_x64` is thread-local)."""
    items = list(items)
    workers = min(len(items), len(usable_cpus()))
    if workers < 2:
        return [fn(item) for item in items]
    from concurrent.futures import ThreadPoolExecutor

    pool = ThreadPoolExecutor(workers, thread_name_prefix=BACKGROUND_THREADS)
    try:
        results = list(pool.map(_under_callers_x64(fn), items))
    except BaseException:
        # After an error or an interrupt (Ctrl-C) here, the calls not yet started are
        # dropped (a `with` block would run every one of them first); those running end
        # on their own (`background_running`).
        pool.shutdown(wait=False, cancel_futures=True)
        raise
    pool.shutdown(wait=True)  # every call has returned: its threads end at once
    return results


def _under_callers_x64(fn):
    """`fn`, to be called on another thread, under the x64 setting of the thread that
    wraps it (`jax.enable_x64` is thread-local: a new thread would see the global one)."""
    import jax

    x64 = bool(jax.config.read("jax_enable_x64"))

    def under(*args):
        with jax.enable_x64(x64):
            return fn(*args)

    return under


def spare_cpu() -> bool:
    """Whether this process has a CPU that nothing else is using now: at least two usable
    CPUs (`usable_cpus`) and fewer runnable threads on the machine, the caller's included,
    than their count (Linux: `/proc/loadavg`'s running count, read at once; elsewhere the
    one-minute load average below the count minus a half). For work that only saves time
    on an idle CPU (compiling a later stage's program ahead, which may not be needed); it
    changes no result."""
    cpus = len(usable_cpus())
    if cpus < 2:
        return False
    running = _running_threads()
    if running is not None:
        return running < cpus
    try:
        load = os.getloadavg()[0]
    except (AttributeError, OSError):  # not on every OS
        return True
    return load < cpus - 0.5


def _running_threads() -> int | None:
    """The machine's runnable threads now (`/proc/loadavg`'s fourth field, before the
    slash), or None where there is no such file."""
    try:
        with open("/proc/loadavg") as f:
            return int(f.read().split()[3].split("/")[0])
    except (OSError, ValueError, IndexError):
        return None


def in_background(*calls):
    """Each of `calls` (functions of no arguments) run in turn on one background thread,
    under the caller's x64 setting: their `concurrent.futures.Future`s, in order. The
    thread ends after the last call."""
    from concurrent.futures import ThreadPoolExecutor

    pool = ThreadPoolExecutor(1, thread_name_prefix=BACKGROUND_THREADS)
    futures = [pool.submit(_under_callers_x64(call)) for call in calls]
    pool.shutdown(wait=False)
    return futures


def background_running() -> bool:
    """Whether a thread of `thread_map` or `in_background` is still running a call (a
    program compiled ahead for a later stage, a refit): at the end of a command that
    finished normally none is, since it waited for every result it needed."""
    import threading

    return any(
        thread.name.startswith(BACKGROUND_THREADS) and thread.is_alive()
        for thread in threading.enumerate()
    )


def beside(*calls):
    """Each of `calls` (functions of no arguments) started beside the caller's next work:
    in turn on one background thread where this process has two CPUs or more
    (`usable_cpus`, `in_background`), else here, in turn, at once (an error raised here,
    as the call itself would). Their `Future`s, in order: `result()` gives a call's value
    or raises its error. For independent work whose results do not depend on where it
    runs: the same calls, the same results."""
    from concurrent.futures import Future

    if len(usable_cpus()) >= 2:
        return in_background(*calls)
    futures = []
    for call in calls:
        future: Future = Future()
        future.set_result(call())
        futures.append(future)
    return futures


# ---------------------------------------------------------------------------------------
# XLA options that cannot abort a process (module docstring).

XLA_OPTIONS_SEEN_ACCEPTED: dict[str, frozenset[str]] = {
    # jaxlib version: the package's options its XLA was started with and accepted (by
    # `_probe_xla_flags`), so that the pinned stack never pays for a probe.
    "0.10.2": frozenset(
        {
            "xla_cpu_enable_concurrency_optimized_scheduler",
            "xla_cpu_use_fusion_emitters",
            "xla_backend_optimization_level",
        }
    ),
}

_SKIPPED_ENV = "_ACCEL_JAX_XLA_SKIPPED"
"""Where the options skipped in this process are noted (JSON), so that the processes it
starts (the report's workers, the blind diagnosis), which inherit `XLA_FLAGS` and decide
nothing themselves, record them in their provenance too."""

_PROBE_PROGRAM = "import jax; jax.devices()"
_decided: dict[tuple[str, str], bool] = {}  # (jaxlib version, option name) → accepted


def xla_option_name(flag: str) -> str:
    """`--xla_foo=false` → `xla_foo`."""
    return flag.strip().lstrip("-").split("=", 1)[0]


def jaxlib_version() -> str:
    """The installed jaxlib's version, read without importing it (`"unknown"` if absent)."""
    from importlib import metadata

    try:
        return metadata.version("jaxlib")
    except metadata.PackageNotFoundError:
        return "unknown"


def _options_cache_file() -> Path | None:
    """`$XDG_CACHE_HOME/accel_jax/xla_options.json` (`~/.cache/…`); None when the user
    turned the caches off (`ACCEL_JAX_CACHE_DIR=off`): then each process decides anew."""
    from ._cache import CACHE_ENV, cache_home, compilation_cache_dir

    if os.environ.get(CACHE_ENV) is not None and compilation_cache_dir() is None:
        return None
    return cache_home() / "xla_options.json"


def _read_options_cache() -> dict:
    path = _options_cache_file()
    if path is None:
        return {}
    try:
        import json

        cached = json.loads(path.read_text())
        return cached if isinstance(cached, dict) else {}
    except (OSError, ValueError):
        return {}


def _write_options_cache(version: str, decisions: dict[str, bool]) -> None:
    """Merge `decisions` into the cache file (a temporary file, then a rename); a cache
    that cannot be written is skipped (the next process probes again)."""
    import json
    import tempfile

    path = _options_cache_file()
    if path is None or not decisions:
        return
    cached = _read_options_cache()
    entry = cached.get(version)
    if not isinstance(entry, dict):
        entry = {}
    cached[version] = {**entry, **decisions}
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".xla_options.", suffix=".tmp")
        with os.fdopen(fd, "w") as handle:
            json.dump(cached, handle, indent=1, sort_keys=True)
        os.replace(tmp, path)
    except OSError:
        pass


def _probe_xla_flags(flags: list[str]) -> bool | None:
    """Start XLA (its CPU backend) in a subprocess with exactly `flags` in `XLA_FLAGS`:
    True if it starts, False if it refuses (exits non-zero, as XLA's fatal "Unknown flag"
    does), None if the probe could not be run or did not answer within a minute."""
    import subprocess
    import sys

    env = {
        **os.environ,
        "XLA_FLAGS": " ".join(flags),
        "JAX_PLATFORMS": "cpu",  # the options are parsed whatever the backend; CPU is quick
        "TF_CPP_MIN_LOG_LEVEL": "3",
    }
    try:
        done = subprocess.run(
            [sys.executable, "-c", _PROBE_PROGRAM],
            env=env,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            timeout=60,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return done.returncode == 0


def accepted_xla_flags(flags) -> list[str]:
    """The members of `flags` (`--xla_name=value` strings) that the running XLA accepts, in
    order; each other one is noted in `skipped_xla_flags` with its reason.

    Decided per jaxlib version: the versions in `XLA_OPTIONS_SEEN_ACCEPTED` without a
    subprocess; otherwise the answer cached in `~/.cache/accel_jax/xla_options.json`, or a
    probe (`_probe_xla_flags`: the undecided options together, each alone if that fails),
    cached for the next process. An option that could not be checked is skipped too (not
    cached): adding it could abort the process, leaving it out only costs compile time."""
    flags = list(flags)
    version = jaxlib_version()
    seen = XLA_OPTIONS_SEEN_ACCEPTED.get(version, frozenset())
    cached = _read_options_cache().get(version) or {}
    answer: dict[str, bool | None] = {}
    undecided = []
    for flag in flags:
        name = xla_option_name(flag)
        if name in seen:
            answer[flag] = True
        elif (version, name) in _decided:
            answer[flag] = _decided[version, name]
        elif isinstance(cached.get(name), bool):
            answer[flag] = cached[name]
        else:
            undecided.append(flag)
    if undecided:
        together = _probe_xla_flags(undecided)
        if together or len(undecided) == 1:
            answer.update(dict.fromkeys(undecided, together))
        else:
            answer.update({flag: _probe_xla_flags([flag]) for flag in undecided})
        decided = {xla_option_name(f): ok for f in undecided if (ok := answer[f]) is not None}
        _decided.update({(version, name): ok for name, ok in decided.items()})
        _write_options_cache(version, decided)
    for flag in flags:
        if answer[flag] is not True:
            why = "not accepted by" if answer[flag] is False else "could not be checked on"
            _note_skipped(flag, f"{why} this XLA (jaxlib {version}); skipped")
    return [flag for flag in flags if answer[flag] is True]


def _note_skipped(flag: str, reason: str) -> None:
    import json

    skipped = skipped_xla_flags()
    skipped[flag] = reason
    os.environ[_SKIPPED_ENV] = json.dumps(skipped, sort_keys=True)


def skipped_xla_flags() -> dict[str, str]:
    """The package's XLA options left out in this process or the one that started it,
    `{flag: reason}` (recorded in every result's provenance)."""
    import json

    try:
        skipped = json.loads(os.environ.get(_SKIPPED_ENV, "") or "{}")
    except ValueError:
        return {}
    return skipped if isinstance(skipped, dict) else {}
