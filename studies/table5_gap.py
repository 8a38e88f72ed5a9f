"""Study: the sim-to-real gap of the measured Table 5 (docs/models.md §3 and §5).

Table 5 of the navigation-accelerometer paper is a real shaker measurement of two units
(AKS-05, AL-1M): 1 g along the input axis, a 2 g sinusoid at 30 Hz. With the passport
coefficients of Table 4 known (nothing is fitted), this study applies the diagnosis's
where / which / how-far reasoning to it:

- where: the measured error splits into the basic (static) error of the passport model and
  a vibration error; the nominal model of the vibration kind (bias + scale factor only)
  predicts no vibration error at all, so the whole vibration error is the gap;
- which: how much of that gap each effect of the library explains with its passport value
  (A1, k2, k3, k4, k5; the unit has no cross-axis vibration, so m31, m32 cannot act), by
  the exact expectation and by the paper's closed form (19);
- how far: the gap before and after adding the effects, and what single coefficient change
  would close what remains — with the honest conclusion that one reading per unit cannot
  tell those explanations apart, and which further shaker rows would.

Writes OUT/result.json and PNG figures. Run: `python studies/table5_gap.py [--out DIR]
[--quick]` (float64; the study is closed-form and takes seconds either way).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import jax

# Run as a script: float64 before the module's constants are built, as in the report's
# workers (imported by the report, this changes nothing: the report chose already).
if __name__ == "__main__":
    jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import matplotlib  # noqa: E402
import numpy as np  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

import accel_jax as aj  # noqa: E402
from accel_jax import PPM, StaticTransferFunction  # noqa: E402
from accel_jax.report import (  # noqa: E402
    Figures,
    provenance,
    study_main,
    study_run,
    write_json_atomic,
)
from accel_jax.vibration import AKS05_RANGES_PPM, VibrationEnvironment  # noqa: E402

STUDY = "table5_gap"

# --- the measurement (docs/models.md §3, Table 5) ---------------------------------------------
INPUT_G = 1.0  # along the input axis
SINE_G = 2.0  # sinusoidal vibration amplitude along the input axis
SINE_HZ = 30.0
READING_RESOLUTION_G = 1e-6  # Table 5 prints â to 1e-6 g: ±0.5 ppm of rounding
TABLE5 = {
    # â [g]: no compensation (a0 removed), after basic-error compensation, after vibration
    # compensation by the paper's algorithm (19).
    "AKS-05": (1.000100, 1.000083, 1.000006),
    "AL-1M": (1.001303, 1.001088, 1.000110),
}
UNITS = aj.PASSPORTS  # the paper's two accelerometers, Table 4
EFFECTS = ("asymmetry", "k2", "k3", "k4", "k5")
LABELS = {"asymmetry": "A1", "k2": "k2", "k3": "k3", "k4": "k4", "k5": "k5"}
UNIT_NAMES = {effect: aj.PPM_UNITS[effect] for effect in EFFECTS}

# Further shaker rows at which the candidate explanations are compared (a [g], b [g]).
PROBES = ((1.0, 2.0), (-1.0, 2.0), (0.0, 2.0), (1.0, 4.0), (1.0, 1.0), (0.0, 6.0))


def _single(name: str, value_ppm: float) -> StaticTransferFunction:
    return StaticTransferFunction(**{name: value_ppm * PPM})


@eqx.filter_jit
@eqx.filter_vmap(in_axes=(None, 0, 0))
def _errors(tf, a, b):
    """Vibration error of `tf` at input a [g] under a sinusoid of amplitude b [g] along the
    input axis: (exact expectation, closed form (19), (19) with the printed k5 factor 1.185)
    [g]; vmapped over (a, b), compiled once."""
    env = VibrationEnvironment(sine_amplitude=jnp.stack([0 * b, 0 * b, b]), sine_frequency=SINE_HZ)
    return (
        aj.vibration.vibration_error(tf, env, a),
        aj.vibration.paper_deterministic_error(tf, env, a),
        aj.vibration.paper_deterministic_error(tf, env, a, k5_quartic=1.185),
    )


def _exact(tf, a, b) -> np.ndarray:
    """Exact vibration error [ppm] at the (broadcast) points a, b [g]."""
    a, b = np.broadcast_arrays(
        np.atleast_1d(np.asarray(a, float)), np.atleast_1d(np.asarray(b, float))
    )
    return np.asarray(_errors(tf, jnp.asarray(a), jnp.asarray(b))[0]) / PPM


def _ppm(x) -> float:
    return float(x) / PPM


def _contributions(passport: StaticTransferFunction, a: float, b: float) -> dict:
    """Each effect's vibration error at (a, b) with its passport value [ppm]: the exact
    expectation and the paper's closed form (19) (k5 quartic factor 1.875 and the printed
    1.185)."""
    out = {}
    for name in EFFECTS:
        tf = _single(name, float(getattr(passport, name)) / PPM)
        exact, paper, printed = (_ppm(x[0]) for x in _errors(tf, jnp.array([a]), jnp.array([b])))
        out[name] = {"exact_ppm": exact, "paper_ppm": paper, "paper_printed_k5_ppm": printed}
    return out


def _sensitivity(name: str, a, b) -> np.ndarray:
    """∂δ_V/∂coefficient at (a, b) [ppm of g per ppm unit] (exact: δ_V is linear in it)."""
    return _exact(_single(name, 1.0), a, b)


def _passport_exact(passport: StaticTransferFunction, a, b) -> np.ndarray:
    """The exact vibration error of the passport's A1, k2..k5 (no a0, δ) [ppm]."""
    tf = StaticTransferFunction(**{e: getattr(passport, e) for e in EFFECTS})
    return _exact(tf, a, b)


def analyse_unit(name: str) -> dict:
    passport = UNITS[name]()
    readings = TABLE5[name]
    residual_ppm = [(r - INPUT_G) / PPM for r in readings]
    basic = _ppm(aj.basic_error(passport, INPUT_G, include_bias=False))
    # The measured vibration error: the reading after basic-error compensation (the paper's
    # second column); the same to rounding as the first reading minus our basic error.
    measured = residual_ppm[1]
    contributions = _contributions(passport, INPUT_G, SINE_G)
    explained_exact = sum(c["exact_ppm"] for c in contributions.values())
    explained_paper = sum(c["paper_ppm"] for c in contributions.values())
    for c in contributions.values():
        c["share_of_measured_exact"] = c["exact_ppm"] / measured
        c["share_of_measured_paper"] = c["paper_ppm"] / measured
    gap_exact = measured - explained_exact
    gap_paper = measured - explained_paper
    # Which: the change of one coefficient that alone would close what the exact
    # expectation leaves. Every candidate closes it exactly: one reading, one unknown each.
    closing = {}
    probe_a = np.array([p[0] for p in PROBES])
    probe_b = np.array([p[1] for p in PROBES])
    at_probes = _passport_exact(passport, probe_a, probe_b)
    for effect in EFFECTS:
        sensitivity = float(_sensitivity(effect, INPUT_G, SINE_G)[0])
        delta = gap_exact / sensitivity
        value = float(getattr(passport, effect)) / PPM
        entry = {
            "sensitivity_ppm_per_unit": sensitivity,
            "change": delta,
            "passport": value,
            "closing_value": value + delta,
            "unit": UNIT_NAMES[effect],
        }
        if name == "AKS-05":
            low, high = AKS05_RANGES_PPM[effect]
            entry["table2_range_of_modulus"] = [low, high]
            entry["within_table2_range"] = bool(low <= abs(value + delta) <= high)
        # What each explanation predicts at further shaker rows [ppm of vibration error].
        entry["predicted_at_probes_ppm"] = (
            at_probes + delta * _sensitivity(effect, probe_a, probe_b)
        ).tolist()
        closing[effect] = entry
    # The largest vibration error the batch's coefficient ranges (Table 2) allow, for
    # AKS-05: every |coefficient| at the end of its range, signs chosen to add up.
    batch_max = None
    if name == "AKS-05":
        batch_max = sum(
            max(abs(float(_sensitivity(e, INPUT_G, SINE_G)[0]) * v) for v in AKS05_RANGES_PPM[e])
            for e in EFFECTS
        )
    # Spread of the explanations' predictions at each probe row: the data that would
    # discriminate them.
    spread = []
    for j, (a, b) in enumerate(PROBES):
        values = [closing[e]["predicted_at_probes_ppm"][j] for e in EFFECTS]
        spread.append(
            {
                "a_g": a,
                "b_g": b,
                "min_ppm": min(values),
                "max_ppm": max(values),
                "spread_ppm": max(values) - min(values),
            }
        )
    return {
        "passport": passport.as_ppm(),
        "readings_g": list(readings),
        "readings_residual_ppm": residual_ppm,
        "basic_error_ppm": basic,
        "basic_from_readings_ppm": residual_ppm[0] - residual_ppm[1],
        "measured_vibration_error_ppm": measured,
        "contributions": contributions,
        "explained_exact_ppm": explained_exact,
        "explained_paper_ppm": explained_paper,
        "gap": {
            "metric": "measured vibration error minus the model's, at the one Table 5 condition",
            "before_ppm": measured,  # nominal vibration model (bias + scale factor): δ_V = 0
            "after_exact_ppm": gap_exact,
            "after_paper_ppm": gap_paper,
            "shrink_exact": 1 - abs(gap_exact) / abs(measured),
            "shrink_paper": 1 - abs(gap_paper) / abs(measured),
            "paper_published_after_ppm": residual_ppm[2],
            "reading_rounding_ppm": 0.5 * READING_RESOLUTION_G / PPM,
        },
        "one_effect_closing_the_gap": closing,
        "verdict": "cannot_tell",
        "verdict_reason": (
            "one reading (one test condition) per unit: each of the five effects closes the "
            "remaining gap exactly with one coefficient change, leaving no residual degree of "
            "freedom to rank them; nor can a static (basic-error) mismatch be told from a "
            "vibration effect, since the unit's reading without vibration is not reported."
        ),
        "batch_max_vibration_error_ppm": batch_max,
        "discriminating_rows": spread,
    }


def _figures(out_dir: Path, result: dict) -> list[dict]:
    figures = Figures(out_dir)
    save = figures.save

    units = list(TABLE5)
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.8))
    for ax, unit in zip(axes, units, strict=True):
        r = result["units"][unit]
        x = np.arange(len(EFFECTS) + 2)
        exact = [r["contributions"][e]["exact_ppm"] for e in EFFECTS]
        paper = [r["contributions"][e]["paper_ppm"] for e in EFFECTS]
        exact_stack = np.concatenate([[0], np.cumsum(exact)])
        paper_stack = np.concatenate([[0], np.cumsum(paper)])
        for i in range(len(EFFECTS)):
            ax.bar(i - 0.2, exact[i], 0.4, bottom=exact_stack[i], color=f"C{i}")
            ax.bar(
                i + 0.2, paper[i], 0.4, bottom=paper_stack[i], color=f"C{i}", alpha=0.45, hatch="//"
            )
        ax.bar(len(EFFECTS) - 0.2, exact_stack[-1], 0.4, color="0.3", label="exact expectation")
        ax.bar(
            len(EFFECTS) + 0.2,
            paper_stack[-1],
            0.4,
            color="0.7",
            hatch="//",
            label="paper's closed form (19)",
        )
        ax.bar(
            len(EFFECTS) + 1,
            r["measured_vibration_error_ppm"],
            0.5,
            color="k",
            label="measured (after basic compensation)",
        )
        ax.set_xticks(x, [LABELS[e] for e in EFFECTS] + ["sum", "measured"])
        ax.set_ylabel("vibration error at 1 g, 2 g sine [ppm]")
        gap = r["gap"]
        ax.set_title(
            f"{unit}: gap {gap['before_ppm']:.0f} → {gap['after_exact_ppm']:.1f} ppm (exact), "
            f"{gap['after_paper_ppm']:.1f} ppm (closed form)"
        )
        ax.legend(fontsize=8)
    save(
        fig,
        "table5_contributions.png",
        (
            "Table 5 (1 g, 2 g sinusoid at 30 Hz): the vibration error each effect explains "
            "with its Table 4 passport value, cumulated (solid: exact expectation; hatched: the "
            "paper's closed form (19), which differs only in the A1 term), against the measured "
            "vibration error (the reading after basic-error compensation). Nothing is fitted."
        ),
    )

    fig, axes = plt.subplots(2, 2, figsize=(13, 8.5))
    amplitudes = np.linspace(0.0, 4.0, 81)
    for row, unit in zip(axes, units, strict=True):
        r = result["units"][unit]
        for ax, a in zip(row, (INPUT_G, -INPUT_G), strict=True):
            for i, e in enumerate(EFFECTS):
                delta = r["one_effect_closing_the_gap"][e]["change"]
                extra = _sensitivity(e, a, amplitudes) * delta
                ax.plot(
                    amplitudes,
                    extra,
                    color=f"C{i}",
                    label=f"Δ{LABELS[e]} = {delta:+.3g} {UNIT_NAMES[e]}",
                )
            if a == INPUT_G:
                ax.plot(
                    [SINE_G],
                    [r["gap"]["after_exact_ppm"]],
                    "ko",
                    ms=7,
                    label="Table 5 gap (exact model)",
                )
            ax.axhline(0, color="k", lw=0.5)
            ax.set_xlabel(f"sine amplitude b along the input axis [g] (a = {a:+g} g)")
            ax.set_ylabel("vibration error beyond the passport model [ppm]")
            ax.set_title(f"{unit}, a = {a:+g} g: the single-effect explanations")
            ax.legend(fontsize=7)
    save(
        fig,
        "table5_explanations.png",
        (
            "The gap the passport model leaves (exact expectation), closed by changing one "
            "coefficient at a time: the extra vibration error each explanation predicts. At "
            "a = +1 g every curve passes through the one Table 5 reading (b = 2 g) and they "
            "part at other amplitudes; at a = −1 g the odd terms (k3, k5) change sign. Shaker "
            "rows at other amplitudes and input levels would discriminate the explanations; "
            "the one reading cannot."
        ),
    )
    return figures.entries


@study_run(compile_bound_when_quick=False)
def run(out_dir: Path, *, quick: bool = False) -> dict:
    """Run the study; write OUT/result.json and figures; return the result dict. `quick`
    changes nothing (the study is closed-form); it is accepted for the report runner."""
    del quick
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    units = {name: analyse_unit(name) for name in TABLE5}
    aks, al = units["AKS-05"], units["AL-1M"]
    result = {
        "title": "The sim-to-real gap of the measured Table 5 (the vibration-error paper)",
        "condition": {"a_in_g": INPUT_G, "sine_amplitude_g": SINE_G, "sine_frequency_Hz": SINE_HZ},
        "units": units,
        "probes_a_b_g": [list(p) for p in PROBES],
    }
    summary = []
    for name, r in units.items():
        gap = r["gap"]
        summary += [
            {
                "quantity": f"{name}: measured vibration error (after basic compensation) [ppm]",
                "ours": r["measured_vibration_error_ppm"],
                "paper": r["measured_vibration_error_ppm"],
                "note": "Table 5 reading; the basic error from Table 4 at 1 g is "
                f"{r['basic_error_ppm']:.1f} ppm (the readings differ by "
                f"{r['basic_from_readings_ppm']:.0f}).",
            },
            {
                "quantity": f"{name}: explained by A1, k2..k5 with passport values, exact [ppm]",
                "ours": r["explained_exact_ppm"],
                "paper": None,
                "note": "largest share: "
                + max(EFFECTS, key=lambda e: r["contributions"][e]["exact_ppm"])
                + ".",
            },
            {
                "quantity": f"{name}: explained, paper's closed form (19) [ppm]",
                "ours": r["explained_paper_ppm"],
                "paper": r["readings_residual_ppm"][1] - r["readings_residual_ppm"][2],
                "note": "paper column: what its compensation removed (Table 5).",
            },
            {
                "quantity": f"{name}: gap left, exact expectation [ppm]",
                "ours": gap["after_exact_ppm"],
                "paper": gap["paper_published_after_ppm"],
                "note": f"shrink {gap['shrink_exact']:.2f}; paper column: its residual after "
                f"compensation; readings rounded to ±{gap['reading_rounding_ppm']} ppm.",
            },
        ]
    closing_aks = aks["one_effect_closing_the_gap"]
    within = [LABELS[e] for e in EFFECTS if closing_aks[e]["within_table2_range"]]
    conclusions = [
        f"AKS-05: the passport model explains {aks['explained_exact_ppm']:.1f} of the "
        f"{aks['measured_vibration_error_ppm']:.0f} ppm measured vibration error (exact "
        f"expectation; {aks['explained_paper_ppm']:.1f} by the closed form), leaving "
        f"{aks['gap']['after_exact_ppm']:.1f} ppm; AL-1M: {al['explained_exact_ppm']:.1f} of "
        f"{al['measured_vibration_error_ppm']:.0f} ppm, leaving {al['gap']['after_exact_ppm']:.1f} "
        "ppm. Both gaps are far above the ±0.5 ppm rounding of the readings.",
        "The paper's closed form leaves less (its A1 term, A1 (0.673 b − 0.5 a), is "
        f"{aks['contributions']['asymmetry']['paper_ppm']:.1f} / "
        f"{al['contributions']['asymmetry']['paper_ppm']:.1f} ppm against the exact "
        f"{aks['contributions']['asymmetry']['exact_ppm']:.1f} / "
        f"{al['contributions']['asymmetry']['exact_ppm']:.1f}): it absorbs part of the gap "
        "by being wrong about A1, not by explaining it.",
        "Which effect: cannot tell. Each unit gives one reading under vibration; each of A1, "
        "k2, k3, k4, k5 closes the remaining gap exactly with one coefficient change (the "
        "'one_effect_closing_the_gap' table), so no evidence can rank them, and a static "
        "mismatch (a0, δ, passport drift) cannot be told from a vibration effect either. For "
        "AKS-05 the single changes that stay within the batch ranges of Table 2: "
        f"{within or 'none'}; with every coefficient at the end of its Table 2 range the exact "
        f"vibration error reaches only {aks['batch_max_vibration_error_ppm']:.1f} ppm.",
        "What would discriminate: the explanations agree at b = 2 g, a = 1 g by construction "
        "and part at other shaker rows, e.g. at a = −1 g, b = 2 g they spread over "
        f"{aks['discriminating_rows'][1]['spread_ppm']:.0f} ppm (AKS-05) / "
        f"{al['discriminating_rows'][1]['spread_ppm']:.0f} ppm (AL-1M); a table of such rows is "
        "what the vibration diagnosis (accel-jax diagnose on a vibration CSV) needs.",
    ]
    result["summary"] = summary
    result["conclusions"] = conclusions
    result["figures"] = _figures(out_dir, result)
    result["timing_s"] = {"total": time.perf_counter() - started}
    result["provenance"] = provenance(precision="float64")
    write_json_atomic(out_dir / "result.json", result)
    return result


def main(argv=None) -> int:
    def summary(result):
        for row in result["summary"]:
            print(f"{row['quantity']}: {row['ours']:.4g} (paper {row['paper']})")
        for line in result["conclusions"]:
            print("-", line)

    return study_main(run, __file__, __doc__, argv=argv, summary=summary)


if __name__ == "__main__":
    sys.exit(main())
