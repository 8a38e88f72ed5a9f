"""Process-level settings: the XLA:CPU deadlock workaround (applied at `import accel_jax`),
XLA log level, compile-time options and the persistent compilation cache.

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
    flags = os.environ.get("XLA_FLAGS", "")
    os.environ["XLA_FLAGS"] = f"{flags} {CPU_SCHEDULER_FLAG}".strip()
    return True


def apply_at_import() -> str:
    """What `import accel_jax` does about the deadlock; returns what happened:
    `"applied"`, `"user"` (the user set the option or opted out), or `"too_late"` (JAX's
    backend had started without the flag: a one-time `RuntimeWarning` on the CPU)."""
    if _scheduler_option_set() or _opted_out():
        return "user"
    if _backend_started():
        _warn_too_late()
        return "too_late"
    apply_cpu_workarounds()
    return "applied"


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


FAST_COMPILE_FLAGS = ("--xla_cpu_use_fusion_emitters=false",)
"""XLA:CPU option for compile-bound runs: the older loop emitters instead of the MLIR fusion
emitters. On the 2-core CPU it cut the quick studies' compile time by a quarter to a third
(scale-factor study 44 → 31 s, noise 30 → 20 s) at an unchanged run time (one vmapped
scale-factor identification: 13.3 ms either way). An XLA:CPU option only: GPU and TPU
backends ignore it."""


def _backend_started() -> bool:
    try:
        from jax._src import xla_bridge

        return bool(xla_bridge.backends_are_initialized())
    except (ImportError, AttributeError):  # a JAX without this (private) query
        return False


def apply_fast_compile() -> list[str]:
    """Add `FAST_COMPILE_FLAGS` to `XLA_FLAGS` (each unless the user set that option), for
    this process and the processes it starts (the report's workers, the blind diagnosis);
    returns the flags added. Nothing is added once JAX has started its backend (the flags
    would not apply here, and `XLA_FLAGS`, which `provenance` records, would then claim
    them)."""
    if _backend_started():
        return []
    flags = os.environ.get("XLA_FLAGS", "")
    added = [f for f in FAST_COMPILE_FLAGS if f.split("=")[0] not in flags]
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


CACHE_ENV = "ACCEL_JAX_CACHE_DIR"
"""Where `enable_compilation_cache` keeps compiled programs; `off` (or `0`) disables it."""


def compilation_cache_dir() -> Path | None:
    """The persistent compilation cache folder the entry points use, or None when disabled.

    `$ACCEL_JAX_CACHE_DIR` if set (`off`/`0`/empty disables), else JAX's own
    `$JAX_COMPILATION_CACHE_DIR` if set, else `$XDG_CACHE_HOME/accel_jax/xla`
    (`~/.cache/accel_jax/xla`).
    """
    value = os.environ.get(CACHE_ENV)
    if value is not None:
        return None if value.strip().lower() in ("", "0", "off", "no", "false") else Path(value)
    if os.environ.get("JAX_COMPILATION_CACHE_DIR"):
        return Path(os.environ["JAX_COMPILATION_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "accel_jax" / "xla"


def enable_compilation_cache(path: str | os.PathLike | None = None) -> Path | None:
    """Keep XLA's compiled programs on disk between runs (JAX's persistent compilation cache).

    The design studies are compile-bound at quick sizes: the quick report spends about
    three quarters of its time compiling, and a second run with the cache warm takes a
    fraction of the first. Entries are keyed by the program, the JAX/jaxlib version, the
    device and the XLA flags, so a stale entry is never used for a different computation.

    Called by the CLI's `report` (not on import). Sets both this process's JAX config and
    the environment, so that subprocesses (the blind diagnosis) share the cache. Returns
    the folder, or None when disabled (`ACCEL_JAX_CACHE_DIR=off`) or not writable.
    """
    import jax

    folder = Path(path) if path is not None else compilation_cache_dir()
    if folder is None:
        return None
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None  # a read-only home: run without the cache rather than fail
    if not os.access(folder, os.W_OK):
        return None
    os.environ["JAX_COMPILATION_CACHE_DIR"] = str(folder)
    # Every program, however quick to compile: --quick compiles most of its programs in
    # well under 0.5 s (fast_compile), and tracing them is not cached. Measured on the
    # 2-core CPU: a second quick report takes 92 s with all 752 programs cached (9 MB),
    # 102 s with only those over 0.5 s (14).
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update(
        "jax_persistent_cache_min_compile_time_secs",
        float(os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"]),
    )
    return folder


MAP_LIMIT = 30_000
"""Memory mappings of a process beyond which `bound_compiled_programs` drops its compiled
programs: every XLA:CPU executable keeps a few mappings, and a long-running process that
compiles thousands of programs (a test worker, a blind harness diagnosing hundreds of
records of varying shapes) reaches the kernel's vm.max_map_count (65 530) — then LLVM fails
with 'Cannot allocate memory' and the process segfaults in a later compile."""


def memory_mappings() -> int:
    """The number of this process's memory mappings (0 where /proc is not available)."""
    try:
        with open("/proc/self/maps", "rb") as maps:
            return sum(1 for _ in maps)
    except OSError:
        return 0


def bound_compiled_programs(limit: int = MAP_LIMIT) -> bool:
    """Drop this process's compiled programs (`jax.clear_caches`) when its memory mappings
    exceed `limit`; returns whether it did. Later calls recompile (or read the persistent
    cache, `enable_compilation_cache`)."""
    if memory_mappings() <= limit:
        return False
    import gc

    import jax

    jax.clear_caches()
    gc.collect()
    return True
