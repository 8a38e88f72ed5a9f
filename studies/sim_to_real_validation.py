"""Study: blind validation of the sim-to-real diagnosis on step records (SPEC.md §5).

A truth simulator makes step records in which one unmodelled effect (or none) is drawn at
random with a random magnitude, on a device whose J, μ, c, k_dm are drawn from their ±5 %
prior and whose constant external moment is random. The records are written as CSV files
(the user's format: t, u_test, u_out); the diagnosis then runs on the files in a separate
process that is given only the folder (never the effects, magnitudes or devices), and
writes its verdicts. Only afterwards does this script compare them with the truth, which it
kept in memory (and writes to truth.json after the diagnosis has finished).

Truth simulators: `simulate_linear` (exact ZOH) for the lags, the drift and the noise;
`simulate_nonlinear` (diffrax, stiff inelastic stop contact) for the stops — a different
model from the diagnosis's own stop surrogate.

Writes OUT/result.json and PNG figures. Run: `python studies/sim_to_real_validation.py
[--out DIR] [--quick]` (float64).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)  # a study script's own choice, see docstring

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import accel_jax as aj  # noqa: E402
from accel_jax import StepData, write_csv  # noqa: E402

STUDY = "sim_to_real_validation"

# --- assumptions (recorded in the output) ------------------------------------------------
SAMPLE_RATE = 100e3  # Hz
SEGMENT = 200  # samples per constant test voltage (2 ms ≈ 7 T: the transient has decayed to ~3 %)
STEP_VOLTAGE = 2.0  # V
PATTERN = (0.0, 1.0, 0.0, -1.0, 1.0, 0.0)  # U_test / STEP_VOLTAGE per segment
NOISE_RANGE = (2e-4, 2e-3)  # V, white output noise σ, log-uniform (SNR 60–80 dB on the step)
PRIOR = 0.05  # relative 1σ of J, μ, c, k_dm (log-normal, truncated at 2σ)
MOMENT_RANGE = (-2e-6, 2e-6)  # N·m, constant external moment M_v, uniform
LAG_RANGE = (5e-6, 5e-5)  # s, T_dm or T_f, log-uniform (the reference device has 1e-5)
STOP_RANGE = (0.85, 1.1)  # stop output k_dp k_y h_max / STEP_VOLTAGE, uniform
DRIFT_RANGE = (2e-3, 2e-2)  # V, settled-output drift over the record, log-uniform, ± sign
GM_TIME_RANGE = (2e-5, 2e-4)  # s, Gauss–Markov correlation time, log-uniform
GM_RATIO_RANGE = (0.5, 2.0)  # GM σ / white σ, uniform
EFFECTS = (
    "none",
    "torquer_lag",
    "output_filter",
    "stop_saturation",
    "disturbance_drift",
    "colored_noise",
)
VERDICTS = EFFECTS[1:] + ("none", "cannot_tell")


def _grid():
    u = np.repeat(np.asarray(PATTERN) * STEP_VOLTAGE, SEGMENT)
    return np.arange(u.size) / SAMPLE_RATE, u


def _log_uniform(rng, bounds, size=None):
    lo, hi = np.log(bounds[0]), np.log(bounds[1])
    return np.exp(rng.uniform(lo, hi, size))


def _draw(rng: np.random.Generator, effect: str) -> dict:
    """One truth: device perturbation, noise, and the effect's magnitude."""
    z = np.clip(rng.normal(size=4), -2, 2)
    ref = aj.REFERENCE_VALUES
    truth = {
        "effect": effect,
        "moment_of_inertia": ref["moment_of_inertia"] * np.exp(PRIOR * z[0]),
        "damping": ref["damping"] * np.exp(PRIOR * z[1]),
        "stiffness": ref["stiffness"] * np.exp(PRIOR * z[2]),
        "torquer_gain": ref["torquer_gain"] * np.exp(PRIOR * z[3]),
        "external_moment": rng.uniform(*MOMENT_RANGE),
        "noise_std": _log_uniform(rng, NOISE_RANGE),
        "torquer_time_constant": 0.0,
        "filter_time_constant": 0.0,
        "stop_output_V": np.inf,
        "drift_V": 0.0,
        "gm_time_s": 0.0,
        "gm_std_V": 0.0,
    }
    if effect == "torquer_lag":
        truth["torquer_time_constant"] = _log_uniform(rng, LAG_RANGE)
    elif effect == "output_filter":
        truth["filter_time_constant"] = _log_uniform(rng, LAG_RANGE)
    elif effect == "stop_saturation":
        truth["stop_output_V"] = rng.uniform(*STOP_RANGE) * STEP_VOLTAGE
    elif effect == "disturbance_drift":
        truth["drift_V"] = _log_uniform(rng, DRIFT_RANGE) * rng.choice([-1.0, 1.0])
    elif effect == "colored_noise":
        truth["gm_time_s"] = _log_uniform(rng, GM_TIME_RANGE)
        truth["gm_std_V"] = rng.uniform(*GM_RATIO_RANGE) * truth["noise_std"]
    return {k: (float(v) if not isinstance(v, str) else v) for k, v in truth.items()}


def _device(truth: dict) -> aj.ServoParams:
    fields = {k: truth[k] for k in aj.REFERENCE_VALUES if k in truth}
    params = aj.ServoParams.reference(**fields)
    if np.isfinite(truth["stop_output_V"]):
        gain = params.pickoff_gain * params.amplifier_gain
        params = eqx.tree_at(lambda p: p.stop_displacement, params, truth["stop_output_V"] / gain)
    return params


def _linear_record(params, moment, key, ts, u):
    return aj.simulate_linear(params, ts, u, external_moment=moment, key=key)


def _stop_record(params, key, ts, u):
    return aj.simulate_nonlinear(params, ts, u, key=key, rtol=1e-8, atol=1e-8, throw=False)


def _gauss_markov(rng, n, dt, tau, std):
    """Sampled first-order Gauss–Markov noise, stationary from the first sample."""
    phi = np.exp(-dt / tau)
    w = rng.normal(size=n) * std * np.sqrt(1 - phi**2)
    out = np.empty(n)
    out[0] = rng.normal() * std
    for i in range(1, n):
        out[i] = phi * out[i - 1] + w[i]
    return out


def generate(truths: list[dict], seed: int) -> list[StepData]:
    """Simulate the records of `truths` (batched by simulator)."""
    ts_np, u_np = _grid()
    ts, u = jnp.asarray(ts_np), jnp.asarray(u_np)
    rng = np.random.default_rng(seed + 1)
    keys = jax.random.split(jax.random.key(seed), len(truths))
    outputs = [None] * len(truths)
    devices = [_device(t) for t in truths]

    def stacked(idx):
        return jax.tree_util.tree_map(lambda *x: jnp.stack(x), *[devices[i] for i in idx])

    linear = [i for i, t in enumerate(truths) if t["effect"] != "stop_saturation"]
    stops = [i for i, t in enumerate(truths) if t["effect"] == "stop_saturation"]
    if linear:
        moments = []
        for i in linear:
            t = truths[i]
            # A drift of the settled output by drift_V over the record: Ṁ = ΔU·K/(k_dp k_y l)/T_rec.
            p = devices[i]
            per_volt = float(
                aj.loop_stiffness(p) / (p.pickoff_gain * p.amplifier_gain * p.pendulum_length)
            )
            moments.append(t["external_moment"] + t["drift_V"] * per_volt * ts_np / ts_np[-1])
        out = aj.sweep(
            _linear_record,
            stacked(linear),
            jnp.asarray(np.stack(moments)),
            keys[np.asarray(linear)],
            ts,
            u,
            in_axes=(0, 0, 0, None, None),
            desc="truth (linear)",
        )
        for j, i in enumerate(linear):
            outputs[i] = np.asarray(out[j])
    if stops:
        out = aj.sweep(
            _stop_record,
            stacked(stops),
            keys[np.asarray(stops)],
            ts,
            u,
            in_axes=(0, 0, None, None),
            desc="truth (stops)",
        )
        for j, i in enumerate(stops):
            outputs[i] = np.asarray(out[j])
    records = []
    dt = 1 / SAMPLE_RATE
    for truth, y in zip(truths, outputs, strict=True):
        if not np.all(np.isfinite(y)):
            raise RuntimeError(f"truth simulation failed for {truth}")
        if truth["effect"] == "colored_noise":
            y = y + _gauss_markov(rng, y.size, dt, truth["gm_time_s"], truth["gm_std_V"])
        records.append(StepData(ts_np, u_np, y))
    return records


_DIAGNOSE_CODE = """
import json, sys, pathlib
import jax
jax.config.update("jax_enable_x64", True)
from accel_jax import read_csv
from accel_jax.diagnose import diagnose_many
folder, out = pathlib.Path(sys.argv[1]), pathlib.Path(sys.argv[2])
files = sorted(folder.glob("*.csv"))
results = diagnose_many([read_csv(f) for f in files])
rows = [{"file": f.name, "verdict": r.verdict, "tied": r.tied, "gap": r.gap,
         "ranking": [{k: e[k] for k in ("effect", "evidence", "significant", "gap_shrink", "params")}
                     for e in r.ranking],
         "refit": r.refit} for f, r in zip(files, results)]
out.write_text(json.dumps(rows, default=float))
"""


def diagnose_blind(folder: Path) -> list[dict]:
    """Run the diagnosis on every CSV of `folder` in a fresh Python process (it sees only
    the files), and return its verdicts."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "verdicts.json"
        subprocess.run(
            [sys.executable, "-c", _DIAGNOSE_CODE, str(folder), str(out)],
            check=True,
            cwd=Path(__file__).resolve().parent.parent,
        )
        return json.loads(out.read_text())


def score(truths: list[dict], verdicts: list[dict]) -> dict:
    confusion = {t: {v: 0 for v in VERDICTS} for t in EFFECTS}
    strict, lenient, shrinks, false_alarms, n_none, n_effect = 0, 0, [], 0, 0, 0
    per_class = {}
    for truth, verdict in zip(truths, verdicts, strict=True):
        t, v = truth["effect"], verdict["verdict"]
        confusion[t][v] += 1
        ok = v == t
        tied_ok = v == "cannot_tell" and t in verdict["tied"]
        c = per_class.setdefault(t, {"n": 0, "correct": 0, "correct_or_tied": 0})
        c["n"] += 1
        c["correct"] += ok
        c["correct_or_tied"] += ok or tied_ok
        if t == "none":
            n_none += 1
            false_alarms += v != "none"
            continue
        n_effect += 1
        strict += ok
        lenient += ok or tied_ok
        if ok:
            shrinks.append(verdict["gap"]["shrink"])
    for c in per_class.values():
        c["accuracy"] = c["correct"] / c["n"]
        c["accuracy_incl_cannot_tell"] = c["correct_or_tied"] / c["n"]
    return {
        "confusion": confusion,
        "accuracy": strict / max(n_effect, 1),
        "accuracy_incl_cannot_tell_naming_truth": lenient / max(n_effect, 1),
        "false_alarm_rate": false_alarms / max(n_none, 1),
        "median_gap_shrink": float(np.median(shrinks)) if shrinks else float("nan"),
        "gap_shrink_p10_p90": [float(np.percentile(shrinks, 10)), float(np.percentile(shrinks, 90))]
        if shrinks
        else None,
        "n_datasets": len(truths),
        "n_per_class": {t: per_class.get(t, {}).get("n", 0) for t in EFFECTS},
        "per_class": per_class,
    }


def _lag_breakdown(truths, verdicts):
    """Verdicts of the lag datasets against the lag: the two lags are exactly degenerate
    on a test-winding step except through the damping prior (see the summary note)."""
    rows = []
    for truth, verdict in zip(truths, verdicts, strict=True):
        if truth["effect"] in ("torquer_lag", "output_filter"):
            lag = truth["torquer_time_constant"] or truth["filter_time_constant"]
            rows.append({"effect": truth["effect"], "lag_s": lag, "verdict": verdict["verdict"]})
    return rows


def _figures(out_dir, result, lag_rows):
    figures = []
    conf = result["step"]["confusion"]
    matrix = np.array([[conf[t][v] for v in VERDICTS] for t in EFFECTS], dtype=float)
    fig, axes = plt.subplots(1, 3, figsize=(17, 5))
    ax = axes[0]
    shown = matrix / np.maximum(matrix.sum(1, keepdims=True), 1)
    im = ax.imshow(shown, cmap="Blues", vmin=0, vmax=1)
    ax.set_xticks(range(len(VERDICTS)), VERDICTS, rotation=40, ha="right", fontsize=8)
    ax.set_yticks(range(len(EFFECTS)), EFFECTS, fontsize=8)
    for i in range(len(EFFECTS)):
        for j in range(len(VERDICTS)):
            if matrix[i, j]:
                ax.text(j, i, int(matrix[i, j]), ha="center", va="center", fontsize=8)
    ax.set_xlabel("verdict (blind)")
    ax.set_ylabel("true effect")
    ax.set_title("confusion matrix (counts; colour = row fraction)")
    fig.colorbar(im, ax=ax, fraction=0.046, label="fraction of the true class")
    ax = axes[1]
    shrinks = result["step"]["_shrinks"]
    ax.hist(shrinks, bins=20, range=(min(0.0, min(shrinks, default=0)), 1.0), color="C2")
    ax.axvline(0.5, color="k", ls=":", label="target median 0.5")
    ax.axvline(result["step"]["median_gap_shrink"], color="C3", label="median")
    ax.set_xlabel("held-out gap shrink 1 − after/before [–]")
    ax.set_ylabel("datasets (effect named correctly)")
    ax.set_title("held-out gap shrink")
    ax.legend(fontsize=8)
    ax = axes[2]
    markers = {"torquer_lag": "o", "output_filter": "s"}
    colours = {"torquer_lag": "C0", "output_filter": "C1", "cannot_tell": "C7", "none": "C3"}
    level = {v: k for k, v in enumerate(("none", "torquer_lag", "output_filter", "cannot_tell"))}
    for row in lag_rows:
        y = level.get(row["verdict"], 4) + (0.1 if row["effect"] == "output_filter" else -0.1)
        ax.semilogx(
            row["lag_s"] * 1e6,
            y,
            markers[row["effect"]],
            color=colours.get(row["verdict"], "k"),
            ms=4,
        )
    ax.set_yticks(range(5), ["none", "torquer_lag", "output_filter", "cannot_tell", "other"])
    ax.set_ylim(-0.5, 4.5)
    ax.plot([], [], "o", color="0.3", label="truth: torquer_lag")
    ax.plot([], [], "s", color="0.3", label="truth: output_filter")
    ax.set_xlabel("true lag T_dm or T_f [µs]")
    ax.set_ylabel("verdict")
    ax.set_title("lag datasets: verdict vs magnitude")
    ax.legend(fontsize=8)
    fig.tight_layout()
    aj.save_figure_atomic(fig, out_dir / "validation.png")
    plt.close(fig)
    figures.append(
        {
            "file": "validation.png",
            "caption": (
                "Blind validation of the step diagnosis. Left: confusion matrix of true effect "
                "vs blind verdict. Middle: held-out gap shrink (RMS prediction error above the "
                "noise floor, on the last third of each record) where the effect was named "
                "correctly. Right: verdicts on the lag datasets against the true lag. "
                f"Assumptions: {SAMPLE_RATE / 1e3:.0f} kHz, {len(PATTERN)} segments of "
                f"{SEGMENT / SAMPLE_RATE * 1e3:.0f} ms at U_test = ±{STEP_VOLTAGE} V, white noise "
                f"{NOISE_RANGE[0]:.0e}–{NOISE_RANGE[1]:.0e} V, J, μ, c, k_dm drawn from their ±5 % "
                "prior; effect magnitudes as in the assumptions block."
            ),
        }
    )
    return figures


def run(out_dir: Path, *, quick: bool = False, seed: int = 20261122) -> dict:
    """Run the study; write OUT/result.json and figures; return the result dict."""
    out_dir = Path(out_dir)
    started = time.perf_counter()
    per_class = 3 if quick else 100
    rng = np.random.default_rng(seed)
    truths = [_draw(rng, effect) for effect in EFFECTS for _ in range(per_class)]
    order = rng.permutation(len(truths))  # file names carry no hint of the class
    truths = [truths[i] for i in order]
    records = generate(truths, seed)
    data_dir = out_dir / "datasets"
    data_dir.mkdir(parents=True, exist_ok=True)
    for old in data_dir.glob("*.csv"):
        old.unlink()
    for i, record in enumerate(records):
        write_csv(data_dir / f"step_{i:04d}.csv", record)
    generated = time.perf_counter()
    verdicts = diagnose_blind(data_dir)
    diagnosed = time.perf_counter()
    names = [f"step_{i:04d}.csv" for i in range(len(records))]
    if [v["file"] for v in verdicts] != names:
        raise RuntimeError("the diagnosis returned verdicts for other files than were written")
    aj.write_json_atomic(
        out_dir / "truth.json", {"datasets": dict(zip(names, truths, strict=True))}
    )

    step = score(truths, verdicts)
    shrinks = [
        v["gap"]["shrink"]
        for t, v in zip(truths, verdicts, strict=True)
        if v["verdict"] == t["effect"] != "none"
    ]
    lag_rows = _lag_breakdown(truths, verdicts)
    result = {
        "title": "Blind validation of the sim-to-real diagnosis — step records (SPEC.md §5)",
        "step": step,
    }
    result["step"]["_shrinks"] = shrinks
    figures = _figures(out_dir, result, lag_rows)
    del result["step"]["_shrinks"]
    target_note = "SPEC.md §5 / issue 6 target"
    result.update(
        {
            "summary": [
                {
                    "quantity": "effects named correctly (strict: verdict = true effect)",
                    "ours": step["accuracy"],
                    "paper": 0.90,
                    "note": f"{target_note} ≥ 0.90. cannot_tell counts as wrong here.",
                },
                {
                    "quantity": "effects named correctly or cannot_tell naming the true effect",
                    "ours": step["accuracy_incl_cannot_tell_naming_truth"],
                    "paper": 0.90,
                    "note": "torquer_lag and output_filter are exactly degenerate on a "
                    "test-winding step up to a damping shift Δμ = k_dm k_dp k_y l·T (the loop "
                    "polynomials coincide to O(T²)); only the ±5 % prior on μ separates them, "
                    "so small lags are honestly cannot_tell.",
                },
                {
                    "quantity": "false-alarm rate on no-effect records",
                    "ours": step["false_alarm_rate"],
                    "paper": 0.05,
                    "note": f"{target_note} ≤ 0.05.",
                },
                {
                    "quantity": "median held-out gap shrink (effect named)",
                    "ours": step["median_gap_shrink"],
                    "paper": 0.5,
                    "note": f"{target_note} ≥ 0.5; gap = held-out RMS error above the noise floor.",
                },
            ],
            "lag_breakdown": lag_rows,
            "datasets": [
                {
                    "file": name,
                    "truth": truth["effect"],
                    "verdict": verdict["verdict"],
                    "tied": verdict["tied"],
                    "gap_shrink": verdict["gap"]["shrink"],
                    "gap_shrink_std": verdict["gap"]["shrink_std"],
                }
                for name, truth, verdict in zip(names, truths, verdicts, strict=True)
            ],
            "figures": figures,
            "assumptions": {
                "sample_rate_Hz": SAMPLE_RATE,
                "segments_V": [p * STEP_VOLTAGE for p in PATTERN],
                "segment_s": SEGMENT / SAMPLE_RATE,
                "held_out": "the last ~1/3 of each record (from the input change nearest 2/3)",
                "noise_std_V_log_uniform": list(NOISE_RANGE),
                "device_prior": "J, μ, c, k_dm log-normal 5 % (truncated at 2σ) about the reference",
                "external_moment_Nm_uniform": list(MOMENT_RANGE),
                "lag_s_log_uniform": list(LAG_RANGE),
                "stop_output_over_U_uniform": list(STOP_RANGE),
                "drift_V_over_record_log_uniform": list(DRIFT_RANGE),
                "gauss_markov_time_s_log_uniform": list(GM_TIME_RANGE),
                "gauss_markov_std_over_white_uniform": list(GM_RATIO_RANGE),
                "per_class": per_class,
                "truth_simulators": "simulate_linear (lags, drift, noise); simulate_nonlinear with stops",
                "blindness": "diagnosis in a separate process given only the CSV folder",
                "precision": "float64",
            },
            "timing_s": {
                "generate": generated - started,
                "diagnose": diagnosed - generated,
                "total": time.perf_counter() - started,
            },
            "provenance": aj.provenance(seeds={"study": seed}, precision="float64"),
        }
    )
    aj.write_json_atomic(out_dir / "result.json", result)
    return result


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("out") / STUDY)
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args()
    res = run(args.out, quick=args.quick)
    print(json.dumps({k: res[k] for k in ("summary", "timing_s")}, indent=1, default=float))
    print(json.dumps(res["step"]["confusion"], indent=1))
