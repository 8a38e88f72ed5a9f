"""Blind check of the step diagnosis on records with coloured noise of any strength and at
either place: at the output, and as a moment inside the loop.

Every record comes from the independent truth simulator `colored_truth.py` (SciPy, written
from the loop equations without reading the library's effect code; it reuses
`step_truth.py`'s world: device, test sequence, recorder conventions). Classes:

- `output_gm`: a stationary Gauss–Markov noise added at the output, its standard deviation
  1–20× the white noise's (log-uniform), its correlation time from 3 samples to 1/20 of
  the record (log-uniform);
- `moment_gm`: a stationary Gauss–Markov moment inside the loop (filtered by it), scaled so
  that its part of the output has 1–20× the white noise's standard deviation, the same
  range of correlation times;
- `none`: the same worlds with white noise only (false alarms).

The diagnosis runs in a fresh process that sees only the CSV files, against the reference
device with T_dm = T_f = 0 (the truths' lags), as `measured_input_harness.py` and the blind
validation do. Scored per class: the verdicts (the library's noise effect is
`colored_noise`; right for both coloured classes, which the library does not tell apart
yet), by strength band; for each coloured record the `colored_noise` candidate's evidence,
its held-out one-step whiteness (Ljung–Box) and whether its free-run errors are of the
size it predicts — the two conditions under which the diagnosis credits a noise. Float64.

    python studies/colored_noise_harness.py --per-class 30 --out out/colored_noise

Each record's world and noise come from its own generator, seeded by (seed, class,
index), so a record is the same in every run. Results are written whole.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import colored_truth  # noqa: E402
from measured_input_harness import _commit  # noqa: E402

CLASSES = colored_truth.CLASSES
NOMINAL_LAGS = {"torquer_time_constant": 0.0, "filter_time_constant": 0.0}
BANDS = ((1.0, 3.0), (3.0, 8.0), (8.0, 20.0))
"""Bands of the coloured part's standard deviation over the white noise's."""

_BLIND = (
    f"NOMINAL_LAGS = {NOMINAL_LAGS!r}\n"
    + """
import json, pathlib, sys
import accel_jax
from accel_jax._runtime import apply_device, enable_compilation_cache
apply_device(latency_bound=True)
enable_compilation_cache()
import jax
jax.config.update("jax_enable_x64", True)
from accel_jax import NominalDevice, read_csv
from accel_jax.diagnose import diagnose_many
nominal = NominalDevice.reference(**NOMINAL_LAGS)
out = {}
for f in sorted(pathlib.Path(sys.argv[2]).glob("*.csv")):
    result = diagnose_many([read_csv(f)], nominal, recommend=False)[0]
    noise = next((e for e in result.ranking if e["effect"] == "colored_noise"), {})
    white = noise.get("one_step_whiteness") or {}
    out[f.stem] = {
        "verdict": result.verdict,
        "tied": list(result.tied),
        "reason": result.reason,
        "noise_evidence": noise.get("evidence"),
        "noise_significant": noise.get("significant"),
        "noise_explains": noise.get("explains"),
        "noise_ljung_box": white.get("statistic"),
        "noise_ljung_box_p": white.get("p_value"),
        "noise_variance_consistent": noise.get("variance_consistent"),
        "noise_deterministic_misfit": noise.get("deterministic_misfit"),
        "noise_params": noise.get("params"),
    }
pathlib.Path(sys.argv[1]).write_text(json.dumps(out, default=float))
"""
)


def record_rng(seed: int, effect: str, index: int) -> np.random.Generator:
    """One record's generator: its world, then its noise (`colored_truth.make`)."""
    return np.random.default_rng([seed, CLASSES.index(effect), index])


def write_records(per_class: int, seed: int, folder: Path, classes=CLASSES) -> dict:
    """Draw and simulate `per_class` records of each class, write them as CSV files named
    `<class>_<index>`; returns their truths by name."""
    from accel_jax import StepData, write_csv

    truths = {}
    for effect in classes:
        for i in range(per_class):
            rng = record_rng(seed, effect, i)
            truth = colored_truth.draw_truth(rng, effect)
            t, u, y, _ = colored_truth.make(truth, rng)
            name = f"{effect}_{i:04d}"
            write_csv(folder / f"{name}.csv", StepData(t, u, y))
            truths[name] = truth
    return truths


def diagnose_blind(folder: Path) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "rows.json"
        subprocess.run(
            [sys.executable, "-c", _BLIND, str(out), str(folder)],
            check=True,
            cwd=Path(__file__).resolve().parent.parent,
        )
        return json.loads(out.read_text())


def score(truths: dict, rows: dict) -> dict:
    """Per class: verdict counts, the share named `colored_noise` (coloured classes) or
    `none` (the `none` class), by strength band; for the coloured classes, how often the
    noise candidate was significant, white on the held-out part, and of consistent size."""
    out = {}
    for effect in CLASSES:
        names = [n for n in truths if truths[n]["effect"] == effect]
        if not names:
            continue
        right = "none" if effect == "none" else "colored_noise"
        verdicts = [rows[n]["verdict"] for n in names]
        section = {
            "n": len(names),
            "verdicts": {v: verdicts.count(v) for v in sorted(set(verdicts))},
            "right": right,
            "right_share": verdicts.count(right) / len(names),
        }
        if effect != "none":
            section["by_ratio"] = {}
            for low, high in BANDS:
                band = [n for n in names if low <= truths[n]["ratio"] < high]
                section["by_ratio"][f"{low:g}-{high:g}"] = {
                    "n": len(band),
                    "right": sum(rows[n]["verdict"] == right for n in band),
                }
            for key in ("noise_significant", "noise_variance_consistent"):
                section[key] = sum(bool(rows[n][key]) for n in names)
            section["noise_white_held_out"] = sum(
                (rows[n]["noise_ljung_box_p"] or 0.0) >= 1e-3 for n in names
            )
            section["noise_ljung_box_median"] = float(
                np.median([rows[n]["noise_ljung_box"] or np.nan for n in names])
            )
        out[effect] = section
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--per-class", type=int, default=10)
    parser.add_argument("--seed", type=int, default=2028)
    parser.add_argument("--classes", nargs="+", choices=CLASSES, default=list(CLASSES))
    parser.add_argument("--out", type=Path, default=Path("out/colored_noise"))
    args = parser.parse_args(argv)
    if args.per_class < 1:
        parser.error("--per-class must be at least 1")
    start = time.time()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "records"
        truths = write_records(args.per_class, args.seed, folder, args.classes)
        rows = diagnose_blind(folder)
    result = {
        "commit": _commit(),
        "seed": args.seed,
        "per_class": args.per_class,
        "nominal": "the reference device with T_dm = T_f = 0",
        "seconds": time.time() - start,
        "score": score(truths, rows),
        "records": {
            n: {
                "effect": truths[n]["effect"],
                "ratio": truths[n]["ratio"],
                "tau_s": truths[n]["tau_s"],
                "rate_Hz": truths[n]["rate"],
                **rows[n],
            }
            for n in truths
        },
    }
    args.out.mkdir(parents=True, exist_ok=True)
    partial = args.out / "result.json.partial"
    partial.write_text(json.dumps(result, indent=1, default=float))
    partial.replace(args.out / "result.json")
    print(json.dumps(result["score"], indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
