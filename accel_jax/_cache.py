"""The package's persistent state between runs: its cache folder (`cache_home`), JAX's
persistent compilation cache (`enable_compilation_cache`), and the bound on a long-running
process's compiled programs (`bound_compiled_programs`). Process settings, as `_runtime`'s
called by the entry points, never on import.
"""

from __future__ import annotations

import os
from pathlib import Path

CACHE_ENV = "ACCEL_JAX_CACHE_DIR"
"""Where `enable_compilation_cache` keeps compiled programs; `off` (or `0`) disables it."""


def cache_home() -> Path:
    """The package's folder for what it keeps between runs: `$XDG_CACHE_HOME/accel_jax`
    (`~/.cache/accel_jax`)."""
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "accel_jax"


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
    return cache_home() / "xla"


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
