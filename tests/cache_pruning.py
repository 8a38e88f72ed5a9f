"""The test suite's persistent compilation cache kept bounded (tests/conftest.py): no JAX
imported here, so that the controller can prune the folder before JAX reads it."""

import time
from pathlib import Path

MAX_AGE_DAYS = 30
"""Entries last used longer ago than this are removed (a program of code long changed)."""

MAX_BYTES = 2 * 1024**3
"""The folder's size kept after pruning (the suite's first 60 % compiled 5,971 programs, 72 MB)."""


def prune_test_cache(folder, max_age_days: float = MAX_AGE_DAYS, max_bytes: int = MAX_BYTES):
    """Remove the files of `folder` last used (read or written: the later of a file's
    access and modification times) over `max_age_days` ago, then the least recently used
    until the rest fit in `max_bytes`. Returns the number of files removed."""
    entries = []
    for path in Path(folder).iterdir():
        try:
            info = path.stat()
        except OSError:  # removed by another process meanwhile
            continue
        if path.is_file():
            entries.append((max(info.st_atime, info.st_mtime), info.st_size, path))
    entries.sort(key=lambda entry: entry[0], reverse=True)  # the most recently used first
    cutoff = time.time() - max_age_days * 86400
    kept, removed = 0, 0
    for used, size, path in entries:
        if used < cutoff or kept + size > max_bytes:
            path.unlink(missing_ok=True)
            removed += 1
        else:
            kept += size
    return removed
