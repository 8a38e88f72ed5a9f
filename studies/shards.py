"""A blind harness's run spread over machines (one definition: `sim_to_real_validation` and
`measured_input_harness` read it), and its diagnosis in a fresh process (`run_blind`, one
definition: `sim_to_real_validation` and the measured-input, discovery, coloured-noise and
vibration-discovery harnesses read it).

`--shard k/n` diagnoses records k, k+n, k+2n, … of the draw; every shard draws the same
truths (same seed), so the shards of one draw are disjoint and together are the whole
draw, and `--merge` joins their results and scores them as one run."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path


def shard_indices(count: int, shard: tuple[int, int]) -> list[int]:
    """The record indices of shard k of n (`--shard k/n`): every n-th from k."""
    k, n = shard
    if not (n >= 1 and 0 <= k < n):
        raise ValueError(f"--shard {k}/{n}: it must be k/n with 0 ≤ k < n")
    return list(range(k, count, n))


def parse_shard(text: str) -> tuple[int, int]:
    """`--shard`'s argparse type: "k/n" as (k, n), or one clear error."""
    try:
        k, n = (int(x) for x in text.split("/"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: give the shard as k/n, e.g. 0/4") from None
    if not (n >= 1 and 0 <= k < n):
        raise argparse.ArgumentTypeError(f"{text!r}: it must be k/n with 0 ≤ k < n")
    return k, n


def blind_prelude(nominal_lags: dict) -> str:
    """The start every harness's diagnosing script shares: the package imported, the
    process placed as a latency-bound one, the compilation cache on, float64, and
    `nominal` the reference device with the lags `nominal_lags`; then an empty `out`
    (the rows by record name) for the script to fill."""
    return f"NOMINAL_LAGS = {nominal_lags!r}\n" + """
import json, pathlib, sys
import accel_jax
from accel_jax._placement import apply_device
from accel_jax._cache import enable_compilation_cache
apply_device(latency_bound=True)
enable_compilation_cache()
import jax
jax.config.update("jax_enable_x64", True)
from accel_jax import DataError, NominalDevice, read_csv
from accel_jax.diagnose import diagnose_many
nominal = NominalDevice.reference(**NOMINAL_LAGS)
out = {}
"""


def run_blind_side_by_side(
    code: str, groups: list[list[str]], cpus: list[int] | None = None
) -> list[dict]:
    """`run_blind(code, *group)` for every group at once, each in its own fresh process
    allowed on every CPU of `cpus` (the operating system balances them; `None`: this
    process's CPUs); the JSON each writes, in `groups`' order. A failure in one stops the
    others and raises `subprocess.CalledProcessError`."""
    import os
    import time

    root = Path(__file__).resolve().parent.parent
    with tempfile.TemporaryDirectory() as tmp:
        outs = [Path(tmp) / f"rows_{i}.json" for i in range(len(groups))]
        # A child inherits the calling thread's CPU mask: set for the spawns, then restored
        # (not a `preexec_fn`, which would fork this multithreaded process).
        pinned = cpus is not None and hasattr(os, "sched_setaffinity")
        before = os.sched_getaffinity(0) if pinned else None
        procs = []
        try:
            if pinned:
                try:
                    os.sched_setaffinity(0, cpus)
                except OSError:  # not permitted: the children keep this process's CPUs
                    pass
            for out, group in zip(outs, groups, strict=True):
                command = [sys.executable, "-c", code, str(out), *group]
                procs.append(subprocess.Popen(command, cwd=root))
        finally:
            if pinned:
                os.sched_setaffinity(0, before)
        failed = None
        try:
            # Polled, not waited for in turn: a child that fails stops the others at once.
            while failed is None and any(proc.poll() is None for proc in procs):
                failed = next((p for p in procs if p.poll() not in (None, 0)), None)
                time.sleep(0.2)
            failed = failed or next((p for p in procs if p.returncode != 0), None)
        finally:
            for proc in procs:  # no child outlives this call
                if proc.poll() is None:
                    proc.kill()
                    proc.wait()
        if failed is not None:
            raise subprocess.CalledProcessError(failed.returncode, failed.args)
        return [json.loads(out.read_text()) for out in outs]


def run_blind(code: str, *args: str) -> dict:
    """Run `code` (a harness's diagnosing script) in a fresh Python process, in the
    repository root, as `python -c code OUT *args`, and return the JSON it writes to OUT.
    The child sees only what `args` name (the records' files), never the truth; a failure
    in it raises `subprocess.CalledProcessError`."""
    return run_blind_side_by_side(code, [list(args)])[0]
