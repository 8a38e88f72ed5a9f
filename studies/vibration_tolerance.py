"""Study: vibration error of a navigation accelerometer, tolerance limits on its
transfer-function coefficients, shaker test and in-flight compensation (SPEC.md §3).

Reproduces the paper's Table 1 (σ_V3), Table 2 (admissible coefficients, both examples),
Table 3 (shaker test of 12 AKS-05 units) and Table 5 (compensation on a shaker) beside
ours, with every discrepancy explained; compares the exact expectation of the vibration
error with the paper's closed forms (3)-(5), (19), (20) and a time-domain Monte Carlo;
computes gradient-based limits (exact sensitivities by jax.grad), the worst case over the
flight profile, the joint admissible region and a Monte Carlo production yield; and fits
the coefficients from simulated shaker/tilt test tables (identifiability, minimal plan).

Writes OUT/result.json and PNG figures. Run: `python studies/vibration_tolerance.py
[--out DIR] [--quick]`. float64 throughout: vibration errors are ppm-level differences of
O(1 g) numbers.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

import accel_jax as aj  # noqa: E402
from accel_jax import (  # noqa: E402
    PPM,
    StaticTransferFunction,
    basic_error,
    indicated_acceleration,
)
from accel_jax import (  # noqa: E402
    AKS05_RANGES_PPM,
    TOLERANCED,
    cyclone4,
    gradient_limits,
    paper_limits,
    sample_batch,
    sensitivities,
    sensitivity_profile,
    tactical_missile,
    unit_vibration_error,
)
from accel_jax import (  # noqa: E402
    VibrationEnvironment,
    compensate_in_flight,
    mean_abs_input,
    paper_deterministic_error,
    paper_vibration_error,
    random_rms,
    shaker_vibration_error,
    time_domain_vibration_error,
    vibration_error,
)

STUDY = "vibration_tolerance"

# --- the paper's published numbers ------------------------------------------------------
TABLE1 = {  # band edges [Hz], PSD range [g²/Hz], η, printed "η S Δf" column
    "f_low": [20.0, 40.0, 80.0, 160.0, 320.0],
    "f_high": [40.0, 80.0, 160.0, 320.0, 640.0],
    "psd_low": [0.016, 0.017, 0.020, 0.070, 0.120],
    "psd_high": [0.017, 0.020, 0.070, 0.120, 0.120],
    "eta": [1.6, 1.8, 0.4, 0.1, 0.05],
    "printed_column": [0.72, 1.17, 1.26, 1.26, 1.39],
    "printed_sigma_g": 1.4,
}
TABLE2 = {  # ppm units: A1 [ppm], k2 [ppm/g], k3 [ppm/g²], k4 [ppm/g³], k5 [ppm/g⁴], m [ppm/g]
    "cyclone4": {"asymmetry": 445, "k2": 10, "k3": 37, "k4": 24, "k5": 1, "m31": 48},
    "missile_short": {"asymmetry": 36, "k2": 1, "k3": 0.4, "k4": 0.01, "k5": 0.001, "m31": 0.5},
    "missile_long": {"asymmetry": 36, "k2": 1, "k3": 0.4, "k4": 0.01, "k5": 0.0004, "m31": 0.5},
}
TABLE3_1E4G = [2.2, 1.8, 0.5, 1.0, 0.6, 1.2, 2.0, 2.5, 0.7, 0.2, 2.0, 2.3]
TABLE5 = {  # â(1), â(2), â(3) [g], measured at 1 g with a 2 g, 30 Hz sinusoid on IA
    "AKS-05": [1.000100, 1.000083, 1.000006],
    "AL-1M": [1.001303, 1.001088, 1.000110],
}
COEFF_LABEL = {
    "asymmetry": "A1 [ppm]",
    "k2": "k2 [ppm/g]",
    "k3": "k3 [ppm/g²]",
    "k4": "k4 [ppm/g³]",
    "k5": "k5 [ppm/g⁴]",
    "m31": "m [ppm/g]",
}

# --- our assumptions ---------------------------------------------------------------------
SHAKER_SIGMA = 1.4  # g, the Table 1 level reproduced by the shaker (paper's value)
SHAKER_K1 = 1.0  # V/g (the estimator divides it out)
SHAKER_NOISE = 2e-6  # g per sample of the output record (white)
SHAKER_DRIFT = 2e-7  # g/min random bias drift rate (std), linear over the 15-min test
MC_RECORD_S = 1.0  # s, time-domain Monte Carlo record
MC_RATE = 4000.0  # Hz


def _ppm(x) -> float:
    return float(x) / PPM


def _table1():
    t = {k: np.asarray(v) for k, v in TABLE1.items() if k != "printed_sigma_g"}
    df = t["f_high"] - t["f_low"]
    mid = 0.5 * (t["psd_low"] + t["psd_high"])
    per_band_mid = np.sqrt(t["eta"] * mid * df)
    # The printed column, read as sqrt(η S Δf): the PSD it implies in each band.
    implied_psd = np.asarray(TABLE1["printed_column"]) ** 2 / (t["eta"] * df)
    printed_sq = np.asarray(TABLE1["printed_column"]) ** 2
    return {
        "per_band_sqrt_eta_S_df_g_midpoint_psd": per_band_mid,
        "printed_column": TABLE1["printed_column"],
        "psd_implied_by_printed_column_g2_per_Hz": implied_psd,
        "psd_implied_within_printed_range": bool(
            np.all((implied_psd >= t["psd_low"] * 0.97) & (implied_psd <= t["psd_high"] * 1.03))
        ),
        "paper_formula_sigma_g_midpoint_psd": float(random_rms(mid, df, t["eta"])),
        "mean_square_of_printed_column_g2": float(np.mean(printed_sq)),
        "sigma_from_printed_column_paper_formula_g": float(np.sqrt(np.mean(printed_sq))),
        "sigma_variance_additive_g": float(random_rms(mid, df, t["eta"], paper=False)),
        "paper_sigma_g": TABLE1["printed_sigma_g"],
        "explanation": (
            "The printed 'η S Δf [g²]' column is sqrt(η S Δf) in g (each value reproduces "
            "with a PSD inside the printed range). The paper's formula σ = sqrt((1/n) Σ η S Δf) "
            "gives 1.18 g from that column; the printed σ = 1.4 is the mean square (1/n) Σ η S Δf "
            "= 1.40 g² itself, i.e. the square root was not taken. The variance-additive RMS "
            "(no 1/n) would be 2.6 g. Table 2 is computed with 1.4 g, so we use 1.4 g."
        ),
    }


# --- Table 2 -----------------------------------------------------------------------------


def _variant_limits(sc) -> dict:
    """Candidate slips in the paper's arithmetic that would reproduce its table."""
    d = float(sc.admissible_error)
    a = abs(float(sc.mean_acceleration))
    b3 = float(sc.environment.sine_amplitude[2])
    s3 = float(sc.environment.random_std[2])
    return {
        "k3 with σ² for 3σ²": 0.35 * d / (a * (1.5 * b3**2 + s3**2)) / PPM,
        "k4 multiplicative ×10 (decimal comma lost)": 10
        * 0.24
        * d
        / (3 * a**2 * (b3**2 + 2 * s3**2))
        / PPM,
        "k2 / 10 (digit lost)": 0.44 * d / (0.5 * b3**2 + s3**2) / PPM / 10,
        "A1 with σ3 = 1.18 g (RMS of Table 1)": 0.44 * d / (0.673 * b3 + 0.125 * 1.18) / PPM,
    }


EXPLAIN = {
    "cyclone4": {
        "asymmetry": "reproduced within 3.5 % (430 vs 445); σ3 = 1.18 g (the true RMS of Table 1) gives 454: the paper's σ or its 0.673/0.125 factors were rounded differently",
        "k2": "not reproduced: (13) gives 105.5 ppm/g for any σ3 near 1.4 g (10 would need σ3 ≈ 4.7 g); the table's '10' looks like '105' with a digit lost",
        "k3": "not reproduced by (15) as printed (14.0); reproduced (37.5) if 3σ² is replaced by σ² — an arithmetic slip in the paper, since (5) and the Gaussian moment E[(a+v)³ − a³] = 3aσ² confirm the 3",
        "k4": "the binding (multiplicative) bound gives 2.40 ppm/g³; '24' is 2,4 with the decimal comma lost (the additive bound is 19)",
        "k5": "0.72 ppm/g⁴ (cubic bound; the linear bound is 1.5); the Cyclone-4 row is printed as integers, 0.72 → 1",
        "m31": "reproduced (48.7 vs 48) with in-phase sinusoids and fully correlated random vibration (ρ = 1)",
    },
    "missile_short": {
        "asymmetry": "reproduced (35.6 vs 36)",
        "k2": "reproduced (1.06 vs 1)",
        "k3": "not reproduced (0.055); with the same σ²-for-3σ² slip as Cyclone-4, 0.158; the table repeats the long-range value 0.4",
        "k4": "not reproduced: 0.0037 (multiplicative) vs 0.01 — same order; no single slip found that reproduces both flights and Cyclone-4",
        "k5": "not reproduced: 0.00014 (linear bound) vs 0.001; the long-range entry does reproduce (see there)",
        "m31": "reproduced (0.53 vs 0.5) with σ1 = σ3 = 9 g, ρ = 1",
    },
    "missile_long": {
        "asymmetry": "reproduced (35.6 vs 36)",
        "k2": "reproduced (1.06 vs 1)",
        "k3": "not reproduced (0.128); with the σ²-for-3σ² slip 0.366 ≈ 0.4 — the same slip as Cyclone-4",
        "k4": "not reproduced: 0.0045 (additive bound, binding at 2.2 g) vs 0.01",
        "k5": "reproduced to the table's one significant figure: 0.00032 (linear bound) vs 0.0004",
        "m31": "reproduced (0.53 vs 0.5)",
    },
}


def tolerance_tables(quick: bool) -> dict:
    scenarios = {
        "cyclone4": cyclone4(),
        "missile_short": tactical_missile("short"),
        "missile_long": tactical_missile("long"),
    }
    out = {}
    for name, sc in scenarios.items():
        paper = paper_limits(sc)
        grad_mean = gradient_limits(sc)
        grad_worst = gradient_limits(sc, over_profile=True)
        rows = {}
        for coeff in COEFF_LABEL:
            rows[coeff] = {
                "unit": COEFF_LABEL[coeff],
                "paper_table2": TABLE2[name][coeff],
                "ours_paper_method": _ppm(paper[coeff]),
                "ratio_ours_to_table": _ppm(paper[coeff]) / TABLE2[name][coeff],
                "gradient_paper_shares_at_mean_a3": _ppm(grad_mean["paper_shares"][coeff]),
                "gradient_paper_shares_worst_over_profile": _ppm(grad_worst["paper_shares"][coeff]),
                "gradient_full_budget_at_mean_a3": _ppm(grad_mean["full_budget"][coeff]),
                "gradient_equal_rms_share_at_mean_a3": _ppm(grad_mean["equal_rms"][coeff]),
                "sensitivity_g_per_unit": float(grad_mean["sensitivity"][coeff]),
                "explanation": EXPLAIN[name][coeff],
            }
        # The paper's box: every coefficient at its limit at once, exact sensitivities.
        sens_mean = sensitivities(sc.environment, sc.mean_acceleration)
        sens_prof = sensitivity_profile(sc)
        corner = np.array([float(paper[c]) for c in TOLERANCED])
        s_mean = np.array([float(getattr(sens_mean, c)) for c in TOLERANCED])
        s_prof = np.stack([np.asarray(getattr(sens_prof, c)) for c in TOLERANCED])  # (7, time)
        d = float(sc.admissible_error)
        box = {
            "rms_error_over_budget_at_mean_a3": float(np.sqrt(np.sum((s_mean * corner) ** 2)) / d),
            "coherent_error_over_budget_at_mean_a3": float(np.sum(np.abs(s_mean * corner)) / d),
            "coherent_error_over_budget_worst_over_profile": float(
                np.max(np.sum(np.abs(s_prof * corner[:, None]), axis=0)) / d
            ),
            "meaning": "a unit with every |coefficient| at the paper-method limit: its vibration error as a multiple of δ* — RMS combination (the paper's criterion (7)), sign-coherent sum (the worst case), and the coherent sum at the worst instant of the profile",
        }
        out[name] = {
            "paper_limit_box_corner": box,
            "admissible_error_g": float(sc.admissible_error),
            "mean_acceleration_g": float(sc.mean_acceleration),
            "profile_mean_g": float(np.mean(np.asarray(sc.profile_acceleration))),
            "profile_range_g": [
                float(np.min(sc.profile_acceleration)),
                float(np.max(sc.profile_acceleration)),
            ],
            "sine_amplitude_g": np.asarray(sc.environment.sine_amplitude),
            "random_std_g": np.asarray(sc.environment.random_std),
            "coefficients": rows,
            "paper_method_all_bounds_ppm": {k: _ppm(v) for k, v in paper.items()},
            "candidate_slips_ppm": _variant_limits(sc),
        }
    va = 1.5 / math.sqrt(1.5**2 + 1)
    out["budget_notes"] = {
        "additive_share_from_8_9": va,
        "multiplicative_share_from_8_9": va / 1.5,
        "per_additive_term_from_11": va / math.sqrt(3.5),
        "per_cross_term_from_11": 0.5 * va / math.sqrt(3.5),
        "linear_multiplicative_from_14_consistent": (va / 1.5) / math.sqrt(1.5),
        "paper_linear_multiplicative": 0.49,
        "quadrature_sum_of_paper_multiplicative_shares": math.sqrt(0.49**2 + 2 * 0.24**2),
        "note": "0.83, 0.55, 0.44, 0.22 follow from (8), (9), (11); with δ(2)a² = δ(3)a³ = ½δ(1)a the linear share consistent with 0.55 is 0.45, not the paper's 0.49 (0.49 ≈ 0.55/√1.25, as if one of the two half-shares had been left out), and 0.49, 0.24, 0.24 add in quadrature to 0.60 > 0.55: the paper's multiplicative budget is overspent by 9 %. k3 and k5 then share δ(1) as 0.49/√2 = 0.35 each.",
    }
    return out, scenarios


# --- vibration error: exact vs closed form vs Monte Carlo ----------------------------------


def _mc_one(tf, env, a3, ts, key):
    return time_domain_vibration_error(tf, env, a3, 0.0, 0.0, ts, key=key)


def _mc(tf, env, a3, key, n):
    ts = jnp.arange(int(MC_RECORD_S * MC_RATE)) / MC_RATE
    keys = jax.random.split(key, n)
    a3 = jnp.asarray(a3, dtype=jnp.float64)
    vals = np.asarray(aj.sweep(_mc_one, tf, env, a3, ts, keys, in_axes=(None, None, None, None, 0)))
    return float(vals.mean()), float(vals.std(ddof=1) / math.sqrt(n))


_exact = eqx.filter_jit(vibration_error)
_exact_batch = eqx.filter_jit(jax.vmap(vibration_error, in_axes=(None, None, 0)))
_paper = eqx.filter_jit(paper_vibration_error)


def vibration_comparison(key, quick: bool) -> dict:
    n = 16 if quick else 256
    aks, al = StaticTransferFunction.aks05(), StaticTransferFunction.al1m()
    aks_m = eqx.tree_at(lambda t: (t.m31, t.m32), aks, (3 * PPM, 3 * PPM))
    cyc, mis = cyclone4(), tactical_missile("long")
    cases = {
        "AKS-05, 1 g, sine 2 g (Table 5)": (
            aks,
            VibrationEnvironment(
                sine_amplitude=(0, 0, 2.0), sine_frequency=30.0, random_band=(20.0, 640.0)
            ),
            1.0,
        ),
        "AL-1M, 1 g, sine 2 g (Table 5)": (
            al,
            VibrationEnvironment(
                sine_amplitude=(0, 0, 2.0), sine_frequency=30.0, random_band=(20.0, 640.0)
            ),
            1.0,
        ),
        "AKS-05, 1 g, random 1.4 g (Table 3 shaker)": (
            aks,
            VibrationEnvironment(random_std=(0, 0, SHAKER_SIGMA), random_band=(20.0, 640.0)),
            1.0,
        ),
        "AKS-05 (m = 3 ppm/g), Cyclone-4 flight at 2 g": (aks_m, cyc.environment, 2.0),
        "AKS-05 (m = 3 ppm/g), missile (long) at 2.2 g": (aks_m, mis.environment, 2.2),
    }
    keys = jax.random.split(key, len(cases))
    rows = {}
    for k, (label, (tf, env, a)) in zip(keys, cases.items(), strict=True):
        a = jnp.asarray(a, dtype=jnp.float64)
        exact = _ppm(_exact(tf, env, a))
        paper = _ppm(_paper(tf, env, a))
        mc, se = _mc(tf, env, a, k, n)
        a1_only = StaticTransferFunction(asymmetry=tf.asymmetry)
        rows[label] = {
            "exact_ppm": exact,
            "paper_closed_form_ppm": paper,
            "monte_carlo_ppm": mc / PPM,
            "monte_carlo_standard_error_ppm": se / PPM,
            "monte_carlo_z": (mc / PPM - exact) / (se / PPM),
            "A1_term_exact_ppm": _ppm(_exact(a1_only, env, a)),
            "A1_term_paper_ppm": _ppm(_paper(a1_only, env, a)),
            "difference_paper_minus_exact_ppm": paper - exact,
        }
    return {
        "cases": rows,
        "monte_carlo": {
            "records": n,
            "record_s": MC_RECORD_S,
            "sample_rate_Hz": MC_RATE,
            "synthesis": "sinusoid with random start + 64-tone Gaussian spectral synthesis on the record's Fourier grid",
        },
        "where_they_differ": (
            "Polynomial terms: the paper's (19), (20) equal the exact expectation for a pure "
            "sinusoid or pure Gaussian vibration (k5's quartic factor printed 1.185 in (19) is "
            "1.875 in (5) and exactly); combined sine + random, the paper's sum omits the cross "
            "moment 3b²σ² in E w⁴ (k4, k5 terms). The A1 term differs everywhere: exactly, "
            "½A1(E|a+v| − |a|) is 0 unless the vibration crosses zero and is never negative, "
            "whereas the paper's A1(0.673 b − 0.5 a) + 0.125 A1 σ has the wrong limits (negative "
            "for a > 1.35 b, 0.673 instead of 2/π = 0.637 at a = 0)."
        ),
    }


def asymmetry_curve() -> dict:
    b = 2.0
    ratio = np.linspace(0, 2, 81)
    env = VibrationEnvironment(sine_amplitude=(0, 0, b))
    exact = np.asarray(
        jax.jit(jax.vmap(lambda a: 0.5 * (mean_abs_input(env, a) - jnp.abs(a))))(
            jnp.asarray(ratio * b)
        )
    )
    paper = 0.673 * b - 0.5 * ratio * b
    return {"a_over_b": ratio, "exact_per_A1_g": exact, "paper_per_A1_g": paper, "b_g": b}


# --- Table 5: compensation ---------------------------------------------------------------


_compensate = eqx.filter_jit(compensate_in_flight)


def table5() -> dict:
    env = VibrationEnvironment(sine_amplitude=(0, 0, 2.0), sine_frequency=30.0)
    out = {}
    for name, tf in (
        ("AKS-05", StaticTransferFunction.aks05()),
        ("AL-1M", StaticTransferFunction.al1m()),
    ):
        measured = TABLE5[name]
        # (a) The paper's algorithm (17)-(19), applied by us to the paper's measured â(1).
        ours_on_measured = _compensate(tf, measured[0] + float(tf.bias), env, method="paper")
        printed_k5 = _compensate(
            tf, measured[0] + float(tf.bias), env, method="paper", k5_quartic=1.185
        )
        exact_on_measured = _compensate(tf, measured[0] + float(tf.bias), env, method="exact")
        # (b) Our model's prediction of the measurement: the passport unit at exactly 1 g.
        indicated = float(indicated_acceleration(tf, 1.0)) + float(vibration_error(tf, env, 1.0))
        model_paper = _compensate(tf, indicated, env, method="paper")
        model_exact = _compensate(tf, indicated, env, method="exact")

        def res(x):
            return (float(x) - 1.0) / PPM

        out[name] = {
            "paper_measured_residual_ppm": [res(v) for v in measured],
            "paper_algorithm_on_measured_residual_ppm": [
                res(ours_on_measured.first),
                res(ours_on_measured.after_basic),
                res(ours_on_measured.after_deterministic),
            ],
            "paper_algorithm_printed_1_185_on_measured_residual_ppm": res(
                printed_k5.after_deterministic
            ),
            "exact_compensation_on_measured_residual_ppm": res(
                exact_on_measured.after_deterministic
            ),
            "removed_by_paper_19_ppm": (
                float(ours_on_measured.after_basic) - float(ours_on_measured.after_deterministic)
            )
            / PPM,
            "removed_in_paper_table_ppm": (measured[1] - measured[2]) / PPM,
            "exact_vibration_error_at_1g_ppm": _ppm(vibration_error(tf, env, 1.0)),
            "basic_error_at_1g_ppm": _ppm(basic_error(tf, 1.0, include_bias=False)),
            "model_predicted_residual_ppm": {
                "no_compensation": res(model_paper.first),
                "after_basic": res(model_paper.after_basic),
                "after_paper_19": res(model_paper.after_deterministic),
                "after_exact": res(model_exact.after_deterministic),
            },
            "A1_term_paper_ppm": _ppm(
                paper_deterministic_error(
                    StaticTransferFunction(asymmetry=tf.asymmetry),
                    env,
                    float(ours_on_measured.first),
                )
            ),
            "A1_term_exact_ppm": _ppm(
                vibration_error(StaticTransferFunction(asymmetry=tf.asymmetry), env, 1.0)
            ),
        }
    aks, al = out["AKS-05"], out["AL-1M"]

    def gap(t):
        return (
            t["paper_algorithm_on_measured_residual_ppm"][1] - t["exact_vibration_error_at_1g_ppm"]
        )

    out["explanation"] = (
        f"Step (18) on the measured â(1) removes {aks['basic_error_at_1g_ppm']:.1f} ppm (AKS-05, "
        f"paper 17) and {al['paper_algorithm_on_measured_residual_ppm'][0] - al['paper_algorithm_on_measured_residual_ppm'][1]:.1f} ppm "
        "(AL-1M, paper 215: the paper evaluated δ_OP at 1 g rather than at â(1) = 1.0013 g). "
        f"Step (19) removes {aks['removed_by_paper_19_ppm']:.1f} / {al['removed_by_paper_19_ppm']:.1f} ppm "
        f"(paper {aks['removed_in_paper_table_ppm']:.0f} / {al['removed_in_paper_table_ppm']:.0f}): AL-1M "
        "reproduces to 1 ppm, AKS-05 to 3 ppm (with the printed k5 factor 1.185 the residual is "
        f"{aks['paper_algorithm_printed_1_185_on_measured_residual_ppm']:.1f} ppm). The exact expectation "
        f"of the passport model predicts {aks['exact_vibration_error_at_1g_ppm']:.1f} / "
        f"{al['exact_vibration_error_at_1g_ppm']:.1f} ppm of vibration error, {gap(aks):.0f} / {gap(al):.0f} ppm "
        "less than the measurement shows after basic compensation. The paper's A1 term "
        f"({aks['A1_term_paper_ppm']:.1f} / {al['A1_term_paper_ppm']:.1f} ppm against the exact "
        f"{aks['A1_term_exact_ppm']:.1f} / {al['A1_term_exact_ppm']:.1f} ppm; the polynomial terms of (19) are exact for a pure sinusoid) absorbs "
        "part of that gap, so on these two measurements the paper's formula leaves a smaller residual "
        "than the exact expectation does. What remains (6 / 110 ppm in the paper) is not explained by "
        "the Table 4 passport model: candidates are coefficients that drifted since the passport, "
        "δ(ω) or a frequency-dependent nonlinearity at 30 Hz, and cross-axis shaker motion."
    )
    return out


# --- Table 3: shaker test ----------------------------------------------------------------


def _shaker_one(tf, key, env, n_samples):
    k_n1, k_n2, k_n3, k_d = jax.random.split(key, 4)
    drift = SHAKER_DRIFT * jax.random.normal(k_d, ()) / 60.0  # g/s
    t = jnp.arange(n_samples) * (300.0 / n_samples)
    true_err = vibration_error(tf, env, 1.0, n_phase=128)
    base = indicated_acceleration(tf, 1.0)
    u1 = SHAKER_K1 * (base + drift * t + SHAKER_NOISE * jax.random.normal(k_n1, t.shape))
    u2 = SHAKER_K1 * (
        base + true_err + drift * (t + 300) + SHAKER_NOISE * jax.random.normal(k_n2, t.shape)
    )
    u3 = SHAKER_K1 * (base + drift * (t + 600) + SHAKER_NOISE * jax.random.normal(k_n3, t.shape))
    est = shaker_vibration_error(u1, u2, u3, SHAKER_K1)
    return est.vibration_error, true_err, est.axis_shift, est.valid


def table3(key, quick: bool) -> dict:
    out = _table3_at(key, quick, SHAKER_SIGMA)
    alt = _table3_at(key, quick, float(_table1()["sigma_variance_additive_g"]))
    aks = StaticTransferFunction.aks05()
    out["variance_additive_sigma_g"] = alt["sigma_g"]
    out["ours_mean_abs_1e-4g_variance_additive_sigma"] = alt["ours_mean_abs_1e-4g"]
    out["ours_quantiles_abs_1e-4g_variance_additive_sigma"] = alt["ours_quantiles_abs_1e-4g"]
    out["aks05_passport_exact_1e-4g"] = {
        f"sigma_{sig:.2f}_g": float(
            vibration_error(aks, VibrationEnvironment(random_std=(0, 0, sig)), 1.0)
        )
        / 1e-4
        for sig in (SHAKER_SIGMA, alt["sigma_g"])
    }
    out["explanation"] = (
        "Units drawn uniformly inside Table 2's AKS-05 ranges (random signs), random vibration on IA at "
        "1 g, shaker records 3 × 5 min with white noise and a random linear drift, estimated by (16). "
        f"The estimator is accurate (RMS error {out['estimator_error_rms_1e-4g']:.4f}e-4 g), so the "
        "comparison tests the coefficient model. With the paper's σ = 1.4 g the exact expectation "
        f"predicts mean |δ_V| = {out['ours_mean_abs_1e-4g']:.2f}e-4 g against the measured "
        f"{out['paper_mean_1e-4g']:.2f}e-4 g (the passport AKS-05, all coefficients positive: "
        f"{out['aks05_passport_exact_1e-4g'][f'sigma_{SHAKER_SIGMA:.2f}_g']:.2f}e-4 g). With the Table 1 "
        f"spectrum without the paper's square-root slip (σ = {alt['sigma_g']:.2f} g) the mean is "
        f"{alt['ours_mean_abs_1e-4g']:.2f}e-4 g, the measured scale. Random coefficient signs make "
        "our spread wider toward zero than the measured one, which suggests like-signed coefficients."
    )
    return out


def _table3_at(key, quick: bool, sigma: float) -> dict:
    env = VibrationEnvironment(random_std=(0, 0, sigma), random_band=(20.0, 640.0))
    n_units = 12 if quick else 2000
    k_units, k_tests = jax.random.split(key)
    batch = sample_batch(
        k_units, n_units, {k: v for k, v in AKS05_RANGES_PPM.items() if k not in ("m31", "m32")}
    )
    keys = jax.random.split(k_tests, n_units)
    est, truth, shift, valid = (
        np.asarray(x)
        for x in aj.sweep(lambda tf, k: _shaker_one(tf, k, env, 3000), batch, keys, in_axes=(0, 0))
    )
    paper = np.asarray(TABLE3_1E4G) * 1e-4
    ours_abs = np.abs(est)
    return {
        "sigma_g": sigma,
        "paper_1e-4g": TABLE3_1E4G,
        "paper_mean_1e-4g": float(paper.mean() / 1e-4),
        "paper_max_1e-4g": float(paper.max() / 1e-4),
        "units_simulated": n_units,
        "ours_mean_abs_1e-4g": float(ours_abs.mean() / 1e-4),
        "ours_quantiles_abs_1e-4g": {
            q: float(np.quantile(ours_abs, q) / 1e-4) for q in (0.05, 0.5, 0.95)
        },
        "ours_max_abs_1e-4g": float(ours_abs.max() / 1e-4),
        "estimator_error_rms_1e-4g": float(np.sqrt(np.mean((est - truth) ** 2)) / 1e-4),
        "axis_check_pass_fraction": float(valid.mean()),
        "axis_shift_max_rad": float(shift.max()),
        "fraction_above_paper_mean": float(np.mean(ours_abs > paper.mean())),
    }


# --- yield and joint region ----------------------------------------------------------------


def yield_study(key, scenario, quick: bool) -> dict:
    n = 512 if quick else 8192
    batch = sample_batch(key, n)
    # Every 10th profile point (61 instants) and 64 phases: the polynomial terms stay exact
    # (any n_phase ≥ 6); the A1 term's phase average is smooth here (σ3/b3 = 2.8).
    scenario = eqx.tree_at(
        lambda s: (s.profile_time, s.profile_acceleration),
        scenario,
        (scenario.profile_time[::10], scenario.profile_acceleration[::10]),
    )
    at_mean, worst = (
        np.asarray(x)
        for x in aj.sweep(
            lambda tf, sc: unit_vibration_error(tf, sc, n_phase=64),
            batch,
            scenario,
            in_axes=(0, None),
        )
    )
    paper = paper_limits(scenario)
    inside_box = np.ones(n, bool)
    for name in ("asymmetry", "k2", "k3", "k4", "k5", "m31", "m32"):
        inside_box &= np.abs(np.asarray(getattr(batch, name))) <= float(paper[name])
    d = float(scenario.admissible_error)
    p_mean = float(np.mean(np.abs(at_mean) <= d))
    return {
        "units": n,
        "distribution": "|coefficient| uniform in Table 2's AKS-05 ranges, independent random signs",
        "yield_exact_at_mean_a3": p_mean,
        "yield_exact_worst_over_profile": float(np.mean(worst <= d)),
        "yield_standard_error": math.sqrt(max(p_mean * (1 - p_mean), 1.0 / n) / n),
        "fraction_inside_paper_limit_box": float(inside_box.mean()),
        "vibration_error_at_mean_ppm_quantiles": {
            q: float(np.quantile(at_mean, q) / PPM) for q in (0.01, 0.5, 0.99)
        },
        "worst_over_profile_ppm_quantiles": {
            q: float(np.quantile(worst, q) / PPM) for q in (0.5, 0.99)
        },
        "_samples": {
            "at_mean": at_mean,
            "worst": worst,
            "k3": np.asarray(batch.k3),
            "k5": np.asarray(batch.k5),
        },
    }


# --- run ---------------------------------------------------------------------------------


def run(out_dir: Path, *, quick: bool = False, seed: int = 20261122) -> dict:
    """Run the study; write OUT/result.json and figures; return the result dict."""
    if not jax.config.jax_enable_x64:
        raise ValueError(
            "vibration_tolerance needs float64 (ppm-level errors): call "
            "jax.config.update('jax_enable_x64', True) before run()."
        )
    out_dir = Path(out_dir)
    started = time.perf_counter()
    k_mc, k_t3, k_yield, k_fit = jax.random.split(jax.random.key(seed), 4)

    tables, scenarios = tolerance_tables(quick)
    vib = vibration_comparison(k_mc, quick)
    t5 = table5()
    t3 = table3(k_t3, quick)
    yld = yield_study(k_yield, scenarios["cyclone4"], quick)
    fit = coefficient_fitting(k_fit, quick)
    samples = yld.pop("_samples")

    result = {
        "title": "Vibration error, coefficient tolerances, shaker test and compensation (SPEC.md §3)",
        "tolerance_limits": tables,
        "vibration_error": vib,
        "asymmetry_term": asymmetry_curve(),
        "table1_random_vibration": _table1(),
        "table3_shaker": t3,
        "table5_compensation": t5,
        "yield": yld,
        "coefficient_fitting": fit,
        "assumptions": {
            "precision": "float64",
            "units": "g for accelerations; coefficients reported in ppm units (A1 ppm, k_n ppm/g^(n-1), m ppm/g)",
            "cyclone4": "a3 = 2 g; sine b3 = 0.5 g, b1 = b2 = 1.2 g in phase; σ = 1.4 g on every axis, fully correlated (ρ = 1); δ* = 5e-4 g; profile: piecewise-linear approximation of Fig. 3a (1-5 g, 600 s)",
            "tactical_missile": "δ* = 2e-4 g; sine 2 g on every axis in phase; σ = 9 g on every axis (paper's η-scaled value), ρ = 1; a3 = 5.1 g (short, 8 → 2.2 g over 100 s) or 2.2 g (long, 1.2 + 5e^{-t/60} g over 300 s)",
            "paper_method": "(13), (15) as reconstructed in SPEC.md §3 with the fixed shares 0.44, 0.22, 0.35, 0.24",
            "gradient_method": "exact sensitivities ∂δ_V/∂k by jax.grad of the exact expectation (512 phases × 6 Gauss-Hermite nodes); 'paper shares' = the paper's share of δ* for that coefficient",
            "vibration_constant_over_flight": True,
            "shaker_sigma_g": SHAKER_SIGMA,
            "shaker_noise_g": SHAKER_NOISE,
            "shaker_drift_g_per_min": SHAKER_DRIFT,
            "table5_environment": "sinusoid 2 g at 30 Hz on IA only (no cross-axis vibration), a3 = 1 g",
            "yield_distribution": "uniform |coefficient| in the AKS-05 ranges of Table 2, random signs",
        },
        "provenance": aj.provenance(
            seeds={"root": seed},
            precision="float64",
            extra={"quick": quick},
        ),
    }
    result["summary"] = _summary(result)
    result["figures"] = make_figures(out_dir, result, scenarios, samples)
    result["provenance"]["wall_time_s"] = time.perf_counter() - started
    aj.write_json_atomic(out_dir / "result.json", result)
    return result


def _summary(r) -> list:
    rows = []
    for name, label in (
        ("cyclone4", "Cyclone-4"),
        ("missile_short", "missile, short"),
        ("missile_long", "missile, long"),
    ):
        for row in r["tolerance_limits"][name]["coefficients"].values():
            rows.append(
                {
                    "quantity": f"Table 2 {label}: |{row['unit']}| limit",
                    "ours": round(row["ours_paper_method"], 6),
                    "paper": row["paper_table2"],
                    "note": f"gradient (paper shares) {row['gradient_paper_shares_at_mean_a3']:.4g}; "
                    + row["explanation"],
                }
            )
    t1 = r["table1_random_vibration"]
    rows.append(
        {
            "quantity": "Table 1 σ_V3 [g]",
            "ours": round(t1["sigma_from_printed_column_paper_formula_g"], 3),
            "paper": 1.4,
            "note": t1["explanation"],
        }
    )
    for name in ("AKS-05", "AL-1M"):
        t = r["table5_compensation"][name]
        for i, step in enumerate(("â(1)", "â(2) after basic", "â(3) after vibration (19)")):
            rows.append(
                {
                    "quantity": f"Table 5 {name} {step} residual [ppm]",
                    "ours": round(t["paper_algorithm_on_measured_residual_ppm"][i], 2),
                    "paper": round(t["paper_measured_residual_ppm"][i], 2),
                    "note": "our (17)-(19) applied to the measured â(1); model-predicted residuals: "
                    + ", ".join(
                        f"{k} {v:.1f}" for k, v in t["model_predicted_residual_ppm"].items()
                    ),
                }
            )
    t3 = r["table3_shaker"]
    rows.append(
        {
            "quantity": "Table 3 mean |δ̂_V| [1e-4 g]",
            "ours": round(t3["ours_mean_abs_1e-4g"], 3),
            "paper": round(t3["paper_mean_1e-4g"], 3),
            "note": t3["explanation"],
        }
    )
    for label, case in r["vibration_error"]["cases"].items():
        rows.append(
            {
                "quantity": f"δ_V exact [ppm]: {label}",
                "ours": round(case["exact_ppm"], 3),
                "paper": round(case["paper_closed_form_ppm"], 3),
                "note": f"paper column = the paper's closed forms evaluated by us; Monte Carlo {case['monte_carlo_ppm']:.2f} ± {case['monte_carlo_standard_error_ppm']:.2f}",
            }
        )
    rows.append(
        {
            "quantity": "AKS-05 batch yield on Cyclone-4 (|δ_V| ≤ δ* at 2 g)",
            "ours": round(r["yield"]["yield_exact_at_mean_a3"], 4),
            "paper": "'practically all'",
            "note": f"worst over profile {r['yield']['yield_exact_worst_over_profile']:.4f}; inside the paper's limit box {r['yield']['fraction_inside_paper_limit_box']:.3f}",
        }
    )
    return rows


# --- coefficient fitting ------------------------------------------------------------------


FIT_NOISE = 1e-6  # g, standard deviation of one test's mean output (5-min average)
FIT_TRUTH = StaticTransferFunction.from_ppm(
    bias_mg=0.5, scale_factor_error=50, asymmetry=15, k2=2, k3=7, k4=0.02, k5=0.3
)  # AKS-05 passport + a 50 ppm scale-factor error


def _plan(a, b, s=0.0) -> dict:
    a, b, s = (np.asarray(x, float).ravel() for x in np.broadcast_arrays(a, b, s))
    return {
        "a_in": a,
        "vib_amp": b,
        "vib_freq": np.full_like(a, 30.0),
        "vib_rms": s,
        "a_out": np.zeros_like(a),
    }


def _greedy_plan(target_se: np.ndarray, max_rows: int = 30) -> tuple[dict, list]:
    """Rows added one at a time from the candidate grid a_in ∈ {−1, −½, 0, ½, 1} g (tilt in
    gravity) × sine amplitude {0, 1, 2, 3, 4} g, each maximising log det(JᵀJ) (D-optimal),
    until every standard error is below its target."""
    A, B = np.meshgrid([-1.0, -0.5, 0.0, 0.5, 1.0], [0.0, 1.0, 2.0, 3.0, 4.0])
    grid = _plan(A, B)
    J = np.asarray(aj_design(grid)) / FIT_NOISE
    chosen: list[int] = []
    history = []
    for _ in range(max_rows):
        best, best_val = None, -np.inf
        for i in range(J.shape[0]):
            M = J[chosen + [i]]
            val = np.linalg.slogdet(M.T @ M + 1e-12 * np.eye(J.shape[1]))[1]
            if val > best_val:
                best, best_val = i, val
        chosen.append(best)
        M = J[chosen]
        if len(chosen) >= J.shape[1] and np.linalg.matrix_rank(M) == J.shape[1]:
            se = np.sqrt(np.diag(np.linalg.inv(M.T @ M)))
            history.append(
                {"rows": len(chosen), "max_se_over_target": float(np.max(se / target_se))}
            )
            if np.all(se <= target_se):
                break
    plan = {k: v[chosen] for k, v in grid.items()}
    return plan, history


def aj_design(plan):
    from accel_jax import design_matrix

    return design_matrix(plan)


def coefficient_fitting(key, quick: bool) -> dict:
    from accel_jax import fit_coefficients, identifiability, predict_table

    A, B = np.meshgrid([-1.0, 1.0], [0.0, 2.0, 4.0])
    tilt = np.cos(np.linspace(0, np.pi, 12))
    plans = {
        "±1 g only": _plan([-1.0, 1.0], 0.0),
        "0, ±1 g (tumble)": _plan([-1.0, 0.0, 1.0], 0.0),
        "12-position tilt, a = cos θ": _plan(tilt, 0.0),
        "±1 g × sine {0, 2, 4} g": _plan(A, B),
        "12-position tilt + ±1 g × sine {2, 4} g": _plan(
            np.r_[tilt, -1, 1, -1, 1], np.r_[np.zeros(12), 2, 2, 4, 4]
        ),
    }
    cyc = paper_limits(cyclone4())
    # Target: a tenth of the Cyclone-4 paper-method limits; 5 µg / 5 ppm for a0 and δ.
    target_ppm = {
        "bias": 5.0,
        "scale_factor_error": 5.0,
        "asymmetry": 0.1 * _ppm(cyc["asymmetry"]),
        "k2": 0.1 * _ppm(cyc["k2"]),
        "k3": 0.1 * _ppm(cyc["k3"]),
        "k4": 0.1 * _ppm(cyc["k4"]),
        "k5": 0.1 * _ppm(cyc["k5"]),
    }
    minimal, history = _greedy_plan(np.asarray(list(target_ppm.values())))
    plans["recommended (greedy D-optimal)"] = minimal
    out_plans = {}
    for name, plan in plans.items():
        idf = identifiability(plan, noise=FIT_NOISE)
        out_plans[name] = {
            "rows": int(plan["a_in"].size),
            "a_in_g": plan["a_in"],
            "vib_amp_g": plan["vib_amp"],
            "identifiable": dict(
                zip(idf.names, np.asarray(idf.identifiable).tolist(), strict=True)
            ),
            "unexplained_fraction": dict(
                zip(idf.names, np.asarray(idf.unexplained_fraction), strict=True)
            ),
            "standard_error_ppm": {
                n: (float(v) if np.isfinite(v) else None)
                for n, v in zip(idf.names, np.asarray(idf.standard_error_ppm), strict=True)
            },
        }
    # Simulate → fit → recover on the recommended plan.
    n_rep = 4 if quick else 64
    truth = np.array([500.0, 50.0, 15.0, 2.0, 7.0, 0.02, 0.3])
    clean = np.asarray(predict_table(FIT_TRUTH, minimal))
    rng = np.random.default_rng(int(jax.random.randint(key, (), 0, 2**31 - 1)))
    estimates, ses, z = [], [], []
    last = None
    for _ in range(n_rep):
        plan = dict(minimal, a_out=clean + FIT_NOISE * rng.normal(size=clean.size))
        last = fit_coefficients(plan, noise=FIT_NOISE)
        estimates.append(np.asarray(last.estimate_ppm))
        ses.append(np.asarray(last.standard_error_ppm))
        z.append((estimates[-1] - truth) / ses[-1])
    estimates, ses, z = np.asarray(estimates), np.asarray(ses), np.asarray(z)
    names = last.names
    return {
        "noise_g_per_test": FIT_NOISE,
        "truth_ppm": dict(zip(names, truth, strict=True)),
        "target_standard_error_ppm": target_ppm,
        "plans": out_plans,
        "greedy_history": history,
        "recommended_rows": int(minimal["a_in"].size),
        "recovery": {
            "fits": n_rep,
            "mean_estimate_ppm": dict(zip(names, estimates.mean(0), strict=True)),
            "empirical_std_ppm": dict(zip(names, estimates.std(0, ddof=1), strict=True)),
            "reported_standard_error_ppm": dict(zip(names, ses.mean(0), strict=True)),
            "max_abs_z": float(np.max(np.abs(z))),
            "correlation_last_fit": np.asarray(last.correlation),
        },
        "findings": (
            "At ±1 g alone only two combinations are identifiable (a and a³, a² and a⁴ and |a| "
            "and the bias coincide): k3·a³ is indistinguishable from the scale factor. Intermediate "
            "inputs (tilt) separate the polynomial terms but leave k4, k5 poorly determined within "
            "|a| ≤ 1 g; vibration levels separate them through the moments E[(a+w)ⁿ] (k3 via 3a·b²/2, "
            "k4 via 3b⁴/8, k5 via 5a·3b⁴/8). The recommended plan mixes tilt positions and shaker levels."
        ),
    }


# --- figures -----------------------------------------------------------------------------


def make_figures(out_dir, r, scenarios, samples) -> list:
    figures = []
    out_dir.mkdir(parents=True, exist_ok=True)

    # 1. Table 2: paper vs ours vs gradient.
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.5), sharey=False)
    for ax, (name, title) in zip(
        axes,
        (
            ("cyclone4", "Cyclone-4"),
            ("missile_short", "missile, short range"),
            ("missile_long", "missile, long range"),
        ),
        strict=True,
    ):
        rows = r["tolerance_limits"][name]["coefficients"]
        labels = list(rows)
        x = np.arange(len(labels))
        series = (
            ("paper_table2", "paper Table 2"),
            ("ours_paper_method", "paper method (13), (15), ours"),
            ("gradient_paper_shares_at_mean_a3", "gradient, paper shares, mean a3"),
            ("gradient_paper_shares_worst_over_profile", "gradient, worst over profile"),
        )
        for i, (key, lab) in enumerate(series):
            ax.bar(x + (i - 1.5) * 0.2, [rows[c][key] for c in labels], 0.2, label=lab)
        ax.set_yscale("log")
        ax.set_xticks(x, [rows[c]["unit"] for c in labels], rotation=30, ha="right")
        ax.set_ylabel("admissible |coefficient| [ppm units]")
        ax.set_title(title)
        ax.grid(alpha=0.3, axis="y")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    aj.save_figure_atomic(fig, out_dir / "tolerance_limits.png")
    plt.close(fig)
    figures.append(
        {
            "file": "tolerance_limits.png",
            "caption": "Admissible coefficient moduli: the paper's Table 2, the paper's method (13), (15) as reconstructed, and gradient-based limits with exact sensitivities (same budget shares) at the mean a3 and in the worst instant of the approximated flight profile. Vibration taken in phase and fully correlated across axes; σ as the paper's (1.4 g, 9 g).",
        }
    )

    # 2. A1 term.
    a = r["asymmetry_term"]
    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    ax.plot(a["a_over_b"], np.asarray(a["exact_per_A1_g"]), label="exact ½(E|a+b sin θ| − |a|)")
    ax.plot(a["a_over_b"], np.asarray(a["paper_per_A1_g"]), "--", label="paper 0.673 b − 0.5 a")
    ax.axhline(0, color="k", lw=0.5)
    ax.set_xlabel("mean input / sine amplitude a/b [1]")
    ax.set_ylabel("δ_V per unit A1 [g]  (b = 2 g)")
    ax.legend()
    ax.grid(alpha=0.3)
    fig.tight_layout()
    aj.save_figure_atomic(fig, out_dir / "asymmetry_term.png")
    plt.close(fig)
    figures.append(
        {
            "file": "asymmetry_term.png",
            "caption": "Vibration error per unit scale-factor asymmetry A1 under a 2 g sinusoid: exact time average against the paper's A1(0.673 b − 0.5 a). The exact term vanishes once the sinusoid no longer crosses zero (a ≥ b); the paper's goes negative.",
        }
    )

    # 3. Vibration error versus input: exact vs paper, sine 2 g.
    env = VibrationEnvironment(sine_amplitude=(0, 0, 2.0))
    a3 = jnp.linspace(-3, 3, 121)
    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    for tf, name, c in (
        (StaticTransferFunction.aks05(), "AKS-05", "tab:blue"),
        (StaticTransferFunction.al1m(), "AL-1M", "tab:red"),
    ):
        ex = np.asarray(_exact_batch(tf, env, a3)) / PPM
        pa = np.asarray(paper_deterministic_error(tf, env, a3)) / PPM
        ax.plot(a3, ex, color=c, label=f"{name} exact")
        ax.plot(a3, pa, "--", color=c, label=f"{name} paper (19)")
    for label, case in r["vibration_error"]["cases"].items():
        if "Table 5" in label:
            ax.errorbar(
                [1.0],
                [case["monte_carlo_ppm"]],
                yerr=[2 * case["monte_carlo_standard_error_ppm"]],
                fmt="ko",
                ms=4,
            )
    ax.plot([], [], "ko", label="time-domain Monte Carlo ± 2 SE")
    ax.set_yscale("symlog", linthresh=10)
    ax.set_xlabel("input acceleration a3 [g]")
    ax.set_ylabel("vibration error δ_V [ppm of g]")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    aj.save_figure_atomic(fig, out_dir / "vibration_error_vs_input.png")
    plt.close(fig)
    figures.append(
        {
            "file": "vibration_error_vs_input.png",
            "caption": "Vibration error of the Table 4 passport units under a 2 g sinusoid along IA: exact expectation, the paper's (19), and the time-domain Monte Carlo at 1 g (the Table 5 condition). m = 0 (not in Table 4).",
        }
    )

    # 4. Sensitivity along the profile.
    sc = scenarios["cyclone4"]
    prof = sensitivity_profile(sc)
    fig, ax = plt.subplots(figsize=(7, 4.2))
    for name in ("asymmetry", "k3", "k4", "k5"):
        s = np.abs(np.asarray(getattr(prof, name)))
        ax.plot(
            np.asarray(sc.profile_time),
            float(sc.admissible_error) / s / PPM,
            label=COEFF_LABEL[name],
        )
    ax.set_yscale("log")
    ax.set_xlabel("flight time [s]")
    ax.set_ylabel("full-budget limit δ*/|∂δ_V/∂k| [ppm units]")
    ax2 = ax.twinx()
    ax2.plot(np.asarray(sc.profile_time), np.asarray(sc.profile_acceleration), "k:", label="a3(t)")
    ax2.set_ylabel("a3 [g]")
    ax.legend(fontsize=8, loc="upper left")
    ax2.legend(fontsize=8, loc="upper right")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    aj.save_figure_atomic(fig, out_dir / "limits_along_profile.png")
    plt.close(fig)
    figures.append(
        {
            "file": "limits_along_profile.png",
            "caption": "Cyclone-4: admissible coefficient (whole budget to one coefficient) at each instant of the approximated flight profile (dotted, right axis); the worst instant sets the limit. Vibration assumed constant over the flight.",
        }
    )

    # 5. Joint region (k3, k5) and the AKS-05 batch.
    sens = sensitivities(sc.environment, sc.mean_acceleration)
    s3, s5 = abs(float(sens.k3)), abs(float(sens.k5))
    d = float(sc.admissible_error)
    th = np.linspace(0, 2 * np.pi, 200)
    fig, ax = plt.subplots(figsize=(6, 5))
    ax.plot(d / s3 * np.cos(th) / PPM, d / s5 * np.sin(th) / PPM, label="RMS region (k3, k5 alone)")
    ax.plot(
        np.array([1, 0, -1, 0, 1]) * d / s3 / PPM,
        np.array([0, 1, 0, -1, 0]) * d / s5 / PPM,
        label="worst-case (coherent) region",
    )
    pl = r["tolerance_limits"]["cyclone4"]["coefficients"]
    bx, by = pl["k3"]["ours_paper_method"], pl["k5"]["ours_paper_method"]
    ax.plot([-bx, bx, bx, -bx, -bx], [-by, -by, by, by, -by], "k--", label="paper-method box")
    ax.scatter(
        samples["k3"] / PPM, samples["k5"] / PPM, s=3, alpha=0.3, label="AKS-05 batch (sampled)"
    )
    ax.set_xlabel("k3 [ppm/g²]")
    ax.set_ylabel("k5 [ppm/g⁴]")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    aj.save_figure_atomic(fig, out_dir / "joint_region.png")
    plt.close(fig)
    figures.append(
        {
            "file": "joint_region.png",
            "caption": "Cyclone-4 at a3 = 2 g: joint admissible region of (k3, k5) with the other coefficients at 0 — RMS criterion (ellipse) and sign-coherent worst case (diamond) from the exact sensitivities — against the paper-method box and the sampled AKS-05 batch.",
        }
    )

    # 6. Yield histogram.
    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    ax.hist(samples["at_mean"] / PPM, bins=60, alpha=0.7, label="at mean a3 = 2 g")
    ax.hist(samples["worst"] / PPM, bins=60, alpha=0.5, label="worst |δ_V| over the profile")
    ax.axvline(d / PPM, color="r", ls="--", label="δ* = 500 ppm")
    ax.axvline(-d / PPM, color="r", ls="--")
    ax.set_xlabel("vibration error δ_V [ppm of g]")
    ax.set_ylabel("units")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    aj.save_figure_atomic(fig, out_dir / "yield.png")
    plt.close(fig)
    figures.append(
        {
            "file": "yield.png",
            "caption": f"Monte Carlo production batch (|coefficient| uniform in the AKS-05 ranges of Table 2, random signs) in the Cyclone-4 environment: yield {r['yield']['yield_exact_at_mean_a3']:.3f} at 2 g, {r['yield']['yield_exact_worst_over_profile']:.3f} over the whole profile.",
        }
    )

    # 7. Table 5.
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for ax, name in zip(axes, ("AKS-05", "AL-1M"), strict=True):
        t = r["table5_compensation"][name]
        steps = ["â(1)", "â(2)", "â(3)"]
        x = np.arange(3)
        ax.bar(x - 0.27, t["paper_measured_residual_ppm"], 0.27, label="paper, measured")
        ax.bar(
            x,
            t["paper_algorithm_on_measured_residual_ppm"],
            0.27,
            label="our (17)-(19) on measured â(1)",
        )
        m = t["model_predicted_residual_ppm"]
        ax.bar(
            x + 0.27,
            [m["no_compensation"], m["after_basic"], m["after_paper_19"]],
            0.27,
            label="passport model predicts",
        )
        ax.set_xticks(x, steps)
        ax.set_ylabel("residual error â − 1 g [ppm of g]")
        ax.set_title(name)
        ax.grid(alpha=0.3, axis="y")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    aj.save_figure_atomic(fig, out_dir / "table5_compensation.png")
    plt.close(fig)
    figures.append(
        {
            "file": "table5_compensation.png",
            "caption": "Table 5: residual error at 1 g under a 2 g, 30 Hz sinusoid — measured (paper), the paper's algorithm applied by us to the measured first estimate, and what the Table 4 passport model predicts for the measurement.",
        }
    )

    if "plans" in r["coefficient_fitting"]:
        figures.extend(_fit_figure(out_dir, r["coefficient_fitting"]))
    return figures


def _fit_figure(out_dir, fit) -> list:
    names = ["bias", "scale_factor_error", "asymmetry", "k2", "k3", "k4", "k5"]
    labels = [
        "a0 [µg]",
        "δ [ppm]",
        "A1 [ppm]",
        "k2 [ppm/g]",
        "k3 [ppm/g²]",
        "k4 [ppm/g³]",
        "k5 [ppm/g⁴]",
    ]
    fig, ax = plt.subplots(figsize=(10, 4.5))
    x = np.arange(len(names))
    plans = fit["plans"]
    w = 0.8 / len(plans)
    for i, (pname, p) in enumerate(plans.items()):
        se = np.array(
            [
                1e6 if p["standard_error_ppm"][n] is None else p["standard_error_ppm"][n]
                for n in names
            ],
            float,
        )
        ax.bar(x + (i - len(plans) / 2 + 0.5) * w, se, w, label=f"{pname} ({p['rows']} rows)")
    ax.plot(
        x, [fit["target_standard_error_ppm"][n] for n in names], "k_", ms=20, mew=2, label="target"
    )
    ax.set_yscale("log")
    ax.set_xticks(x, labels, rotation=20)
    ax.set_ylabel("standard error [ppm units]; 1e6 = not identifiable")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3, axis="y")
    fig.tight_layout()
    aj.save_figure_atomic(fig, out_dir / "identifiability.png")
    plt.close(fig)
    return [
        {
            "file": "identifiability.png",
            "caption": f"Standard errors of the fitted coefficients (output noise {fit['noise_g_per_test']:.0e} g per test) for several test plans; bars at 1e6 mark coefficients the plan cannot identify. Target: a tenth of the Cyclone-4 paper-method limits.",
        }
    ]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("out") / STUDY)
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args(argv)
    result = run(args.out, quick=args.quick)
    for row in result["summary"]:
        print(f"{row['quantity']}: {row['ours']} (paper {row['paper']})")
    print(f"written: {args.out / 'result.json'}")


if __name__ == "__main__":
    jax.config.update("jax_enable_x64", True)  # the study's own choice, see docstring
    main()
