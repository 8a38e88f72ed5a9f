"""The test suite's persistent compilation cache is kept bounded (tests/cache_pruning.py)."""

import os
import time

from cache_pruning import prune_test_cache


def _entry(folder, name, size, days_ago):
    path = folder / name
    path.write_bytes(b"x" * size)
    then = time.time() - days_ago * 86400
    os.utime(path, (then, then))
    return path


def test_old_entries_then_the_least_recently_used_beyond_the_size_are_removed(tmp_path):
    old = _entry(tmp_path, "old-cache", 10, days_ago=40)
    recent = [_entry(tmp_path, f"e{i}-cache", 100, days_ago=i) for i in range(5)]
    assert prune_test_cache(tmp_path, max_age_days=30, max_bytes=350) == 3
    assert not old.exists()
    assert [p.exists() for p in recent] == [True, True, True, False, False]
    # Read since: its access time counts as a use, whatever its modification time.
    now = time.time()
    os.utime(recent[2], (now, now - 50 * 86400))
    assert prune_test_cache(tmp_path, max_age_days=30, max_bytes=350) == 0
    assert prune_test_cache(tmp_path, max_age_days=30, max_bytes=150) == 2
    assert [p.exists() for p in recent[:3]] == [False, False, True]
