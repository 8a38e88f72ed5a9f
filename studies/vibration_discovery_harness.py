"""Blind check of the discovery of a missing term in vibration tables
(`accel_jax.diagnose.vibration.discover`) on tables the library did not make.

Every table comes from `vibration_truth.py`, an independent truth simulator written from
the physics without the diagnosis's code, on its randomised conventions (test plans,
repeats, row noise, sampled records with white or band-limited random vibration, LSB, row
order, a standard k2/k3 in 30 % of devices).

The denominator is fixed here, before any run (`EXPECTED`): each class's generating
term(s) in the term library. A table is right when the best discovered subset holds every
generating term and nothing but the truth's terms (the class's and the device's own
standard k2/k3, which 30 % of the truth's devices carry), or the one tie it lists does;
credible-and-right counts toward the figure. On the class whose cause no static term
describes (`frequency_dependent`) and on `none` tables, a credible subset holding a term
the truth lacks is a false discovery; a `none` table whose device has no term at all is
clean, and its verdict must not be overturned.
Leave-one-out classes (`loo_k2`, `loo_k4`, `loo_asymmetry`) are a library effect's own
term on a device otherwise clean, diagnosed with that effect removed from the library.

The diagnosis runs in a fresh process that sees only the CSV files (`--discover`'s
library call, `diagnose_many(..., discover=True)`). Float64.

    python studies/vibration_discovery_harness.py --per-class 20 --out out/vibration_discovery
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
import vibration_truth  # noqa: E402
from measured_input_harness import _commit  # noqa: E402
from shards import run_blind  # noqa: E402

from accel_jax.report import write_json_atomic  # noqa: E402

LEFT_OUT = {"loo_k2": "k2", "loo_k4": "k4", "loo_asymmetry": "asymmetry"}
"""Leave-one-out classes: the effect removed from the library; its term generates the
table (drawn by `_leave_one_out`)."""

EXPECTED = {
    **{c: tuple(sorted(vibration_truth.TERM_OF_CLASS[c])) for c in vibration_truth.TERM_OF_CLASS},
    "none": None,
    "frequency_dependent": None,
    **{c: (term,) for c, term in LEFT_OUT.items()},
}
"""Each class's generating term(s) in the term library, sorted (None: nothing to find)."""

CLASSES = tuple(EXPECTED)

_LOO_SIZE = {"k2": (0.3, 30.0), "k4": (0.01, 1.0), "asymmetry": (3.0, 50.0)}
"""The left-out effects' magnitudes, log-uniform with a random sign (the blind
validation's ranges: ppm/g, ppm/g³, ppm)."""


def _leave_one_out(seed: int, effect: str):
    """A clean table of the truth (its plan, noise and conventions) plus the left-out
    effect's term, c·a3², c·a3⁴ or ½c|a3| averaged over each row as the truth averages
    (`vibration_truth.row_average` where it has one, else added from the same record)."""
    data, truth = vibration_truth.draw(seed, "none")
    rng = np.random.default_rng([seed, 7])
    low, high = _LOO_SIZE[effect]
    value = float(np.exp(rng.uniform(np.log(low), np.log(high)))) * rng.choice([-1.0, 1.0])
    a_in, b3, s = (np.asarray(x, float) for x in (data.a_in, data.vib_amp, data.vib_rms))
    theta = 2 * np.pi * (np.arange(4096) + 0.5) / 4096
    z = np.random.default_rng([seed, 8]).normal(size=(a_in.size, 4096))
    z = (z - z.mean(axis=1, keepdims=True)) / z.std(axis=1, keepdims=True)
    a3 = a_in[:, None] + b3[:, None] * np.sin(theta + rng.uniform(0, 2 * np.pi, (a_in.size, 1)))
    a3 = a3 + s[:, None] * z
    signal = {"k2": a3**2, "k4": a3**4, "asymmetry": 0.5 * np.abs(a3)}[effect]
    a_out = np.asarray(data.a_out) + value * 1e-6 * signal.mean(axis=1)
    truth = {**truth, "class": f"loo_{effect}", effect: value, "terms": [*truth["terms"], effect]}
    return type(data)(**{**{f: getattr(data, f) for f in _FIELDS}, "a_out": a_out}), truth


_FIELDS = ("a_in", "vib_amp", "vib_freq", "vib_rms", "a_out", "vib_amp_oa", "vib_amp_pa")


def write_tables(per_class: int, seed: int, folder: Path, classes, first: int = 0) -> dict:
    """Write `per_class` tables of each class under folder/<class>/; their truths by name."""
    from accel_jax import write_csv

    truths = {}
    for effect in classes:
        for i in range(first, first + per_class):
            record_seed = seed * 100_003 + CLASSES.index(effect) * 10_007 + i
            if effect in LEFT_OUT:
                data, truth = _leave_one_out(record_seed, LEFT_OUT[effect])
            else:
                data, truth = vibration_truth.draw(record_seed, effect)
            name = f"{effect}_{i:04d}"
            write_csv(folder / effect / f"{name}.csv", data)
            truths[name] = {"class": effect, **truth}
    return truths


_BLIND = r"""
import json, sys
from pathlib import Path
import jax
jax.config.update("jax_enable_x64", True)
from accel_jax import read_csv
from accel_jax.diagnose import diagnose_many
from accel_jax.diagnose.vibration import entry, vibration_effects
out, folder = Path(sys.argv[1]), Path(sys.argv[2])
rows = {}
for group in sorted(p for p in folder.iterdir() if p.is_dir()):
    left_out = {"loo_k2": "k2", "loo_k4": "k4", "loo_asymmetry": "asymmetry"}.get(group.name)
    effects = [e for e in vibration_effects() if e.name != left_out]
    entry.vibration_effects = lambda effects=effects: effects
    files = sorted(group.glob("*.csv"))
    plain = diagnose_many([read_csv(f) for f in files])
    found = diagnose_many([read_csv(f) for f in files], discover=True)
    for f, before, result in zip(files, plain, found):
        rows[f.stem] = {"verdict_without": before.verdict, **result.to_dict()}
out.write_text(json.dumps(rows, default=float))
"""


def diagnose_blind(folder: Path) -> dict:
    """The diagnosis of every CSV in `folder`, in a fresh process that sees only them."""
    return run_blind(_BLIND, str(folder))


def judge(truth: dict, row: dict) -> dict:
    """One table's outcome: the rating, the best terms, right or not, its coefficients'
    z-scores against the truth."""
    effect = truth["class"]
    discovery = row.get("discovery") or {}
    rating = discovery.get("rating", "not run")
    best = discovery.get("best")
    tie = discovery.get("tie")
    expected = EXPECTED[effect]
    allowed = set(truth["terms"])  # the class's terms and the device's own k2/k3

    def fits(candidate) -> bool:
        terms = set(candidate["terms"]) if candidate else set()
        return bool(expected) and set(expected) <= terms <= allowed

    right = fits(best) or fits(tie)
    z = []
    if best and fits(best):
        for column in best["columns"]:
            value = truth.get(column["term"], 0.0)
            z.append((column["coefficient"] - value) / column["sigma"])
    false = rating == "credible" and not (
        set(best["terms"]) <= allowed or (tie is not None and set(tie["terms"]) <= allowed)
    )
    return {
        "rating": rating,
        "best": sorted(best["terms"]) if best else [],
        "right": right,
        "credible": rating == "credible",
        "credible_and_right": right and rating == "credible",
        "false_credible": false,
        "z": z,
        "overturned": discovery.get("overturned"),
    }


def score(truths: dict, rows: dict) -> dict:
    by_class: dict[str, dict] = {}
    z_all = []
    for name, truth in truths.items():
        outcome = judge(truth, rows[name])
        entry = by_class.setdefault(
            truth["class"],
            {
                "tables": 0,
                "credible": 0,
                "right": 0,
                "credible_and_right": 0,
                "false_credible": 0,
                "unexplained": 0,
                "unexplained_without": 0,
                "overturned": 0,
                "clean": 0,
                "clean_overturned": 0,
                "best": {},
            },
        )
        entry["tables"] += 1
        entry["unexplained"] += rows[name]["verdict"] == "unexplained"
        entry["unexplained_without"] += rows[name]["verdict_without"] == "unexplained"
        entry["overturned"] += outcome["overturned"] is not None
        clean = not truth["terms"]
        entry["clean"] += clean
        entry["clean_overturned"] += clean and outcome["overturned"] is not None
        key = "+".join(outcome["best"]) or "-"
        entry["best"][key] = entry["best"].get(key, 0) + 1
        for k in ("credible", "right", "credible_and_right", "false_credible"):
            entry[k] += outcome[k]
        if outcome["credible_and_right"]:
            z_all.extend(outcome["z"])
    findable = [c for c in by_class if EXPECTED[c] is not None]
    nothing = [c for c in by_class if EXPECTED[c] is None]
    z = np.abs(np.asarray(z_all))
    return {
        "by_class": by_class,
        "findable_credible_and_right": sum(by_class[c]["credible_and_right"] for c in findable),
        "findable_tables": sum(by_class[c]["tables"] for c in findable),
        "false_credible": sum(e["false_credible"] for e in by_class.values()),
        "nothing_to_find_false_credible": sum(by_class[c]["false_credible"] for c in nothing),
        "nothing_to_find_tables": sum(by_class[c]["tables"] for c in nothing),
        "clean_tables": sum(e["clean"] for e in by_class.values()),
        "clean_overturned": sum(e["clean_overturned"] for e in by_class.values()),
        "coefficients_within_2_sigma": float(np.mean(z <= 2)) if z.size else None,
        "coefficients": int(z.size),
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--per-class", type=int, default=20)
    parser.add_argument("--seed", type=int, default=20261203)
    parser.add_argument("--classes", default=",".join(CLASSES))
    parser.add_argument("--out", type=Path, default=Path("out/vibration_discovery"))
    args = parser.parse_args(argv)
    classes = [c for c in args.classes.split(",") if c]
    unknown = sorted(set(classes) - set(CLASSES))
    if unknown:
        parser.error(f"unknown class(es) {unknown}; known: {', '.join(CLASSES)}")
    started = time.time()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        truths = write_tables(args.per_class, args.seed, folder, classes)
        rows = diagnose_blind(folder)
    result = {
        "commit": _commit(),
        "seed": args.seed,
        "per_class": args.per_class,
        "expected": {c: EXPECTED[c] for c in classes},
        "score": score(truths, rows),
        "seconds": round(time.time() - started, 1),
        "tables": {
            n: {
                "truth": truths[n],
                "verdict": rows[n]["verdict"],
                "verdict_without": rows[n]["verdict_without"],
                "discovery": rows[n].get("discovery"),
            }
            for n in truths
        },
    }
    write_json_atomic(args.out / "result.json", result)
    print(json.dumps(result["score"], indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
