"""Blind check of the discovery of a missing term (`accel_jax.diagnose.step.discover`) on
step records the library did not make.

Every record comes from an independent truth simulator written from the loop's physics
without the diagnosis's code: `step_truth.py` (a pickoff nonlinearity, a vibrating stand, a
clean record, and the library's own effects for the leave-one-out cases) and
`discovery_truth.py` (a torquer's scale factor by current direction, Coulomb friction with
sticking, pickoff hysteresis, a second mechanical mode), each on `step_truth`'s randomised
conventions (device, polarities, offsets, ADC, sample rate, start state, off-grid changes).

The denominator is fixed here, before any run (`EXPECTED`): each class's generating term in
the term library, or its stated equivalent; a record is right when the best discovered
subset is exactly that (or the one tie it lists is), and credible-and-right counts toward
the issue's figure. Classes whose cause the term library deliberately lacks
(`pickoff_hysteresis`, `second_mode`) and clean records (`none`, discovered on every record
with `discover="all"`) must give no credible discovery. Leave-one-out classes
(`loo_<effect>`) are diagnosed with that effect removed from the library.

The diagnosis runs in a fresh process per library that sees only the CSV files, against
the reference device with T_dm = T_f = 0 (the truths' lags), as the other blind harnesses
do. Float64.

    python studies/discovery_harness.py --per-class 5 --out out/discovery
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
import discovery_truth  # noqa: E402
import step_truth  # noqa: E402
from measured_input_harness import _commit  # noqa: E402
from shards import run_blind  # noqa: E402

from accel_jax.report import write_json_atomic  # noqa: E402

EXPECTED = {
    "none": None,
    "pickoff_nonlinearity": ("pickoff_cube", "pickoff_square"),
    "periodic_disturbance": ("forcing_sinusoid",),
    "torquer_asymmetry": ("torquer_asymmetry",),
    "coulomb_friction": ("dry_friction",),
    "pickoff_hysteresis": None,
    "second_mode": None,
    "loo_disturbance_drift": ("forcing_ramp",),
    "loo_torquer_lag": ("torquer_pole",),
    "loo_output_filter": ("output_pole",),
}
"""Each class's generating term(s) in the term library, sorted (None: nothing to find —
no credible discovery is the right answer). Not here, with the reason: of the issue's
four leave-one-out effects, `stop_saturation` has no class, because the term library
(`accel_jax.diagnose.step.terms.TERMS`) holds no clip or saturation term (the issue's
"smoothed saturation of θ" is not built), so no term is its equivalent; and the
independent simulator's `bandpass_sensor`, because the library has no output zero (a
high-pass) either. Both are open work on the term library, not classes discovery could
pass."""

CLASSES = tuple(EXPECTED)
LEFT_OUT = {c: c.removeprefix("loo_") for c in CLASSES if c.startswith("loo_")}

_BLIND = """
import json, pathlib, sys
import accel_jax
from accel_jax._placement import apply_device
from accel_jax._cache import enable_compilation_cache
apply_device(latency_bound=True)
enable_compilation_cache()
import jax
jax.config.update("jax_enable_x64", True)
from accel_jax import NominalDevice, read_csv
from accel_jax.diagnose.step import effects as library, entry, fit
left_out = sys.argv[3]
if left_out:
    reduced = [e for e in library.step_effects() if e.name != left_out]
    entry.step_effects = fit.step_effects = lambda: reduced
nominal = NominalDevice.reference(torquer_time_constant=0.0, filter_time_constant=0.0)
files = sorted(pathlib.Path(sys.argv[2]).glob("*.csv"))
out = {}
for f in files:
    result = entry.diagnose_step([read_csv(f)], nominal, recommend=False, discover="all")[0]
    out[f.stem] = {
        "verdict": result.verdict,
        "tied": list(result.tied),
        "discovery": None if result.discovery is None else result.discovery.to_dict(),
    }
pathlib.Path(sys.argv[1]).write_text(json.dumps(out, default=float))
"""


def record_rng(seed: int, effect: str, index: int) -> np.random.Generator:
    return np.random.default_rng([seed, CLASSES.index(effect), index])


def _world(effect: str, rng) -> tuple[dict, tuple]:
    """(truth, (t, u_test, u_out)) of one record of class `effect`."""
    if effect in discovery_truth.CLASSES and effect != "none":
        truth = discovery_truth.draw(rng, effect)
        return truth, discovery_truth.make(truth, rng)
    source = LEFT_OUT.get(effect, effect)
    truth = step_truth.draw_truth(rng, source)
    t, u, y, _ = step_truth.make(truth, rng)
    return truth, (t, u, y)


def write_records(per_class: int, seed: int, folder: Path, classes, first: int = 0) -> dict:
    """Write `per_class` records of each class (indices `first`, `first` + 1, …) under
    folder/<class>/; their truths by name."""
    from accel_jax import StepData, write_csv

    truths = {}
    for effect in classes:
        for i in range(first, first + per_class):
            truth, (t, u, y) = _world(effect, record_rng(seed, effect, i))
            name = f"{effect}_{i:04d}"
            write_csv(folder / effect / f"{name}.csv", StepData(t, u, y))
            truths[name] = {"class": effect, **truth}
    return truths


def diagnose_blind(folder: Path, left_out: str) -> dict:
    """The diagnosis of every CSV in `folder` with `left_out` taken out of the library, in a
    fresh process that sees only the files."""
    return run_blind(_BLIND, str(folder), left_out)


def judge(effect: str, row: dict) -> dict:
    """One record's outcome: the discovery's rating, its best terms, right or not."""
    discovery = row.get("discovery")
    rating = discovery["rating"] if discovery else "not run"
    best = discovery.get("best") if discovery else None
    terms = tuple(sorted(best["terms"])) if best else ()
    tie = discovery.get("tie") if discovery else None
    tie_terms = tuple(sorted(tie["terms"])) if tie else ()
    expected = EXPECTED[effect]
    right = expected is not None and expected in (terms, tie_terms)
    return {
        "rating": rating,
        "best": list(terms),
        "tie": list(tie_terms),
        "right": bool(right),
        "credible_and_right": bool(right and rating == "credible"),
        "credible": rating == "credible",
    }


def score(truths: dict, rows: dict) -> dict:
    by_class = {}
    for name, truth in truths.items():
        outcome = judge(truth["class"], rows[name])
        entry = by_class.setdefault(
            truth["class"],
            {"records": 0, "credible": 0, "right": 0, "credible_and_right": 0, "unexplained": 0},
        )
        entry["records"] += 1
        entry["unexplained"] += rows[name]["verdict"] == "unexplained"
        for key in ("credible", "right", "credible_and_right"):
            entry[key] += outcome[key]
    findable = [c for c in by_class if EXPECTED[c] is not None]
    nothing = [c for c in by_class if EXPECTED[c] is None]
    return {
        "by_class": by_class,
        "findable_credible_and_right": sum(by_class[c]["credible_and_right"] for c in findable),
        "findable_records": sum(by_class[c]["records"] for c in findable),
        "nothing_to_find_credible": sum(by_class[c]["credible"] for c in nothing),
        "nothing_to_find_records": sum(by_class[c]["records"] for c in nothing),
    }


def truth_coefficient(truth: dict, scales: dict) -> float | None:
    """The generating term's coefficient in the term library's units, from the truth's
    physics (None where no single-coefficient mapping is stated):

    - torquer_asymmetry: the torquer's moment is k i (1 + a sgn i) = k i + a k |i|, so
      c = a in the loop's own frame, whose sign the record's output polarity sets;
    - loo_disturbance_drift: the settled output moves by drift_V over the record, and the
      ramp (a moment term: M/k_dm += c·h·t/t_rec) moves it by k_test·c·h, k_test the
      truth device's closed-loop gain from M/k_dm to the output, so c = drift_V /
      (k_test h) (in the output's frame; t_rec, the fitted record's length, is one sample
      short of the truth's, a 1e-4 relative difference left out);
    - loo_torquer_lag, loo_output_filter: a first-order lag of time constant lag_s, the
      pole's c·T, so c = lag_s / T.

    (The periodic disturbance's coefficients are the input-referred moment's, its truth the
    output's amplitude after the loop's response: not compared. The pickoff truth is a
    pair.)"""
    effect = truth["class"]
    sign = float(truth.get("output_sign", 1.0))
    if effect == "torquer_asymmetry":
        return sign * truth["asymmetry"]
    if effect == "loo_disturbance_drift":
        d = truth["device"]
        gain = d["k_dp"] * d["k_y"] * step_truth.Device().l
        k_test = d["k_dm"] * gain / (d["c"] + d["k_dm"] * gain)
        return sign * truth["drift_V"] / (k_test * scales["half_V"])
    if effect in ("loo_torquer_lag", "loo_output_filter"):
        return truth["lag_s"] / scales["period_s"]
    return None


def calibration(records: dict) -> dict:
    """Where the best discovered subset is exactly the generating term and a truth
    coefficient is stated (`truth_coefficient`): (c − c_true)/σ per record, and the
    fraction within 2σ (the issue's target: 85–99 %)."""
    z = {}
    for name, row in records.items():
        truth, discovery = row["truth"], row.get("discovery")
        expected = EXPECTED[truth["class"]]
        best = discovery.get("best") if discovery else None
        if not best or expected is None or tuple(sorted(best["terms"])) != expected:
            continue
        true = truth_coefficient(truth, discovery["scales"])
        if true is None or len(best["columns"]) != 1:
            continue
        column = best["columns"][0]
        z[name] = (column["coefficient"] - true) / column["sigma"]
    within = [abs(v) <= 2 for v in z.values()]
    fraction = float(np.mean(within)) if within else None
    return {
        "records": len(z),
        "within_2_sigma": int(sum(within)),
        "fraction": fraction,
        # The band, both ways: below 85 % the σ are too small (or the coefficient
        # biased), above 99 % too large (inflated).
        "in_band_85_99": None if fraction is None else bool(0.85 <= fraction <= 0.99),
        "z": z,
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--per-class", type=int, default=5)
    parser.add_argument("--seed", type=int, default=4500)
    parser.add_argument("--classes", nargs="+", choices=CLASSES, default=list(CLASSES))
    parser.add_argument(
        "--first", type=int, default=0,
        help="the first record index of each class (a run that extends an earlier one)",
    )
    parser.add_argument("--out", type=Path, default=Path("out/discovery"))
    parser.add_argument(
        "--rescore", type=Path, nargs="+", metavar="RESULT_JSON",
        help="score saved results again, together (and add the calibration figure); no "
        "records run",
    )
    args = parser.parse_args(argv)
    if args.first < 0:
        parser.error("--first must be at least 0")
    if args.per_class < 1:
        parser.error("--per-class must be at least 1")
    if args.rescore is not None:
        records = {}
        for path in args.rescore:
            try:
                saved = json.loads(path.read_text())["records"]
                twice = [n for n in saved if n in records and records[n] != saved[n]]
                if twice:
                    raise ValueError(
                        f"record {twice[0]} is in an earlier file with other results (another "
                        "seed or commit): give each record once"
                    )
                records.update(saved)
            except (OSError, ValueError, KeyError, TypeError, AttributeError) as error:
                parser.error(f"--rescore: cannot read a harness result from {path}: {error}")
        truths = {n: r["truth"] for n, r in records.items()}
        rescored = {"score": score(truths, records), "calibration": calibration(records)}
        print(json.dumps(rescored, indent=1))
        return 0
    start = time.time()
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "records"
        truths = write_records(args.per_class, args.seed, folder, args.classes, args.first)
        libraries: dict[str, list[str]] = {}
        for effect in args.classes:
            libraries.setdefault(LEFT_OUT.get(effect, ""), []).append(effect)
        for left_out, classes in libraries.items():
            group = Path(tmp) / f"group_{left_out or 'full'}"
            group.mkdir()
            for effect in classes:
                for f in (folder / effect).glob("*.csv"):
                    f.rename(group / f.name)
            rows.update(diagnose_blind(group, left_out))
    result = {
        "commit": _commit(),
        "seed": args.seed,
        "per_class": args.per_class,
        "first": args.first,
        "expected": {k: list(v) if v else None for k, v in EXPECTED.items()},
        "nominal": "the reference device with T_dm = T_f = 0",
        "seconds": time.time() - start,
        "score": score(truths, rows),
        "calibration": None,
        "records": {
            n: {"truth": truths[n], **rows[n], "outcome": judge(truths[n]["class"], rows[n])}
            for n in truths
        },
    }
    result["calibration"] = calibration(result["records"])
    write_json_atomic(args.out / "result.json", result)  # whole or not at all
    print(json.dumps({"score": result["score"], "calibration": result["calibration"]}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
