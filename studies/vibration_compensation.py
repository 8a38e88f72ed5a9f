"""Study: vibration error of a navigation accelerometer, its shaker test and its in-flight
compensation (docs/models.md §3, eqs. 1-5, 16-20, Tables 3-5).

For the two passport units of Table 4 (AKS-05, AL-1M) under the Table 5 condition (1 g
along the input axis, a 2 g sinusoid at 30 Hz): the basic error (2), the vibration error
by the exact expectation and by the paper's closed form (19), and the residual after the
compensation algorithm (17)-(20) with each form, beside the measured Table 5. Also: the
exact expectation against the closed forms (3)-(5), (19), (20) and a vmapped time-domain
Monte Carlo; the shaker estimator (16) with its axis-stability check against Table 3; and
gradient-based coefficient fitting from test tables (identifiability, a minimal test plan,
simulate → fit → recover).

Writes OUT/result.json and PNG figures. Run: `python studies/vibration_compensation.py
[--out DIR] [--quick]`. float64 throughout (run() enables it): vibration errors are
ppm-level differences of O(1 g) numbers.
"""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import jax

# Run as a script: float64 before the module's constants are built, as in the report's
# workers (imported by the report, this changes nothing: the report chose already).
if __name__ == "__main__":
    jax.config.update("jax_enable_x64", True)

import equinox as eqx
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
from accel_jax.report import (  # noqa: E402
    Figures,
    provenance,
    study_main,
    study_run,
    write_json_atomic,
)
from accel_jax.vibration import (  # noqa: E402
    AKS05_RANGES_PPM,
    BandSpectrum,
    VibrationEnvironment,
    compensate_in_flight,
    cyclone4,
    design_matrix,
    fit_coefficients,
    identifiability,
    mean_abs_input,
    paper_deterministic_error,
    paper_limits,
    paper_vibration_error,
    predict_table,
    sample_batch,
    shaker_vibration_error,
    tactical_missile,
    time_domain_vibration_error,
    vibration_error,
)

STUDY = "vibration_compensation"

# --- the paper's published numbers ------------------------------------------------------
TABLE3_1E4G = [2.2, 1.8, 0.5, 1.0, 0.6, 1.2, 2.0, 2.5, 0.7, 0.2, 2.0, 2.3]
TABLE5 = {  # â(1), â(2), â(3) [g], measured at 1 g with a 2 g, 30 Hz sinusoid on IA
    "AKS-05": [1.000100, 1.000083, 1.000006],
    "AL-1M": [1.001303, 1.001088, 1.000110],
}
TABLE5_STEPS = ("no compensation", "after basic-error compensation", "after vibration compensation")
UNITS = aj.PASSPORTS  # the paper's two accelerometers, Table 4

# --- our assumptions ---------------------------------------------------------------------
TABLE5_A3 = 1.0  # g along IA (the shaker table's gravity)
TABLE5_ENV = dict(sine_amplitude=(0.0, 0.0, 2.0), sine_frequency=30.0)
SHAKER_SIGMA = 1.4  # g, the Table 1 level the paper's shaker reproduces (its printed value)
SHAKER_K1 = 1.0  # V/g (the estimator divides it out)
SHAKER_NOISE = 2e-6  # g per sample of the output record (white)
SHAKER_DRIFT = 2e-7  # g/min random bias drift rate (std), linear over the 15-min test
MC_RECORD_S = 1.0  # s, time-domain Monte Carlo record
MC_RATE = 4000.0  # Hz
FIT_NOISE = 1e-6  # g, standard deviation of one test's mean output (5-min average)
FIT_TRUTH_PPM = dict(bias_mg=0.5, scale_factor_error=50, asymmetry=15, k2=2, k3=7, k4=0.02, k5=0.3)
"""The coefficient fit's truth: the AKS-05 passport + a 50 ppm scale-factor error. Built
inside `run` (float64), not at import: a JAX array made at import starts JAX's backend
before the script's XLA options and `--device` can be set."""


def _ppm(x) -> float:
    return float(x) / PPM


def _table5_env() -> VibrationEnvironment:
    return VibrationEnvironment(**TABLE5_ENV)


# --- vibration error: exact vs closed form vs Monte Carlo ---------------------------------


def _mc_one(tf, env, a3, ts, key):
    return time_domain_vibration_error(tf, env, a3, 0.0, 0.0, ts, key=key)


def _mc(tf, env, a3, key, n):
    ts = jnp.arange(int(MC_RECORD_S * MC_RATE)) / MC_RATE
    keys = jax.random.split(key, n)
    a3 = jnp.asarray(a3, dtype=jnp.float64)
    vals = np.asarray(aj.sweep(_mc_one, tf, env, a3, ts, keys, in_axes=(None, None, None, None, 0)))
    return float(vals.mean()), float(vals.std(ddof=1) / math.sqrt(n))


_exact_batch = eqx.filter_jit(jax.vmap(vibration_error, in_axes=(None, None, 0)))


@eqx.filter_jit
def _errors(tf, env, a3):
    # One compiled kernel for every case (same pytree structure): exact expectation and the
    # paper's closed forms, for the whole unit and for its A1 term alone.
    a1_only = StaticTransferFunction(asymmetry=tf.asymmetry)
    return {
        "exact": vibration_error(tf, env, a3),
        "paper": paper_vibration_error(tf, env, a3),
        "a1_exact": vibration_error(a1_only, env, a3),
        "a1_paper": paper_vibration_error(a1_only, env, a3),
    }


def vibration_comparison(key, quick: bool) -> dict:
    n = 16 if quick else 256
    aks, al = StaticTransferFunction.aks05(), StaticTransferFunction.al1m()
    aks_m = eqx.tree_at(lambda t: (t.m31, t.m32), aks, (jnp.asarray(3 * PPM), jnp.asarray(3 * PPM)))
    cyc, mis = cyclone4(), tactical_missile("long")
    band = dict(random_band=(20.0, 640.0))
    cases = {
        "AKS-05, 1 g, sine 2 g (Table 5)": (aks, VibrationEnvironment(**TABLE5_ENV, **band), 1.0),
        "AL-1M, 1 g, sine 2 g (Table 5)": (al, VibrationEnvironment(**TABLE5_ENV, **band), 1.0),
        "AKS-05, 1 g, random 1.4 g (Table 3 shaker)": (
            aks,
            VibrationEnvironment(random_std=(0, 0, SHAKER_SIGMA), **band),
            1.0,
        ),
        "AKS-05 (m = 3 ppm/g), Cyclone-4 flight at 2 g": (aks_m, cyc.environment, 2.0),
        "AKS-05 (m = 3 ppm/g), missile (long) at 2.2 g": (aks_m, mis.environment, 2.2),
    }
    keys = jax.random.split(key, len(cases))
    rows = {}
    for k, (label, (tf, env, a)) in zip(keys, cases.items(), strict=True):
        a = jnp.asarray(a, dtype=jnp.float64)
        err = {key: _ppm(v) for key, v in _errors(tf, env, a).items()}
        mc, se = _mc(tf, env, a, k, n)
        rows[label] = {
            "exact_ppm": err["exact"],
            "paper_closed_form_ppm": err["paper"],
            "monte_carlo_ppm": mc / PPM,
            "monte_carlo_standard_error_ppm": se / PPM,
            "monte_carlo_z": (mc / PPM - err["exact"]) / (se / PPM),
            "A1_term_exact_ppm": err["a1_exact"],
            "A1_term_paper_ppm": err["a1_paper"],
            "difference_paper_minus_exact_ppm": err["paper"] - err["exact"],
        }
    return {
        "cases": rows,
        "monte_carlo": {
            "records": n,
            "record_s": MC_RECORD_S,
            "sample_rate_Hz": MC_RATE,
            "synthesis": "sinusoid with a random start + 64-tone Gaussian spectral synthesis "
            "on the record's Fourier grid; the time average of a_F(a + v(t)) − a_F(a) per "
            "record, vmapped over records",
        },
        "where_they_differ": (
            "Polynomial terms: the paper's (19), (20) equal the exact expectation for a pure "
            "sinusoid or pure Gaussian vibration (k5's quartic factor printed 1.185 in (19) is "
            "1.875 in (5) and exactly); combined sine + random, the paper's sum omits the cross "
            "moment 3b²σ² in E w⁴ (k4, k5 terms). The A1 term differs everywhere: exactly, "
            "½A1(E|a+v| − |a|) is 0 unless the vibration crosses zero and is never negative, "
            "whereas the paper's A1(0.673 b − 0.5 a) + 0.125 A1 σ has the wrong limits (negative "
            "for a > 1.35 b, 0.673 b where the exact value at a = 0 is b/π = 0.318 b)."
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


# --- Table 5: basic error, vibration error, compensation ---------------------------------


@eqx.filter_jit
def _table5_kernel(tf, env, a3, measured_first):
    """Everything Table 5 needs for one unit, in one compiled kernel [g]."""
    # (a) The algorithm (17)-(20) applied by us to the paper's measured â(1): Û/K1 is
    # â(1) + a0 (step (17) removes a0 again; δ = 0 in the passport).
    indicated_measured = measured_first + tf.bias
    paper_form = compensate_in_flight(tf, indicated_measured, env, method="paper")
    printed_k5 = compensate_in_flight(tf, indicated_measured, env, method="paper", k5_quartic=1.185)
    exact_form = compensate_in_flight(tf, indicated_measured, env, method="exact")
    # (b) The passport model's prediction of the measurement: the unit at exactly a3.
    exact_err = vibration_error(tf, env, a3)
    indicated_model = indicated_acceleration(tf, a3) + exact_err
    model_paper = compensate_in_flight(tf, indicated_model, env, method="paper")
    model_exact = compensate_in_flight(tf, indicated_model, env, method="exact")
    a1_only = StaticTransferFunction(asymmetry=tf.asymmetry)
    return {
        "basic": basic_error(tf, a3, include_bias=False),
        "exact": exact_err,
        "paper": paper_deterministic_error(tf, env, a3),
        "paper_printed": paper_deterministic_error(tf, env, a3, k5_quartic=1.185),
        "a1_paper": paper_deterministic_error(a1_only, env, a3),
        "a1_exact": vibration_error(a1_only, env, a3),
        "paper_form": paper_form,
        "printed_k5": printed_k5,
        "exact_form": exact_form,
        "model_paper": model_paper,
        "model_exact": model_exact,
    }


def table5() -> tuple[dict, str]:
    env = _table5_env()
    a = jnp.asarray(TABLE5_A3)
    out = {}
    for name, preset in UNITS.items():
        tf = preset()
        measured = TABLE5[name]
        k = _table5_kernel(tf, env, a, jnp.asarray(measured[0]))
        paper_form, printed_k5, exact_form = k["paper_form"], k["printed_k5"], k["exact_form"]
        model_paper, model_exact = k["model_paper"], k["model_exact"]

        def res(x):
            return (float(x) - TABLE5_A3) / PPM

        out[name] = {
            "basic_error_ppm": _ppm(k["basic"]),
            "vibration_error_exact_ppm": _ppm(k["exact"]),
            "vibration_error_paper_ppm": _ppm(k["paper"]),
            "vibration_error_paper_printed_k5_1_185_ppm": _ppm(k["paper_printed"]),
            "table5_measured": {
                "steps": list(TABLE5_STEPS),
                "a_hat_g": measured,
                "residual_ppm": [res(v) for v in measured],
            },
            "residual_after_compensation_ppm": {
                "paper": res(paper_form.after_deterministic),
                "exact": res(exact_form.after_deterministic),
                "paper_printed_k5_1_185": res(printed_k5.after_deterministic),
            },
            "residual_after_basic_compensation_ppm": res(paper_form.after_basic),
            "removed_by_vibration_compensation_ppm": {
                "paper": (float(paper_form.after_basic) - float(paper_form.after_deterministic))
                / PPM,
                "exact": (float(exact_form.after_basic) - float(exact_form.after_deterministic))
                / PPM,
                "paper_table5": (measured[1] - measured[2]) / PPM,
            },
            "model_predicted_residual_ppm": {
                "no_compensation": res(model_paper.first),
                "after_basic": res(model_paper.after_basic),
                "after_paper": res(model_paper.after_deterministic),
                "after_exact": res(model_exact.after_deterministic),
            },
            "A1_term_paper_ppm": _ppm(k["a1_paper"]),
            "A1_term_exact_ppm": _ppm(k["a1_exact"]),
        }
    aks, al = out["AKS-05"], out["AL-1M"]
    removed = {n: out[n]["removed_by_vibration_compensation_ppm"] for n in out}
    first_step_al = (
        al["table5_measured"]["residual_ppm"][0] - al["residual_after_basic_compensation_ppm"]
    )
    gaps = {
        n: out[n]["residual_after_basic_compensation_ppm"] - out[n]["vibration_error_exact_ppm"]
        for n in out
    }
    explanation = (
        f"Basic error (2) at 1 g from Table 4 (a0 excluded, removed in (17)): "
        f"{aks['basic_error_ppm']:.1f} / {al['basic_error_ppm']:.1f} ppm (AKS-05 / AL-1M), "
        "the paper's first step (17 / 215 ppm). Step (18) on the measured â(1) removes "
        f"{first_step_al:.1f} ppm for AL-1M: the paper evaluated δ_OP at 1 g rather than at "
        "â(1) = 1.0013 g. Step (19) removes "
        f"{removed['AKS-05']['paper']:.1f} / {removed['AL-1M']['paper']:.1f} ppm against the "
        f"paper's {removed['AKS-05']['paper_table5']:.0f} / "
        f"{removed['AL-1M']['paper_table5']:.0f}: AL-1M reproduces to "
        f"{abs(removed['AL-1M']['paper'] - removed['AL-1M']['paper_table5']):.1f} ppm, AKS-05 to "
        f"{abs(removed['AKS-05']['paper'] - removed['AKS-05']['paper_table5']):.1f} ppm (the "
        "printed k5 factor 1.185 moves it further away). The exact expectation of the "
        f"passport model gives {aks['vibration_error_exact_ppm']:.1f} / "
        f"{al['vibration_error_exact_ppm']:.1f} ppm of vibration error, {gaps['AKS-05']:.0f} / "
        f"{gaps['AL-1M']:.0f} ppm less than the measurement shows after basic compensation. The "
        f"paper's A1 term ({aks['A1_term_paper_ppm']:.1f} / {al['A1_term_paper_ppm']:.1f} ppm "
        f"against the exact {aks['A1_term_exact_ppm']:.1f} / {al['A1_term_exact_ppm']:.1f} ppm; "
        "the polynomial terms of (19) are exact for a pure sinusoid) absorbs part of that gap, "
        "so on these two measurements the paper's form leaves a smaller residual than the "
        "exact expectation does. What remains (6 / 110 ppm in the paper) is not explained by "
        "the Table 4 passport model: candidates are coefficients that drifted since the "
        "passport, δ(ω) or a frequency-dependent nonlinearity at 30 Hz, and cross-axis shaker "
        "motion."
    )
    return out, explanation


# --- Table 3: shaker test ----------------------------------------------------------------


def _shaker_one(tf, key, env):
    n_samples = 3000
    # One draw for the three records' noise and the drift rate (one random kernel to compile).
    z = jax.random.normal(key, (3 * n_samples + 1,))
    noise = SHAKER_NOISE * z[:-1].reshape(3, n_samples)
    drift = SHAKER_DRIFT * z[-1] / 60.0  # g/s
    t = jnp.arange(n_samples) * (300.0 / n_samples)
    true_err = vibration_error(tf, env, 1.0, n_phase=128)
    base = indicated_acceleration(tf, 1.0)
    u1 = SHAKER_K1 * (base + drift * t + noise[0])
    u2 = SHAKER_K1 * (base + true_err + drift * (t + 300) + noise[1])
    u3 = SHAKER_K1 * (base + drift * (t + 600) + noise[2])
    est = shaker_vibration_error(u1, u2, u3, SHAKER_K1)
    return est.vibration_error, true_err, est.axis_shift, est.valid


def _table3_at(key, quick: bool, sigma: float) -> dict:
    env = VibrationEnvironment(random_std=(0, 0, sigma), random_band=(20.0, 640.0))
    n_units = 64 if quick else 2000
    k_units, k_tests = jax.random.split(key)
    batch = sample_batch(
        k_units, n_units, {k: v for k, v in AKS05_RANGES_PPM.items() if k not in ("m31", "m32")}
    )
    keys = jax.random.split(k_tests, n_units)
    est, truth, shift, valid = (
        np.asarray(x) for x in aj.sweep(_shaker_one, batch, keys, env, in_axes=(0, 0, None))
    )
    paper = np.asarray(TABLE3_1E4G) * 1e-4
    ours_abs = np.abs(est)
    return {
        "sigma_g": sigma,
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
        "_abs_1e-4g": ours_abs / 1e-4,
    }


def table3(key, quick: bool) -> dict:
    sigma_additive = float(BandSpectrum.cyclone4().rms(paper=False))
    paper_level = _table3_at(key, quick, SHAKER_SIGMA)
    additive = _table3_at(key, quick, sigma_additive)
    aks = StaticTransferFunction.aks05()
    paper = np.asarray(TABLE3_1E4G)
    out = {
        "paper_1e-4g": TABLE3_1E4G,
        "paper_mean_1e-4g": float(paper.mean()),
        "paper_max_1e-4g": float(paper.max()),
        "at_paper_sigma": paper_level,
        "at_variance_additive_sigma": additive,
        "aks05_passport_exact_1e-4g": {
            f"sigma_{sig:.2f}_g": float(
                _errors(aks, VibrationEnvironment(random_std=(0, 0, sig)), jnp.asarray(1.0))[
                    "exact"
                ]
            )
            / 1e-4
            for sig in (SHAKER_SIGMA, sigma_additive)
        },
    }
    out["explanation"] = (
        "Units drawn uniformly inside Table 2's AKS-05 ranges (random signs), random vibration "
        "on IA at 1 g, shaker records 3 × 5 min with white noise and a random linear drift, "
        "estimated by (16). The estimator is accurate (RMS error "
        f"{paper_level['estimator_error_rms_1e-4g']:.4f}e-4 g) and the axis check passes in "
        f"{paper_level['axis_check_pass_fraction']:.0%} of the runs, so the comparison tests the "
        f"coefficient model. With the paper's σ = {SHAKER_SIGMA} g the exact expectation predicts "
        f"mean |δ_V| = {paper_level['ours_mean_abs_1e-4g']:.2f}e-4 g against the measured "
        f"{out['paper_mean_1e-4g']:.2f}e-4 g (the passport AKS-05, all coefficients positive: "
        f"{out['aks05_passport_exact_1e-4g'][f'sigma_{SHAKER_SIGMA:.2f}_g']:.2f}e-4 g). With "
        f"the Table 1 spectrum summed without the 1/n (σ = {sigma_additive:.2f} g) the mean is "
        f"{additive['ours_mean_abs_1e-4g']:.2f}e-4 g, the measured scale. Random coefficient "
        "signs make our spread wider toward zero than the measured one, which suggests "
        "like-signed coefficients."
    )
    return out


# --- coefficient fitting -------------------------------------------------------------------


def _plan(a, b, s=0.0) -> dict:
    a, b, s = (np.asarray(x, float).ravel() for x in np.broadcast_arrays(a, b, s))
    return {
        "a_in": a,
        "vib_amp": b,
        "vib_freq": np.full_like(a, 30.0),
        "vib_rms": s,
        "a_out": np.zeros_like(a),
    }


def _greedy_plan(grid: dict, J: np.ndarray, target_se: np.ndarray, max_rows: int = 30):
    """The grid's rows chosen by `aj.vibration.greedy_test_plan` (greedy D-optimal), as a table."""
    chosen, history = aj.vibration.greedy_test_plan(J, target_se, max_rows=max_rows)
    return {k: v[chosen] for k, v in grid.items()}, history


def coefficient_fitting(key, quick: bool) -> dict:
    tilt = np.cos(np.linspace(0, np.pi, 12))
    A, B = np.meshgrid([-1.0, 1.0], [0.0, 2.0, 4.0])
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
    # Candidate rows: a_in ∈ {−1, −½, 0, ½, 1} g (tilt in gravity) × sine {0, 1, 2, 3, 4} g.
    GA, GB = np.meshgrid([-1.0, -0.5, 0.0, 0.5, 1.0], [0.0, 1.0, 2.0, 3.0, 4.0])
    grid = _plan(GA, GB)
    J = np.asarray(design_matrix(grid)) / FIT_NOISE
    minimal, history = _greedy_plan(grid, J, np.asarray(list(target_ppm.values())))
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
            "meets_target": bool(
                np.all(np.isfinite(np.asarray(idf.standard_error_ppm)))
                and np.all(
                    np.asarray(idf.standard_error_ppm) <= np.asarray(list(target_ppm.values()))
                )
            ),
        }
    # Simulate → fit → recover on the recommended plan.
    n_rep = 4 if quick else 64
    fit_truth = StaticTransferFunction.from_ppm(**FIT_TRUTH_PPM)
    truth = fit_truth.as_ppm()
    truth = {"bias": truth["bias_mg"] * 1e3, **{k: v for k, v in truth.items() if k != "bias_mg"}}
    clean = np.asarray(predict_table(fit_truth, minimal))
    rng = np.random.default_rng(int(jax.random.randint(key, (), 0, 2**31 - 1)))
    estimates, ses = [], []
    last = None
    for _ in range(n_rep):
        plan = dict(minimal, a_out=clean + FIT_NOISE * rng.normal(size=clean.size))
        last = fit_coefficients(plan, noise=FIT_NOISE)
        estimates.append(np.asarray(last.estimate_ppm))
        ses.append(np.asarray(last.standard_error_ppm))
    names = last.names
    true_vec = np.array([truth[n] for n in names])
    estimates, ses = np.asarray(estimates), np.asarray(ses)
    z = (estimates - true_vec) / ses
    return {
        "noise_g_per_test": FIT_NOISE,
        "truth_ppm": dict(zip(names, true_vec, strict=True)),
        "target_standard_error_ppm": target_ppm,
        "plans": out_plans,
        "greedy_history": history,
        "recommended_rows": int(minimal["a_in"].size),
        "recommended_plan": {"a_in_g": minimal["a_in"], "vib_amp_g": minimal["vib_amp"]},
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
            "and the bias coincide): k3·a³ is indistinguishable from the scale factor. "
            "Intermediate inputs (tilt) separate the polynomial terms but leave k4, k5 poorly "
            "determined within |a| ≤ 1 g; vibration levels separate them through the moments "
            "E[(a+w)ⁿ] (k3 via 3a·b²/2, k4 via 3b⁴/8, k5 via 5a·3b⁴/8). The recommended plan "
            "mixes tilt positions and shaker levels."
        ),
    }


# --- run ---------------------------------------------------------------------------------


# A quick run is compile-bound throughout and compiles with most XLA optimisations off
# (study_run(compile_bound_when_quick=True); measured on the 2-core CPU, quick, cache off: ~150 programs, most
# run once: 11 → 7.6 CPU-s).
@study_run(compile_bound_when_quick=True)
def run(out_dir: Path, *, quick: bool = False, seed: int = 20261122) -> dict:
    """Run the study; write OUT/result.json and figures; return the result dict."""
    out_dir = Path(out_dir)
    started = time.perf_counter()
    k_mc, k_t3, k_fit = jax.random.split(jax.random.key(seed), 3)

    units, t5_explanation = table5()
    vib = vibration_comparison(k_mc, quick)
    t3 = table3(k_t3, quick)
    fit = coefficient_fitting(k_fit, quick)
    shaker_samples = {
        "paper σ": t3["at_paper_sigma"].pop("_abs_1e-4g"),
        "variance-additive σ": t3["at_variance_additive_sigma"].pop("_abs_1e-4g"),
    }
    for name in units:
        case = vib["cases"][f"{name}, 1 g, sine 2 g (Table 5)"]
        units[name]["vibration_error_monte_carlo_ppm"] = case["monte_carlo_ppm"]
        units[name]["vibration_error_monte_carlo_standard_error_ppm"] = case[
            "monte_carlo_standard_error_ppm"
        ]

    result = {
        "title": "Vibration error, shaker test, in-flight compensation and coefficient "
        "fitting (the vibration-error paper, Tables 3-5)",
        **units,
        "table5_explanation": t5_explanation,
        "vibration_error": vib,
        "asymmetry_term": asymmetry_curve(),
        "table3_shaker": t3,
        "coefficient_fitting": fit,
        "assumptions": {
            "precision": "float64",
            "units": "g for accelerations; errors and residuals in ppm of g (1e-6 g); "
            "coefficients in ppm units (A1 ppm, k_n ppm/g^(n-1), m ppm/g)",
            "table5_condition": "a3 = 1 g along IA; sinusoid 2 g at 30 Hz along IA only (no "
            "cross-axis vibration, no random vibration); Table 4 passport coefficients (δ, m "
            "not given: 0)",
            "basic_error": "eq. (2) at 1 g without a0 (a0 is removed by step (17))",
            "vibration_error_paper": "eq. (19) at a = 1 g with k5's quartic factor 1.875 "
            "(as (5) and the exact average); the printed 1.185 is reported beside it",
            "residual_after_compensation": "the algorithm (17)-(19) applied by us to the "
            "paper's measured â(1) (Û/K1 = â(1) + a0), subtracting the vibration error by the "
            "paper's form (19) or by the exact expectation, both evaluated at â(1) as the "
            "paper does; 'model_predicted' applies it to the passport model's own output",
            "shaker": f"σ = {SHAKER_SIGMA} g on IA at 1 g (the paper's value) and the "
            "variance-additive σ of Table 1; output noise "
            f"{SHAKER_NOISE} g per sample, 3000 samples per 5-min record, bias drift "
            f"{SHAKER_DRIFT} g/min (std, linear); K1 = {SHAKER_K1} V/g",
            "monte_carlo": f"{MC_RECORD_S} s records at {MC_RATE:.0f} Hz",
            "fitting": f"output noise {FIT_NOISE} g per test row; truth = AKS-05 passport + "
            "50 ppm scale-factor error; candidate rows a_in ∈ {−1, −½, 0, ½, 1} g × sine "
            "{0, 1, 2, 3, 4} g at 30 Hz",
        },
        "provenance": provenance(seeds={"root": seed}, precision="float64", extra={"quick": quick}),
    }
    result["summary"] = _summary(result)
    result["figures"] = make_figures(out_dir, result, shaker_samples)
    result["provenance"]["wall_time_s"] = time.perf_counter() - started
    write_json_atomic(out_dir / "result.json", result)
    return result


def _closed_form_explanation(exact, closed_form, paper, monte_carlo, standard_error) -> dict:
    """The report's explanation of a gap between our exact δ_V and the paper's number: given
    only when the paper's closed form, evaluated by us, reproduces the paper's number (within
    5 %) and the time-domain Monte Carlo confirms the exact value (within 3 standard errors
    or 0.5 %): the gap is then the closed form's approximation, shown, not assumed."""
    form_reproduces = abs(closed_form - paper) <= 0.05 * abs(paper)
    confirmed = abs(monte_carlo - exact) <= max(3 * standard_error, 0.005 * abs(exact))
    if not (form_reproduces and confirmed):
        return {}
    return {
        "explanation": f"the paper's closed form gives {closed_form:.4g} ppm (evaluated by us); "
        f"the exact expectation {exact:.4g} ppm is confirmed by a time-domain Monte Carlo "
        f"({monte_carlo:.4g} ± {standard_error:.2g} ppm): the closed form's approximation"
    }


def _summary(r) -> list:
    rows = []
    for name in UNITS:
        u = r[name]
        rows += [
            {
                "quantity": f"{name}: basic error (2) at 1 g [ppm]",
                "ours": round(u["basic_error_ppm"], 2),
                "paper": round(
                    u["table5_measured"]["residual_ppm"][0]
                    - u["table5_measured"]["residual_ppm"][1],
                    1,
                ),
                "note": "paper: the drop from 'no compensation' to 'after basic' in Table 5",
            },
            {
                "quantity": f"{name}: vibration error, 2 g at 30 Hz, 1 g [ppm]",
                "ours": round(u["vibration_error_exact_ppm"], 2),
                "paper": round(u["removed_by_vibration_compensation_ppm"]["paper_table5"], 1),
                **_closed_form_explanation(
                    u["vibration_error_exact_ppm"],
                    u["vibration_error_paper_ppm"],
                    u["removed_by_vibration_compensation_ppm"]["paper_table5"],
                    u["vibration_error_monte_carlo_ppm"],
                    u["vibration_error_monte_carlo_standard_error_ppm"],
                ),
                "note": f"exact expectation; paper's (19) evaluated by us "
                f"{u['vibration_error_paper_ppm']:.2f}; Monte Carlo "
                f"{u['vibration_error_monte_carlo_ppm']:.2f} ± "
                f"{u['vibration_error_monte_carlo_standard_error_ppm']:.2f}; paper column = "
                "what Table 5's vibration step removed",
            },
        ]
        measured = u["table5_measured"]["residual_ppm"]
        res = u["residual_after_compensation_ppm"]
        rows += [
            {
                "quantity": f"Table 5 {name}: residual after basic compensation [ppm]",
                "ours": round(u["residual_after_basic_compensation_ppm"], 2),
                "paper": round(measured[1], 2),
                "note": "(17), (18) applied by us to the measured â(1)",
            },
            {
                "quantity": f"Table 5 {name}: residual after vibration compensation [ppm]",
                "ours": round(res["paper"], 2),
                "paper": round(measured[2], 2),
                "note": f"paper's form (19); exact form {res['exact']:.1f}; printed k5 factor "
                f"{res['paper_printed_k5_1_185']:.1f}; the passport model predicts "
                + ", ".join(f"{k} {v:.1f}" for k, v in u["model_predicted_residual_ppm"].items()),
            },
        ]
    t3 = r["table3_shaker"]
    rows.append(
        {
            "quantity": "Table 3 mean |δ̂_V| [1e-4 g]",
            "ours": round(t3["at_paper_sigma"]["ours_mean_abs_1e-4g"], 3),
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
                **_closed_form_explanation(
                    case["exact_ppm"],
                    case["paper_closed_form_ppm"],
                    case["paper_closed_form_ppm"],
                    case["monte_carlo_ppm"],
                    case["monte_carlo_standard_error_ppm"],
                ),
                "note": "paper column = the paper's closed forms evaluated by us; Monte Carlo "
                f"{case['monte_carlo_ppm']:.2f} ± {case['monte_carlo_standard_error_ppm']:.2f}",
            }
        )
    fit = r["coefficient_fitting"]
    rows.append(
        {
            "quantity": "coefficient fitting: rows of the recommended test plan",
            "ours": fit["recommended_rows"],
            "paper": "",
            "note": f"simulate → fit → recover over {fit['recovery']['fits']} fits: max |z| "
            f"{fit['recovery']['max_abs_z']:.2f}; " + fit["findings"],
        }
    )
    return rows


# --- figures -----------------------------------------------------------------------------


def make_figures(out_dir, r, shaker_samples) -> list:
    out_dir.mkdir(parents=True, exist_ok=True)
    figures = Figures(out_dir)
    save = figures.save

    # 1. Table 5.
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for ax, name in zip(axes, UNITS, strict=True):
        u = r[name]
        x = np.arange(3)
        measured = u["table5_measured"]["residual_ppm"]
        on_measured = [
            measured[0],
            u["residual_after_basic_compensation_ppm"],
            u["residual_after_compensation_ppm"]["paper"],
        ]
        containers = []
        containers.append(ax.bar(x - 0.3, measured, 0.2, label="paper, measured"))
        containers.append(
            ax.bar(x - 0.1, on_measured, 0.2, label="our (17)-(19), paper's form, on measured â(1)")
        )
        containers.append(
            ax.bar(
                [2 + 0.1],
                [u["residual_after_compensation_ppm"]["exact"]],
                0.2,
                label="our (17)-(18) + exact expectation, on measured â(1)",
            )
        )
        m = u["model_predicted_residual_ppm"]
        containers.append(
            ax.bar(
                x + 0.3,
                [m["no_compensation"], m["after_basic"], m["after_paper"]],
                0.2,
                label="passport model predicts (paper's form)",
            )
        )
        for bars in containers:  # the values: the symlog axis compresses 6 to 1000 ppm
            values = [p.get_height() for p in bars.patches]
            ax.bar_label(
                bars,
                [f"{v:.0f}" if abs(v) >= 100 else f"{v:.3g}" for v in values],
                fontsize=7,
                rotation=90,
                padding=2,
            )
        ax.set_xticks(x, ["â(1)", "â(2)", "â(3)"])
        ax.set_ylabel("residual error â − 1 g [ppm of g]")
        ax.set_yscale("symlog", linthresh=10)
        low, high = ax.get_ylim()
        ax.set_ylim(low * 3 if low < 0 else low, high * 8)  # room for the labels
        ax.set_title(name)
        ax.grid(alpha=0.3, axis="y")
    axes[0].legend(fontsize=7)
    save(
        fig,
        "table5_compensation.png",
        "Table 5: residual error at 1 g under a 2 g, 30 Hz sinusoid along IA — measured "
        "(paper), the compensation algorithm applied by us to the measured first estimate "
        "with the paper's form (19) and with the exact expectation, and what the Table 4 "
        "passport model predicts for the measurement (δ, m = 0).",
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
    save(
        fig,
        "asymmetry_term.png",
        "Vibration error per unit scale-factor asymmetry A1 under a 2 g sinusoid: exact time "
        "average against the paper's A1(0.673 b − 0.5 a). The exact term vanishes once the "
        "sinusoid no longer crosses zero (a ≥ b); the paper's goes negative.",
    )

    # 3. Vibration error versus input: exact vs paper, sine 2 g.
    env = _table5_env()
    a3 = jnp.linspace(-3, 3, 121)
    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    for (name, preset), c in zip(UNITS.items(), ("tab:blue", "tab:red"), strict=True):
        tf = preset()
        ax.plot(a3, np.asarray(_exact_batch(tf, env, a3)) / PPM, color=c, label=f"{name} exact")
        ax.plot(
            a3,
            np.asarray(paper_deterministic_error(tf, env, a3)) / PPM,
            "--",
            color=c,
            label=f"{name} paper (19)",
        )
        ax.errorbar(
            [1.0],
            [r[name]["vibration_error_monte_carlo_ppm"]],
            yerr=[2 * r[name]["vibration_error_monte_carlo_standard_error_ppm"]],
            fmt="ko",
            ms=4,
        )
    ax.plot([], [], "ko", label="time-domain Monte Carlo ± 2 SE")
    ax.set_yscale("symlog", linthresh=10)
    ax.set_xlabel("input acceleration a3 [g]")
    ax.set_ylabel("vibration error δ_V [ppm of g]")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    save(
        fig,
        "vibration_error_vs_input.png",
        "Vibration error of the Table 4 passport units under a 2 g sinusoid along IA: exact "
        "expectation, the paper's (19), and the time-domain Monte Carlo at 1 g (the Table 5 "
        "condition). m = 0 (not in Table 4).",
    )

    # 4. Table 3: shaker test.
    t3 = r["table3_shaker"]
    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    bins = np.linspace(0, 4, 41)
    for label, values in shaker_samples.items():
        ax.hist(values, bins=bins, density=True, alpha=0.5, label=f"simulated, {label}")
    ax.hist(
        np.asarray(t3["paper_1e-4g"]),
        bins=bins,
        density=True,
        histtype="step",
        lw=2,
        color="k",
        label="Table 3 (12 units)",
    )
    ax.set_xlabel("|δ̂_V| from the shaker estimator (16) [1e-4 g]")
    ax.set_ylabel("density")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    save(
        fig,
        "table3_shaker.png",
        "Shaker test of AKS-05 units: |δ̂_V| by the estimator (16) for simulated units drawn "
        "inside Table 2's AKS-05 ranges (random signs), random vibration on IA at 1 g with the "
        f"paper's σ = {SHAKER_SIGMA} g and with the variance-additive σ of Table 1, against "
        "the 12 measured units of Table 3.",
    )

    # 5. Identifiability of the coefficients per test plan.
    fit = r["coefficient_fitting"]
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
    fig, ax = plt.subplots(figsize=(10, 5.5))
    x = np.arange(len(names))
    plans = fit["plans"]
    w = 0.8 / len(plans)
    missing = []
    for i, (pname, p) in enumerate(plans.items()):
        offset = x + (i - len(plans) / 2 + 0.5) * w
        se = [p["standard_error_ppm"][n] for n in names]
        bars = ax.bar(
            offset,
            [np.nan if v is None else v for v in se],
            w,
            label=f"{pname} ({p['rows']} rows)",
        )
        missing += [
            (o, bars.patches[0].get_facecolor())
            for o, v in zip(offset, se, strict=True)
            if v is None
        ]
    ax.plot(
        x, [fit["target_standard_error_ppm"][n] for n in names], "k_", ms=20, mew=2, label="target"
    )
    ax.set_yscale("log")
    if missing:
        # Not identifiable is a category, not a number: a cross at the top of the axes.
        top = ax.get_ylim()[1]
        ax.set_ylim(top=top * 30)
        for k, (o, color) in enumerate(missing):
            ax.plot(
                o,
                top * 5,
                "x",
                color=color,
                ms=9,
                mew=2,
                label="not identifiable by that plan" if k == 0 else None,
            )
    ax.set_xticks(x, labels, rotation=20)
    ax.set_ylabel("standard error [ppm units]")
    # Below the axes: the unidentifiable bars reach the top of every group.
    ax.legend(fontsize=7, ncol=3, loc="upper center", bbox_to_anchor=(0.5, -0.2))
    ax.grid(alpha=0.3, axis="y")
    save(
        fig,
        "identifiability.png",
        f"Standard errors of the fitted coefficients (output noise {fit['noise_g_per_test']:.0e} "
        "g per test) for several test plans; a cross at the top marks a coefficient the plan "
        "cannot identify. Target: a tenth of the Cyclone-4 paper-method limits.",
    )
    return figures.entries


def main(argv=None) -> int:
    return study_main(run, __file__, __doc__, argv=argv)


if __name__ == "__main__":
    sys.exit(main())
