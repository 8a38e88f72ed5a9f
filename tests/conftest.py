"""Test configuration: the tests run in float64 (the effects measured — δK_a at 0.1 %,
machine-precision agreement between simulators — need it). This is the test suite's
choice; the library itself never changes JAX's global settings."""

from accel_jax._xla import apply_cpu_workarounds

apply_cpu_workarounds()  # XLA:CPU scheduler deadlock on batched nested loops (see _xla.py)

import os  # noqa: E402

# Hermetic timings: the report's persistent compilation cache stays off in the tests unless
# the caller chose a folder (tests/test_xla.py checks the cache itself in a subprocess).
os.environ.setdefault("ACCEL_JAX_CACHE_DIR", "off")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import fcntl  # noqa: E402
import json  # noqa: E402

import pytest  # noqa: E402


@pytest.fixture(scope="session")
def quick_report(tmp_path_factory, worker_id):
    """`accel-jax report --quick` run once per test session and shared by every test (and
    every pytest-xdist worker: the first to arrive runs it under a file lock, the others
    wait and reuse it). Returns the report folder; each study's output is beside it.

    The studies' own tests read their results from here instead of running each study a
    second time."""
    from click.testing import CliRunner

    from accel_jax.cli import main

    base = tmp_path_factory.getbasetemp()
    shared = base.parent if worker_id != "master" else base
    out = shared / "quick_report" / "report"
    done = shared / "quick_report.done"
    with open(shared / "quick_report.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            if not done.exists():
                result = CliRunner().invoke(
                    main, ["report", "--quick", "--no-progress", "--out", str(out)]
                )
                done.write_text(
                    json.dumps({"exit_code": result.exit_code, "output": result.output})
                )
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)
    status = json.loads(done.read_text())
    assert status["exit_code"] == 0, status["output"]
    return out
