"""Blind check of the step diagnosis on records whose mechanical stops are compliant
spring-damper contacts: symmetric, on one side only, or at different clearances.

Every record comes from the independent truth simulator `contact_truth.py` (SciPy, written
from the loop equations without the library's effect code; it reuses `step_truth.py`'s
world: device, small-step sequence, recorder conventions). Classes:

- `stop_compliant`, `stop_one_sided`, `stop_uneven` (`contact_truth.CONTACT_CLASSES`):
  a contact of stiffness κ = K_c/k_loop log-uniform in 10–3000 and damping ratio ζ_c
  log-uniform in 0.05–2, its clearance set from the record's own free response so that
  the record reaches it, and a quarter of the records starting pressed against a stop;
- `none`: `step_truth`'s clean worlds (no stop), for the false alarms.

The diagnosis runs in a fresh process that sees only the CSV files, against the reference
device with T_dm = T_f = 0 (the truths' lags), as the other harnesses do. Scored per
class, over every record (a record the diagnosis refused or failed on counts as a miss):

- **named**, strictly: `stop_contact`, or `cannot_tell` with it among the tied; and as
  the stop family (`stop_contact` or the inelastic clamp `stop_saturation`, the limit of
  a stiff, well-damped contact), reported beside it, never instead of it;
- by κ and ζ_c band, and for the records that start against a stop;
- **false assurance**: `none` on a record whose contact pushed at some time
  (`sides_reached`, from the truth simulator's own contact events); a record whose
  contact never pushed is counted apart (`stop_absent`), outside the shares;
- the fitted contact against the truth where `stop_contact` is named: κ and ζ_c ratios;
- **false alarms** on the `none` class: any other verdict.

    python studies/contact_harness.py --per-class 100 --shard 0/10 --out out/contact/s0
    python studies/contact_harness.py --merge out/contact/s*/result.json --out out/contact

Each record's world and noise come from its own generator, seeded by (seed, class, index,
attempt): a draw the truth simulator refuses ("drives the pendulum towards neither side")
is drawn again with the next attempt, so a record is the same in every shard. `--shard
k/n` writes and diagnoses records k, k+n, … of the draw's list (class by class); `--merge`
joins the shards' results and scores them together. Results are written whole. Float64.
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
import contact_truth  # noqa: E402
import step_truth  # noqa: E402
from measured_input_harness import _commit  # noqa: E402
from shards import blind_prelude, parse_shard, run_blind, shard_indices  # noqa: E402
from verdict_family import family  # noqa: E402

from accel_jax.report import write_json_atomic  # noqa: E402

CLASSES = ("none",) + contact_truth.CONTACT_CLASSES
NOMINAL_LAGS = {"torquer_time_constant": 0.0, "filter_time_constant": 0.0}
KAPPA_BANDS = ((10.0, 100.0), (100.0, 1000.0), (1000.0, 3000.0))
ZETA_BANDS = ((0.05, 0.3), (0.3, 1.0), (1.0, 2.0))
DRAW_ATTEMPTS = 8
"""Draws of one record before the harness gives up (`contact_truth.draw_truth` refuses a
sequence that drives the pendulum towards neither side)."""

_BLIND = blind_prelude(NOMINAL_LAGS) + (
    """for f in sorted(pathlib.Path(sys.argv[2]).glob("*.csv")):
    try:
        result = diagnose_many([read_csv(f)], nominal, recommend=False)[0]
    except DataError as error:
        out[f.stem] = {"refused": str(error)}
        continue
    except Exception as error:  # a failure is a miss, never a dropped record
        out[f.stem] = {"error": f"{type(error).__name__}: {error}"}
        continue
    row = {"verdict": result.verdict, "tied": list(result.tied), "reason": result.reason}
    for e in result.ranking:
        if e["effect"] in ("stop_contact", "stop_saturation"):
            row[e["effect"]] = {k: e.get(k) for k in ("evidence", "params", "fit_failed")}
    out[f.stem] = row
pathlib.Path(sys.argv[1]).write_text(json.dumps(out, default=float))
"""
)


def record_rng(seed: int, effect: str, index: int, attempt: int) -> np.random.Generator:
    """One record's generator: its world, then its noise."""
    return np.random.default_rng([seed, CLASSES.index(effect), index, attempt])


def draw(effect: str, seed: int, index: int):
    """(truth, its generator after the draw, attempt) of one record (module docstring)."""
    for attempt in range(DRAW_ATTEMPTS):
        rng = record_rng(seed, effect, index, attempt)
        try:
            if effect == "none":
                return step_truth.draw_truth(rng, "none"), rng, attempt
            return contact_truth.draw_truth(rng, effect), rng, attempt
        except RuntimeError:
            continue
    raise RuntimeError(f"{effect} record {index}: no drawable world in {DRAW_ATTEMPTS} tries")


def record_names(per_class: int, classes=CLASSES) -> list[str]:
    """The draw's records, class by class: `<class>_<index>`."""
    return [f"{effect}_{i:04d}" for effect in classes for i in range(per_class)]


def write_records(names: list[str], seed: int, folder: Path) -> dict:
    """Draw and simulate the named records, write them as CSV files; their truths by name."""
    from accel_jax import StepData, write_csv

    folder.mkdir(parents=True, exist_ok=True)
    truths = {}
    for name in names:
        effect, index = name.rsplit("_", 1)
        truth, rng, attempt = draw(effect, seed, int(index))
        simulator = step_truth if effect == "none" else contact_truth
        t, u, y, _ = simulator.make(truth, rng)
        write_csv(folder / f"{name}.csv", StepData(t, u, y))
        truths[name] = {**truth, "draw_attempt": attempt}
    return truths


def judge(truth: dict, row: dict) -> dict:
    """One record's facts for the score (a refused or failed record: named by nothing)."""
    effect = truth["effect"]
    verdict = row.get("verdict", "refused" if "refused" in row else "error")
    tied = row.get("tied", [])
    facts = {"class": effect, "verdict": verdict}
    if effect == "none":
        facts["false_alarm"] = verdict != "none"
        return facts
    facts.update(
        stop_acts=bool(truth.get("sides_reached")),
        named=verdict == "stop_contact" or (verdict == "cannot_tell" and "stop_contact" in tied),
        family=family(verdict) == family("stop_contact")
        or (verdict == "cannot_tell" and family("stop_contact") in map(family, tied)),
        none=verdict == "none",
        kappa=truth["kappa"],
        zeta_c=truth["zeta_c"],
        against=bool(truth.get("start_against_stop")),
    )
    fitted = (row.get("stop_contact") or {}).get("params") or {}
    if verdict == "stop_contact" and fitted.get("contact_stiffness_over_loop"):
        facts["kappa_ratio"] = fitted["contact_stiffness_over_loop"] / truth["kappa"]
        facts["zeta_ratio"] = (fitted.get("contact_damping_ratio") or np.nan) / truth["zeta_c"]
    return facts


def _share(facts: list[dict], key: str) -> dict:
    count = sum(bool(f[key]) for f in facts)
    return {"n": len(facts), "count": count, "share": count / len(facts) if facts else None}


def _bands(facts: list[dict], key: str, bands) -> dict:
    out = {}
    for low, high in bands:
        mine = [f for f in facts if low <= f[key] <= high]
        out[f"{low:g}-{high:g}"] = {
            "named": _share(mine, "named"), "family": _share(mine, "family")
        }
    return out


def score(truths: dict, rows: dict) -> dict:
    """The per-class figures (module docstring); a record with no row counts as a miss."""
    judged = [judge(truths[n], rows.get(n, {"error": "no verdict returned"})) for n in truths]
    out = {}
    for effect in CLASSES:
        mine = [f for f in judged if f["class"] == effect]
        if not mine:
            continue
        verdicts = [f["verdict"] for f in mine]
        section = {"records": len(mine), "verdicts": {v: verdicts.count(v) for v in set(verdicts)}}
        if effect == "none":
            section["false_alarms"] = _share(mine, "false_alarm")
        else:
            acting = [f for f in mine if f["stop_acts"]]
            ratios = [f for f in acting if "kappa_ratio" in f]
            section.update(
                stop_absent=len(mine) - len(acting),
                named=_share(acting, "named"),
                family=_share(acting, "family"),
                false_assurance=sum(f["none"] for f in acting),
                by_kappa=_bands(acting, "kappa", KAPPA_BANDS),
                by_zeta_c=_bands(acting, "zeta_c", ZETA_BANDS),
                starting_against_stop={
                    "named": _share([f for f in acting if f["against"]], "named"),
                    "family": _share([f for f in acting if f["against"]], "family"),
                },
                fitted_over_true=None if not ratios else {
                    "records": len(ratios),
                    "kappa_median": float(np.median([f["kappa_ratio"] for f in ratios])),
                    "zeta_c_median": float(np.nanmedian([f["zeta_ratio"] for f in ratios])),
                },
            )
        out[effect] = section
    contact = [s for c, s in out.items() if c != "none"]
    out["false_assurance"] = sum(s["false_assurance"] for s in contact)
    named = {c: s["named"]["share"] for c, s in out.items() if isinstance(s, dict) and "named" in s}
    out["lowest_named"] = min(named.items(), key=lambda kv: kv[1] if kv[1] is not None else 2.0,
                              default=None)
    return out


def merge(results: list[dict]) -> dict:
    """Shards' results of one draw as one: rows and truths joined, scored together; refused
    (ValueError) when they drew differently or overlap. `complete`: every shard is in."""
    if not results:
        raise ValueError("nothing to merge")
    keys = ("per_class", "classes", "seed", "shard_count", "commit")
    first = results[0]["assumptions"]
    rows, truths, shards, seconds = {}, {}, [], 0.0
    for r in results:
        differ = [k for k in keys if r["assumptions"].get(k) != first.get(k)]
        if differ:
            raise ValueError(f"the shards differ in {', '.join(differ)}: not one draw")
        overlap = set(truths) & set(r["truths"])
        if overlap:
            raise ValueError(f"the shards overlap in {len(overlap)} records (e.g. {min(overlap)})")
        rows.update(r["rows"])
        truths.update(r["truths"])
        shards += r["assumptions"].get("merged_shards") or [r["assumptions"]["shard"]]
        seconds += r["seconds"]
    missing = sorted(set(range(first["shard_count"])) - {k for k, _ in shards})
    assumptions = {**first, "shard": None, "merged_shards": sorted(map(list, shards)),
                   "complete": not missing, "missing_shards": missing, "merged_at": _commit()}
    return {"assumptions": assumptions, "score": score(truths, rows), "truths": truths,
            "rows": rows, "seconds": seconds}


def run(per_class: int, seed: int, classes, shard) -> dict:
    """One run (or shard): draw, simulate, diagnose blind, score."""
    start = time.time()
    names = record_names(per_class, classes)
    names = [names[i] for i in shard_indices(len(names), shard)]
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "records"
        truths = write_records(names, seed, folder)
        rows = run_blind(_BLIND, str(folder)) if names else {}
    return {
        "assumptions": {
            "truth": "studies/contact_truth.py (SciPy); none: studies/step_truth.py",
            "nominal": "reference device, T_dm = T_f = 0",
            "per_class": per_class,
            "classes": list(classes),
            "seed": seed,
            "shard": list(shard),
            "shard_count": shard[1],
            "commit": _commit(),
            "precision": "float64",
        },
        "score": score(truths, rows),
        "truths": truths,
        "rows": rows,
        "seconds": time.time() - start,
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--per-class", type=int, default=10)
    parser.add_argument("--seed", type=int, default=2029)
    parser.add_argument("--classes", nargs="+", choices=CLASSES, default=list(CLASSES))
    parser.add_argument("--shard", type=parse_shard, default=(0, 1), metavar="k/n")
    parser.add_argument("--merge", nargs="+", type=Path, metavar="RESULT_JSON")
    parser.add_argument("--out", type=Path, default=Path("out/contact"))
    args = parser.parse_args(argv)
    if args.per_class < 1:
        parser.error("--per-class must be at least 1")
    if args.merge:
        try:
            result = merge([json.loads(p.read_text()) for p in args.merge])
        except (OSError, ValueError, KeyError, TypeError) as error:
            print(f"contact_harness: cannot merge: {error}", file=sys.stderr)
            return 1
    else:
        result = run(args.per_class, args.seed, tuple(args.classes), args.shard)
    args.out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(args.out / "result.json", result)
    print(json.dumps(result["score"], indent=1, default=float))
    print(f"written: {args.out / 'result.json'} ({result['seconds']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
