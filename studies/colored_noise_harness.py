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
validation do. Scored per class: the verdicts (right: `colored_noise` for output noise,
`moment_noise` for a moment inside the loop, or `cannot_tell` naming the truth; also how
often a coloured noise is credited at either place), by strength band; for each coloured
record both noise candidates' evidence, held-out one-step whiteness (Ljung–Box) and
whether their free-run errors are of the size they predict — the two conditions under
which the diagnosis credits a noise. Float64.

    python studies/colored_noise_harness.py --per-class 30 --out out/colored_noise

Each record's world and noise come from its own generator, seeded by (seed, class,
index), so a record is the same in every run. Results are written whole.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import colored_truth  # noqa: E402
from measured_input_harness import _commit  # noqa: E402
from shards import blind_prelude, run_blind  # noqa: E402

from accel_jax.report import write_json_atomic  # noqa: E402

CLASSES = colored_truth.CLASSES
NOMINAL_LAGS = {"torquer_time_constant": 0.0, "filter_time_constant": 0.0}
BANDS = ((1.0, 3.0), (3.0, 8.0), (8.0, 20.0))
"""Bands of the coloured part's standard deviation over the white noise's."""

_BLIND = blind_prelude(NOMINAL_LAGS) + (
    """for f in sorted(pathlib.Path(sys.argv[2]).glob("*.csv")):
    result = diagnose_many([read_csv(f)], nominal, recommend=False)[0]
    row = {"verdict": result.verdict, "tied": list(result.tied), "reason": result.reason}
    for effect, key in (("colored_noise", "noise"), ("moment_noise", "moment")):
        noise = next((e for e in result.ranking if e["effect"] == effect), {})
        white = noise.get("one_step_whiteness") or {}
        row.update({
            key + "_evidence": noise.get("evidence"),
            key + "_significant": noise.get("significant"),
            key + "_explains": noise.get("explains"),
            key + "_ljung_box": white.get("statistic"),
            key + "_ljung_box_p": white.get("p_value"),
            key + "_variance_consistent": noise.get("variance_consistent"),
            key + "_deterministic_misfit": noise.get("deterministic_misfit"),
            key + "_fit_failed": noise.get("fit_failed"),
            key + "_params": noise.get("params"),
        })
    out[f.stem] = row
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
    """The diagnosis of every CSV in `folder`, in a fresh process that sees only them."""
    return run_blind(_BLIND, str(folder))


RIGHT = {"none": "none", "output_gm": "colored_noise", "moment_gm": "moment_noise"}
"""The verdict that names each class's truth (the place of a coloured noise included)."""

NOISE_EFFECTS = ("colored_noise", "moment_noise")


def _names_truth(row: dict, right: str) -> bool:
    """Named, or `cannot_tell` with the truth among the tied."""
    return row["verdict"] == right or (row["verdict"] == "cannot_tell" and right in row["tied"])


def _credits_noise(row: dict) -> bool:
    """A coloured noise credited, at either place (or a tie between the two)."""
    return row["verdict"] in NOISE_EFFECTS or (
        row["verdict"] == "cannot_tell" and bool(row["tied"])
        and set(row["tied"]) <= set(NOISE_EFFECTS)
    )


def score(truths: dict, rows: dict) -> dict:
    """Per class: verdict counts, the share that names the truth (`RIGHT`: the noise and its
    place, or `cannot_tell` naming it; `none` for the `none` class) and, for the coloured
    classes, the share that credits a coloured noise at either place, by strength band;
    for each noise candidate, how often it was significant, white on the held-out part,
    of consistent size, and a fit that lost to the nominal (`fit_failed`)."""
    out = {}
    for effect in CLASSES:
        names = [n for n in truths if truths[n]["effect"] == effect]
        if not names:
            continue
        right = RIGHT[effect]
        verdicts = [rows[n]["verdict"] for n in names]
        section = {
            "n": len(names),
            "verdicts": {v: verdicts.count(v) for v in sorted(set(verdicts))},
            "right": right,
            "right_share": sum(_names_truth(rows[n], right) for n in names) / len(names),
        }
        nones = sum(v == "none" for v in verdicts)
        if effect == "none":
            # Any other verdict on a record with no coloured noise: a false alarm.
            section["false_alarms"] = {"n": len(names), "count": len(names) - nones}
        else:
            # `none` on a record with a coloured noise (1–20× the white floor): false assurance.
            section["false_assurance"] = nones
        if effect != "none":
            section["noise_credited_share"] = sum(_credits_noise(rows[n]) for n in names) / len(
                names
            )
            section["by_ratio"] = {}
            for low, high in BANDS:
                band = [n for n in names if low <= truths[n]["ratio"] < high]
                section["by_ratio"][f"{low:g}-{high:g}"] = {
                    "n": len(band),
                    "right": sum(_names_truth(rows[n], right) for n in band),
                    "noise_credited": sum(_credits_noise(rows[n]) for n in band),
                }
            for key in ("noise", "moment"):
                if rows[names[0]].get(key + "_evidence", "absent") == "absent":
                    continue  # rows of a run before the candidate existed
                for field in ("significant", "variance_consistent", "fit_failed"):
                    section[f"{key}_{field}"] = sum(
                        bool(rows[n].get(f"{key}_{field}")) for n in names
                    )
                section[key + "_white_held_out"] = sum(
                    (rows[n][key + "_ljung_box_p"] or 0.0) >= 1e-3 for n in names
                )
                section[key + "_ljung_box_median"] = float(
                    np.median([rows[n][key + "_ljung_box"] or np.nan for n in names])
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
    write_json_atomic(args.out / "result.json", result)  # whole or not at all
    print(json.dumps(result["score"], indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
