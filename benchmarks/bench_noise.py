"""Long static records (issue 21): a 10⁶-sample record diagnosed cold, and the Whittle
forward selection against the exact time-domain likelihood in the same process.

    python benchmarks/bench_noise.py [--samples 1000000] [--cold-repeats 3] [--out DIR]

1. Cold: `accel-jax diagnose REC.csv` and `accel-jax noise REC.csv` each in a fresh
   process with the compilation cache off (what a new user waits for, CSV reading
   included), median of `--cold-repeats` (3) runs. Target: diagnose ≤ 30 s on the 2-core
   CPU.
2. In this process (float64, median of 3 after one warm-up): `select_sensor_noise` on the
   whole record, and on its first 10⁵ samples beside the baseline, the exact Kalman-filter
   maximum likelihood of white + Gauss–Markov (`fit_maximum_likelihood`, one structure
   only) on the same 10⁵ samples: the ratio is per record of equal length.

The record: white 5 mg + a 1.5 mg line at 0.56 Hz + flicker B = 0.3 mg + a 20 Hz
second-order low-pass + a 3.3 mg output grid at 100 Hz (studies/noise_truth.py), the shape
of the MEMS record of the issue.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "studies"))
import noise_truth  # noqa: E402

import accel_jax as aj  # noqa: E402
from accel_jax.report import provenance, write_json_atomic  # noqa: E402

DT = 0.01
TRUTH = {
    "white": 5e-3,
    "lines": [(0.56, 1.5e-3)],
    "flicker": 3e-4,
    "bandlimit": 20.0,
    "quantization": 3.3e-3,
    "level": -1.0,
}


def _cold(command: list, env: dict) -> dict:
    started = time.perf_counter()
    run = subprocess.run(command, capture_output=True, text=True, env=env, timeout=900)
    wall = time.perf_counter() - started
    verdict = next(
        (ln for ln in run.stdout.splitlines() if ln.startswith(("verdict", "effects"))), ""
    )
    return {"wall_s": wall, "returncode": run.returncode, "line": verdict.strip()}


def _cold_median(command: list, env: dict, repeats: int) -> dict:
    """`repeats` cold runs of one command: the median wall time, each run's, and the
    verdict line (which must be the same in every run)."""
    runs = [_cold(command, env) for _ in range(repeats)]
    walls = [r["wall_s"] for r in runs]
    lines = {r["line"] for r in runs}
    return {
        "wall_s": statistics.median(walls),
        "runs_s": walls,
        "returncode": max(r["returncode"] for r in runs),
        "line": runs[0]["line"] if len(lines) == 1 else f"differs between runs: {sorted(lines)}",
    }


def _median_time(fn, repeats=3):
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=1_000_000)
    parser.add_argument("--out", default="out/bench_noise")
    parser.add_argument(
        "--cold-repeats", type=int, default=3, help="cold runs of each command (median)"
    )
    args = parser.parse_args(argv)
    rng = np.random.default_rng(2026)
    x = noise_truth.record(rng, args.samples, DT, TRUTH)
    result = {"samples": args.samples, "sample_interval_s": DT, "truth": str(TRUTH)}
    cli = Path(sys.executable).parent / "accel-jax"
    env = {**os.environ, "ACCEL_JAX_CACHE_DIR": "off"}
    with tempfile.TemporaryDirectory() as tmp:
        csv = Path(tmp) / "static.csv"
        aj.write_csv(csv, aj.NoiseData(np.arange(x.size) * DT, x))
        print("cold diagnose…", flush=True)
        result["cold_diagnose"] = _cold_median(
            [str(cli), "diagnose", str(csv)], env, args.cold_repeats
        )
        print("cold noise…", flush=True)
        result["cold_noise"] = _cold_median([str(cli), "noise", str(csv)], env, args.cold_repeats)
    print("warm selection…", flush=True)
    full_s, found = _median_time(lambda: aj.noise.select_sensor_noise(x, DT), repeats=2)
    result["warm_select_full_s"] = full_s
    result["full_verdict"] = found.verdict
    head = x[:100_000]
    whittle_s, _ = _median_time(lambda: aj.noise.select_sensor_noise(head, DT))
    start = aj.noise.NoiseSum((aj.noise.WhiteNoise(5e-3), aj.noise.GaussMarkov(1e-3, 0.1)))
    exact_s, _ = _median_time(
        lambda: aj.noise.fit_maximum_likelihood(start, head - head.mean(), DT, throw=False)
    )
    result["head_1e5"] = {
        "whittle_forward_selection_s": whittle_s,
        "exact_kalman_ml_one_structure_s": exact_s,
        "ratio_exact_over_whittle_selection": exact_s / whittle_s,
    }
    result["targets"] = {"cold_diagnose_le_30_s": result["cold_diagnose"]["wall_s"] <= 30}
    result["provenance"] = provenance(precision="float64")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "result.json", result)
    print(json.dumps({k: v for k, v in result.items() if k != "provenance"}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
