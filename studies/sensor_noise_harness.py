"""Blind harness of the real-sensor noise effects (`accel_jax.select_sensor_noise`).

Records are drawn by `studies/noise_truth.py` (NumPy/SciPy only, written apart from the
diagnosing code) with the conventions a user's records come with: sample rates of 50 to
400 Hz, a level anywhere within ±1.2 g (and either polarity), white noise σ_w from 0.1 to
10 mg, and each effect at a magnitude drawn from a stated range (`RANGES`): alone, in
composites of two or three effects, and absent (white records: the false-alarm rate). The
diagnosis sees only the samples and the sample interval.

Scored: each effect named (alone or within a composite verdict) per effect, the false
alarms on white records (any verdict but `none`), the periodic lines' frequencies
(relative error of the line nearest the truth) and the quantisation steps.

Run: `python studies/sensor_noise_harness.py [--per-effect 100] [--samples 10000]
[--jobs 2] [--out DIR]` (float64; about 5 s of one core per record).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import noise_truth  # noqa: E402

EFFECTS = (
    "gauss_markov",
    "exp_cosine",
    "random_walk",
    "flicker",
    "bandlimit",
    "sinusoid",
    "startup_transient",
    "quantization",
)

RANGES = {
    "sample_rate_Hz": (50.0, 100.0, 200.0, 400.0),
    "white_g": (1e-4, 1e-2),
    "gauss_markov": {"sigma_over_white": (0.5, 2.0), "tau_samples": (3.0, 100.0)},
    "exp_cosine": {"sigma_over_white": (0.5, 2.0), "period_samples": (4.0, 50.0), "q": (2, 8)},
    "random_walk": {"walk_over_record_over_white": (1.0, 5.0)},
    "flicker": {"B_over_white": (0.05, 0.3)},
    "bandlimit": {"corner_over_nyquist": (0.2, 0.7)},
    "sinusoid": {"amplitude_over_white": (0.15, 0.5), "frequency_over_rate": (0.005, 0.45)},
    "startup_transient": {"amplitude_over_white": (3.0, 10.0), "tau_over_record": (0.005, 0.05)},
    "quantization": {"step_over_white": (0.5, 2.0)},
}
"""Truth ranges (log-uniform where a ratio)."""


def _log_uniform(rng, lo_hi):
    lo, hi = lo_hi
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def draw(rng: np.random.Generator, effects, n: int) -> dict:
    """A truth: its record's sample interval, the `noise_truth.record` spec, and the facts
    the scoring needs."""
    rate = float(rng.choice(RANGES["sample_rate_Hz"]))
    dt = 1 / rate
    white = _log_uniform(rng, RANGES["white_g"])
    spec = {"white": white, "level": float(rng.choice([-1, 1]) * rng.uniform(0.0, 1.2))}
    facts = {"effects": list(effects), "sample_rate_Hz": rate, "white_g": white}
    for e in effects:
        r = RANGES[e]
        if e == "gauss_markov":
            spec[e] = (
                white * _log_uniform(rng, r["sigma_over_white"]),
                _log_uniform(rng, r["tau_samples"]) * dt,
            )
        elif e == "exp_cosine":
            beta = 2 * math.pi / (_log_uniform(rng, r["period_samples"]) * dt)
            spec[e] = (
                white * _log_uniform(rng, r["sigma_over_white"]),
                beta / _log_uniform(rng, r["q"]),
                beta,
            )
        elif e == "random_walk":
            walk = white * _log_uniform(rng, r["walk_over_record_over_white"])
            spec[e] = walk**2 / (n * dt)
        elif e == "flicker":
            spec[e] = white * _log_uniform(rng, r["B_over_white"])
        elif e == "bandlimit":
            spec[e] = _log_uniform(rng, r["corner_over_nyquist"]) * rate / 2
        elif e == "sinusoid":
            f = _log_uniform(rng, r["frequency_over_rate"]) * rate
            spec["lines"] = [(f, white * _log_uniform(rng, r["amplitude_over_white"]))]
            facts["line_Hz"] = f
        elif e == "startup_transient":
            spec["transient"] = (
                float(rng.choice([-1, 1])) * white * _log_uniform(rng, r["amplitude_over_white"]),
                _log_uniform(rng, r["tau_over_record"]) * n * dt,
            )
        elif e == "quantization":
            spec[e] = white * _log_uniform(rng, r["step_over_white"])
            facts["step_g"] = spec[e]
    return {"dt": dt, "spec": spec, "facts": facts}


def plan(per_effect: int, seed: int) -> list:
    """(effects, seed) of every record: `per_effect` single-effect records per effect, as
    many white ones, and composites of two or three effects until every effect appears in
    `per_effect` of them too."""
    rng = np.random.default_rng(seed)
    jobs = [((), int(rng.integers(2**31)))]
    jobs = [((), int(rng.integers(2**31))) for _ in range(per_effect)]
    for e in EFFECTS:
        jobs += [((e,), int(rng.integers(2**31))) for _ in range(per_effect)]
    counts = dict.fromkeys(EFFECTS, 0)
    while min(counts.values()) < per_effect:
        k = int(rng.integers(2, 4))
        lacking = [e for e in EFFECTS if counts[e] < per_effect]
        first = str(rng.choice(lacking))
        others = [e for e in EFFECTS if e != first]
        combo = (first, *rng.choice(others, size=k - 1, replace=False).tolist())
        # one stochastic resonance per record: gauss_markov and exp_cosine together are
        # not told apart from one exp_cosine of wider band by any likelihood of this length
        if {"gauss_markov", "exp_cosine"} <= set(combo):
            continue
        for e in combo:
            counts[e] += 1
        jobs.append((tuple(sorted(combo)), int(rng.integers(2**31))))
    return jobs


def run_one(job, n: int) -> dict:
    import accel_jax as aj

    effects, seed = job
    rng = np.random.default_rng(seed)
    truth = draw(rng, effects, n)
    x = noise_truth.record(rng, n, truth["dt"], truth["spec"])
    started = time.perf_counter()
    try:
        found = aj.select_sensor_noise(x, truth["dt"])
    except Exception as error:  # a failure is a result: recorded, not hidden
        return {"truth": truth["facts"], "error": f"{type(error).__name__}: {error}"}
    out = {
        "truth": truth["facts"],
        "verdict": found.verdict,
        "effects": list(found.effects),
        "unexplained": found.unexplained,
        "seconds": time.perf_counter() - started,
    }
    if "line_Hz" in truth["facts"] and "sinusoid" in found.parameters:
        lines = [line["frequency_Hz"] for line in found.parameters["sinusoid"]]
        nearest = min(lines, key=lambda f: abs(f - truth["facts"]["line_Hz"]))
        out["line_relative_error"] = abs(nearest / truth["facts"]["line_Hz"] - 1)
    if "step_g" in truth["facts"] and found.quantization is not None:
        out["step_relative_error"] = abs(found.quantization["step"] / truth["facts"]["step_g"] - 1)
    return out


def _worker(args):
    job, n = args
    os.environ.setdefault("XLA_FLAGS", "")
    import jax

    jax.config.update("jax_enable_x64", True)
    return run_one(job, n)


def score(rows: list) -> dict:
    per = {}
    for e in EFFECTS:
        with_e = [r for r in rows if e in r["truth"]["effects"] and "error" not in r]
        named = [r for r in with_e if e in r["effects"]]
        per[e] = {
            "records": len(with_e),
            "named": len(named),
            "rate": len(named) / max(len(with_e), 1),
        }
    white = [r for r in rows if not r["truth"]["effects"] and "error" not in r]
    alarms = [r for r in white if r["verdict"] != "none"]
    lines = [r["line_relative_error"] for r in rows if "line_relative_error" in r]
    steps = [r["step_relative_error"] for r in rows if "step_relative_error" in r]
    extras = {}
    for r in rows:
        if "error" in r:
            continue
        for e in r["effects"]:
            if e not in r["truth"]["effects"]:
                extras[e] = extras.get(e, 0) + 1
    return {
        "per_effect": per,
        "white_records": len(white),
        "false_alarms": len(alarms),
        "false_alarm_rate": len(alarms) / max(len(white), 1),
        "false_alarm_verdicts": sorted({r["verdict"] for r in alarms}),
        "lines_within_1pct": sum(e <= 0.01 for e in lines),
        "lines_scored": len(lines),
        "steps_within_5pct": sum(e <= 0.05 for e in steps),
        "steps_scored": len(steps),
        "spurious_effects_named": extras,
        "errors": [r["error"] for r in rows if "error" in r],
        "median_seconds": float(np.median([r["seconds"] for r in rows if "seconds" in r])),
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--per-effect", type=int, default=100)
    parser.add_argument("--samples", type=int, default=10000)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--seed", type=int, default=2026)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    jobs = plan(args.per_effect, args.seed)
    started = time.perf_counter()
    if args.jobs > 1:
        import multiprocessing as mp

        rows = []
        with mp.get_context("spawn").Pool(args.jobs) as pool:
            for row in pool.imap(_worker, [(j, args.samples) for j in jobs], chunksize=2):
                rows.append(row)
                if len(rows) % 100 == 0:
                    print(
                        f"{len(rows)}/{len(jobs)} records, {time.perf_counter() - started:.0f} s",
                        flush=True,
                    )
    else:
        rows = [_worker((j, args.samples)) for j in jobs]
    result = {
        "assumptions": {
            "samples_per_record": args.samples,
            "held_out": "the last third of each record",
            "ranges": RANGES,
            "truth_generator": "studies/noise_truth.py (NumPy/SciPy, not accel_jax)",
            "precision": "float64",
            "seed": args.seed,
        },
        "records": len(rows),
        "score": score(rows),
        "wall_s": time.perf_counter() - started,
        "rows": rows,
    }
    text = json.dumps(result, indent=1, default=float)
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        tmp = args.out / "result.json.tmp"
        tmp.write_text(text)
        tmp.replace(args.out / "result.json")
    print(json.dumps(result["score"], indent=1, default=float))
    print(f"{len(rows)} records in {result['wall_s']:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
