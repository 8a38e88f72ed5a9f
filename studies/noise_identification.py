"""Study: noise-model identification and the Kalman filter it tunes (docs/models.md §4).

Chernodarov, Patrikeev & Ivanov: a Kalman filter estimating INS errors diverges when the
sensor-noise models it carries are wrong; identify them from the autocorrelation of the
sensor errors — first-order Gauss-Markov by rule (15), exponential-cosine by (19)-(21).

1. Simulated records with known parameters, many runs (vmapped, sharded with
   `accel_jax.sweep`): bias and spread of the paper's rules, of least squares on the
   autocorrelation and of exact maximum likelihood (with the coverage of its 95 % intervals).
2. Structure selection (BIC) on an exponential-cosine record, the paper's Fig. 3 case: the
   exponential fit leaves correlated residuals, the exponential-cosine one does not.
3. The single-channel INS filter with drift and diffusion wrong by ×10/÷10 (the paper's
   Fig. 4) against the filter tuned with parameters identified from sensor records (Fig. 5):
   the share of time the vertical error is outside ±3σ, NEES and NIS.
4. The Allan deviation of a gyro-drift record as the cross-check the paper names.
5. In flight (the paper's section 1, Fig. 2; `noise_in_flight.py`): the filter re-identifies
   its sensor models from its own running estimates as the log goes on, switching to the
   exponential-cosine structure when its test says so, beside the wrong model, the batch
   loop, an innovation-based adaptive filter (Sage–Husa) and the oracle, on 48 h logs whose
   gyro drift is exponential-cosine.

Writes OUT/result.json and PNG figures. Run: `python studies/noise_identification.py
[--out DIR] [--quick]` (float64: likelihoods of 10⁴-sample records compared to a unit, and
INS covariances spanning 1e-15..1).
"""

from __future__ import annotations

import functools
import sys
import time
from pathlib import Path

import equinox as eqx  # noqa: E402
import jax

# Run as a script: float64 before the module's constants are built, as in the report's
# workers (imported by the report, this changes nothing: the report chose already).
if __name__ == "__main__":
    jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import accel_jax as aj  # noqa: E402
from accel_jax._runtime import fast_compile  # noqa: E402
from accel_jax.kalman import (  # noqa: E402
    INSChannel,
    ins_consistency_trial,
    ins_initial_covariance,
    kalman_filter,
    rts_smoother,
    scale_noise_coefficients,
    simulate_linear_gaussian,
)
from accel_jax.noise import (  # noqa: E402
    ExponentialCosine,
    GaussMarkov,
    NoiseFitResult,
    NoiseSum,
    RandomWalk,
    WhiteNoise,
    allan_coefficients,
    allan_deviation_intervals,
    allan_variance_of_model,
    autocorrelation,
    fit_allan_terms,
    fit_autocorrelation_least_squares,
    fit_exp_cosine_paper,
    fit_gauss_markov_paper,
    fit_maximum_likelihood,
    select_noise_model,
    simulate_noise,
)
sys.path.insert(0, str(Path(__file__).resolve().parent))
import noise_batch_bias  # noqa: E402
import noise_in_flight  # noqa: E402

from accel_jax.report import (  # noqa: E402
    Figures,
    provenance,
    study_main,
    study_run,
    write_json_atomic,
)

STUDY = "noise_identification"

# --- assumptions (the paper gives no numbers for its test bed; ours are recorded) ---------
DT = 1.0  # s, sampling of the sensor-error records and of the filter (the paper's 1 Hz)
GM_TRUE = {"sigma": 1.0, "tau": 50.0}  # record unit, s
EC_TRUE = {"sigma": 1.0, "alpha": 0.01, "beta": 0.05}  # unit, 1/s, rad/s (period 126 s)
# Single-channel INS: accelerometer error 1e-3 m/s² (≈100 µg), τ_a = 10 min; gyro drift
# 5e-8 rad/s (≈0.01 °/h), τ_ω = 1 h; velocity reference noise 0.1 m/s.
INS_TRUE = {
    "accel_sigma": 1e-3,
    "accel_correlation_time": 600.0,
    "gyro_sigma": 5e-8,
    "gyro_correlation_time": 3600.0,
    "velocity_noise": 0.1,
}
WRONG_DRIFT, WRONG_DIFFUSION = 10.0, 0.1  # drift 1/τ ×10, diffusion 2σ²/τ ÷10


def _sweep_records(one, keys, *shared):
    return aj.sweep(one, keys, *shared, in_axes=(0,) + (None,) * len(shared))


def _stats(values: np.ndarray, truth: float, ok: np.ndarray | None = None) -> dict:
    values = np.asarray(values, dtype=float)
    if ok is not None:
        values = values[np.asarray(ok, bool)]
    rel = values / truth - 1
    return {
        "mean": float(np.mean(values)),
        "median": float(np.median(values)),
        "std": float(np.std(values, ddof=1)),
        "relative_bias": float(np.mean(rel)),
        "relative_rms": float(np.sqrt(np.mean(rel**2))),
        "count": int(values.size),
    }


# --- 1. recovery over many simulated records ------------------------------------------


def _gm_one(key, n, max_lag):
    truth = GaussMarkov(GM_TRUE["sigma"], GM_TRUE["tau"])
    x = simulate_noise(truth, DT, n, key=key)
    R = autocorrelation(x, max_lag)
    paper = fit_gauss_markov_paper(R, DT, throw=False)
    paper_e = fit_gauss_markov_paper(R, DT, min_correlation=float(np.exp(-1)), throw=False)
    start = paper_e.model
    ls = fit_autocorrelation_least_squares(start, R, DT, throw=False)
    ml = fit_maximum_likelihood(start, x, DT, throw=False)
    tau = GM_TRUE["tau"]
    covered = (ml.lower.correlation_time < tau) & (tau < ml.upper.correlation_time)
    return {
        "paper_r_positive": (
            paper.model.correlation_time,
            paper.model.sigma,
            paper.result == NoiseFitResult.successful,
        ),
        "paper_r_above_1_over_e": (
            paper_e.model.correlation_time,
            paper_e.model.sigma,
            paper_e.result == NoiseFitResult.successful,
        ),
        "least_squares": (
            ls.model.correlation_time,
            ls.model.sigma,
            ls.result == NoiseFitResult.successful,
        ),
        "maximum_likelihood": (
            ml.model.correlation_time,
            ml.model.sigma,
            ml.result == NoiseFitResult.successful,
        ),
        "ml_tau_covered": covered,
    }


def _ec_one(key, n, max_lag):
    truth = ExponentialCosine(EC_TRUE["sigma"], EC_TRUE["alpha"], EC_TRUE["beta"])
    x = simulate_noise(truth, DT, n, key=key)
    R = autocorrelation(x, max_lag)
    paper = fit_exp_cosine_paper(R, DT, throw=False)
    ls = fit_autocorrelation_least_squares(paper.model, R, DT, throw=False)
    ml = fit_maximum_likelihood(paper.model, x, DT, throw=False)
    out = {}
    for name, fit, ok in (
        ("paper_rules_19_21", paper.model, paper.result == NoiseFitResult.successful),
        ("least_squares", ls.model, ls.result == NoiseFitResult.successful),
        ("maximum_likelihood", ml.model, ml.result == NoiseFitResult.successful),
    ):
        out[name] = (fit.decay_rate, fit.angular_frequency, fit.sigma, ok)
    out["ml_alpha_covered"] = (ml.lower.decay_rate < EC_TRUE["alpha"]) & (
        EC_TRUE["alpha"] < ml.upper.decay_rate
    )
    out["ml_beta_covered"] = (ml.lower.angular_frequency < EC_TRUE["beta"]) & (
        EC_TRUE["beta"] < ml.upper.angular_frequency
    )
    return out


def _rule_15_one(key, n, max_lag):
    x = simulate_noise(GaussMarkov(GM_TRUE["sigma"], GM_TRUE["tau"]), DT, n, key=key)
    R = autocorrelation(x, max_lag)
    out = {}
    for name, floor in (("paper_r_positive", None), ("paper_r_above_1_over_e", float(np.exp(-1)))):
        kwargs = {} if floor is None else {"min_correlation": floor}
        fit = fit_gauss_markov_paper(R, DT, throw=False, **kwargs)
        out[name] = (fit.model.correlation_time, fit.result == NoiseFitResult.successful)
    return out


def rule_15_statistics(runs: int, n: int, key) -> dict:
    """Rule (15) alone (it is cheap) over many records: the bias and spread of τ̂_c that the
    64-record recovery only hints at (its mean is the noisiest summary of a skewed
    estimator: report the median and the quartiles beside it)."""
    out = _sweep_records(
        functools.partial(_rule_15_one, n=n, max_lag=n // 10), jax.random.split(key, runs)
    )
    stats = {}
    for name, (tau, ok) in out.items():
        tau, ok = np.asarray(tau, float), np.asarray(ok, bool)
        rel = tau[ok] / GM_TRUE["tau"] - 1
        q25, q50, q75 = np.percentile(rel, [25, 50, 75])
        stats[name] = {
            "runs": runs,
            "usable": int(ok.sum()),
            "mean_bias": float(np.mean(rel)),
            "mean_bias_standard_error": float(np.std(rel, ddof=1) / np.sqrt(rel.size)),
            "median_bias": float(q50),
            "spread_std": float(np.std(rel, ddof=1)),
            "interquartile": [float(q25), float(q75)],
        }
    return {"samples_per_record": n, "max_lag": n // 10, "estimators": stats}


def recovery(runs: int, n: int, key) -> dict:
    k_gm, k_ec = jax.random.split(key)
    max_lag = n // 10
    gm = _sweep_records(
        functools.partial(_gm_one, n=n, max_lag=max_lag), jax.random.split(k_gm, runs)
    )
    ec = _sweep_records(
        functools.partial(_ec_one, n=n, max_lag=max_lag), jax.random.split(k_ec, runs)
    )
    gm_out = {}
    for name in (
        "paper_r_positive",
        "paper_r_above_1_over_e",
        "least_squares",
        "maximum_likelihood",
    ):
        tau, sigma, ok = (np.asarray(v) for v in gm[name])
        gm_out[name] = {
            "tau_s": _stats(tau, GM_TRUE["tau"], ok),
            "sigma": _stats(sigma, GM_TRUE["sigma"], ok),
            "usable_fraction": float(np.mean(ok)),
            "tau_samples": tau.tolist(),
        }
    gm_out["maximum_likelihood"]["ci95_coverage_tau"] = float(
        np.mean(np.asarray(gm["ml_tau_covered"]))
    )
    ec_out = {}
    for name in ("paper_rules_19_21", "least_squares", "maximum_likelihood"):
        alpha, beta, sigma, ok = (np.asarray(v) for v in ec[name])
        ec_out[name] = {
            "alpha_per_s": _stats(alpha, EC_TRUE["alpha"], ok),
            "beta_rad_per_s": _stats(beta, EC_TRUE["beta"], ok),
            "sigma": _stats(sigma, EC_TRUE["sigma"], ok),
            "usable_fraction": float(np.mean(ok)),
            "alpha_samples": alpha.tolist(),
            "beta_samples": beta.tolist(),
        }
    ec_out["maximum_likelihood"]["ci95_coverage_alpha"] = float(
        np.mean(np.asarray(ec["ml_alpha_covered"]))
    )
    ec_out["maximum_likelihood"]["ci95_coverage_beta"] = float(
        np.mean(np.asarray(ec["ml_beta_covered"]))
    )
    return {
        "gauss_markov": gm_out,
        "exp_cosine": ec_out,
        "runs": runs,
        "samples_per_record": n,
        "max_lag": max_lag,
    }


# --- 2. structure selection (the paper's Fig. 3 case) ----------------------------------


def structure_case(n: int, key, quick: bool) -> dict:
    truth = NoiseSum(
        (WhiteNoise(0.3), ExponentialCosine(EC_TRUE["sigma"], EC_TRUE["alpha"], EC_TRUE["beta"]))
    )
    x = simulate_noise(truth, DT, n, key=key)
    structures = (
        ("white+gauss_markov", "white+exp_cosine")
        if quick
        else (
            "white",
            "gauss_markov",
            "exp_cosine",
            "random_walk",
            "white+gauss_markov",
            "white+random_walk",
            "white+exp_cosine",
        )
    )
    sel = select_noise_model(x, DT, structures=structures, residual_lags=40)
    max_lag = 300
    R = np.asarray(autocorrelation(x, max_lag))
    lags = np.arange(max_lag + 1) * DT
    gm_fit = sel.fits["white+gauss_markov"].model
    ec_fit = sel.fits["white+exp_cosine"].model
    return {
        "truth": "white (σ = 0.3) + exponential-cosine (σ = 1, α = 0.01 /s, β = 0.05 rad/s)",
        "chosen": sel.chosen,
        "samples": n,
        "table": sel.table,
        "residual_autocorrelation": {
            k: np.asarray(v).tolist() for k, v in sel.residual_autocorrelation.items()
        },
        "curves": {
            "lag_s": lags.tolist(),
            "sample": (R / R[0]).tolist(),
            "white+gauss_markov": (np.asarray(gm_fit.autocovariance(lags)) / R[0]).tolist(),
            "white+exp_cosine": (np.asarray(ec_fit.autocovariance(lags)) / R[0]).tolist(),
        },
    }


# --- 3. the INS filter -----------------------------------------------------------------


def identify_sensor(sigma, tau, n, key) -> dict:
    """Identify a Gauss-Markov sensor error from a static record of n samples at 1 Hz: rule
    (15) over r_j > e⁻¹ (the starting point) and maximum likelihood (used by the filter)."""
    return identify_series(simulate_noise(GaussMarkov(sigma, tau), DT, n, key=key))


# One compiled ML fit for every series of a length (a new filter_jit wrapper per call would
# compile again each time: the filter loop fits 2 series per iteration).
_fit_ml = eqx.filter_jit(functools.partial(fit_maximum_likelihood, throw=False))


def identify_series(x, throw: bool = True) -> dict:
    """Rule (15) over r_j > e⁻¹ and maximum likelihood of a Gauss-Markov model of series x
    sampled at DT (the sensor's record, or the filter's estimates of it). With
    `throw=False` a series rule (15) cannot fit (no r_j > 0: it looks white) gives
    "paper_ok": False instead of an error."""
    n = x.shape[0]
    scale = float(jnp.std(x))
    x = x / scale  # fit in units of the record's std: the optimiser's tolerances are absolute
    R = autocorrelation(x, min(n // 10, 2000))
    paper = fit_gauss_markov_paper(R, DT, min_correlation=float(np.exp(-1)), throw=throw)
    ml = _fit_ml(paper.model, x, DT)
    return {
        "paper_ok": bool(paper.result == NoiseFitResult.successful),
        "ml_converged": bool(ml.result == NoiseFitResult.successful),
        "paper": {
            "sigma": float(paper.model.sigma) * scale,
            "tau_s": float(paper.model.correlation_time),
        },
        "ml": {"sigma": float(ml.model.sigma) * scale, "tau_s": float(ml.model.correlation_time)},
        "ml_ci95_tau_s": [float(ml.lower.correlation_time), float(ml.upper.correlation_time)],
    }


def kalman_study(runs: int, hours: float, record_hours: float, key) -> dict:
    truth = INSChannel(**INS_TRUE)
    wrong = scale_noise_coefficients(
        truth, drift_factor=WRONG_DRIFT, diffusion_factor=WRONG_DIFFUSION
    )
    k_a, k_w, k_mc = jax.random.split(key, 3)
    n_rec = int(record_hours * 3600 / DT)
    accel = identify_sensor(INS_TRUE["accel_sigma"], INS_TRUE["accel_correlation_time"], n_rec, k_a)
    gyro = identify_sensor(INS_TRUE["gyro_sigma"], INS_TRUE["gyro_correlation_time"], n_rec, k_w)
    identified = {
        method: eqx.tree_at(
            lambda c: (
                c.accel_sigma,
                c.accel_correlation_time,
                c.gyro_sigma,
                c.gyro_correlation_time,
            ),
            truth,
            tuple(
                jnp.float64(v)
                for v in (
                    accel[method]["sigma"],
                    accel[method]["tau_s"],
                    gyro[method]["sigma"],
                    gyro[method]["tau_s"],
                )
            ),
        )
        for method in ("paper", "ml")
    }
    steps = int(hours * 3600 / DT)
    keys = jax.random.split(k_mc, runs)
    trial = functools.partial(ins_consistency_trial, num_steps=steps)

    def one(key, assumed):
        return trial(truth, assumed, key)

    out = {}
    traces = {}
    for name, assumed in (
        ("true_model", truth),
        ("wrong_model", wrong),
        ("identified", identified["ml"]),
        ("identified_paper_rule", identified["paper"]),
    ):
        res = aj.sweep(one, keys, assumed, in_axes=(0, None))
        frac = np.asarray(res.fraction_outside_3sigma)
        out[name] = {
            "fraction_outside_3sigma": float(frac.mean()),
            "fraction_outside_3sigma_per_run_std": float(frac.std(ddof=1)) if runs > 1 else 0.0,
            "mean_nees": float(np.mean(np.asarray(res.nees))),
            "mean_nis": float(np.mean(np.asarray(res.nis))),
            "final_rms_vertical_error_rad": float(
                np.sqrt(np.mean(np.asarray(res.vertical_error)[:, -1] ** 2))
            ),
            "final_predicted_vertical_sigma_rad": float(
                np.mean(np.asarray(res.vertical_sigma)[:, -1])
            ),
            "assumed": {k: float(getattr(assumed, k)) for k in INS_TRUE},
        }
        traces[name] = (np.asarray(res.vertical_error[0]), np.asarray(res.vertical_sigma[0]))
    # The paper does not say in which direction the coefficients were wrong: all four.
    variants = {}
    for drift in (10.0, 0.1):
        for diffusion in (10.0, 0.1):
            assumed = scale_noise_coefficients(
                truth, drift_factor=drift, diffusion_factor=diffusion
            )
            res = aj.sweep(one, keys, assumed, in_axes=(0, None))
            variants[f"drift_x{drift:g}_diffusion_x{diffusion:g}"] = {
                "fraction_outside_3sigma": float(np.mean(np.asarray(res.fraction_outside_3sigma))),
                "mean_nees": float(np.mean(np.asarray(res.nees))),
            }
    out["wrong_model_variants"] = variants
    out["identification"] = {"accelerometer": accel, "gyro": gyro, "record_hours": record_hours}
    out["runs"] = runs
    out["hours"] = hours
    return out, traces


def _consistency(one, keys, assumed) -> dict:
    res = aj.sweep(one, keys, assumed, in_axes=(0, None))
    return {
        "fraction_outside_3sigma": float(np.mean(np.asarray(res.fraction_outside_3sigma))),
        "mean_nees": float(np.mean(np.asarray(res.nees))),
        "mean_nis": float(np.mean(np.asarray(res.nis))),
    }


def _sensor_fields(channel) -> dict:
    return {k: float(getattr(channel, k)) for k in INS_TRUE if k != "velocity_noise"}


def filter_identification_loop(
    iterations: int, log_hours: float, runs: int, hours: float, key, estimator: str = "rule_15"
) -> dict:
    """Seed 001's experiment as the paper runs it: the INS filter, tuned with the wrong
    model, processes a flight log (velocity observations only); the sensor-error models are
    identified from its own estimates of Δa and Δω — the RTS-smoothed means over the log
    (the batch, from-a-log variant) — by the paper's rule (15) over r_j > e⁻¹
    (`estimator="rule_15"`) or by exact ML (`"ml"`, which treats the smoothed series as a
    Gauss-Markov record); the filter is retuned with them and the loop repeats. Each iteration's model is judged by Monte
    Carlo consistency (truth simulated, this model in the filter) beside the oracle that
    knows the true models. The smoothed estimate is a conditional mean, not the sensor
    error: where Δa is weakly observable from velocity it is shrunk towards zero, and the
    model identified from it is biased; the table shows by how much and whether the loop
    still reaches a consistent filter."""
    truth = INSChannel(**INS_TRUE)
    assumed = scale_noise_coefficients(
        truth, drift_factor=WRONG_DRIFT, diffusion_factor=WRONG_DIFFUSION
    )
    k_log, k_mc = jax.random.split(key)
    true_model = truth.discretise(DT)
    n_log = int(log_hours * 3600 / DT)
    zeros = jnp.zeros(4)
    states, observations = simulate_linear_gaussian(
        true_model, zeros, ins_initial_covariance(truth), n_log, key=k_log
    )
    keys = jax.random.split(k_mc, runs)
    trial = functools.partial(ins_consistency_trial, num_steps=int(hours * 3600 / DT))

    def one(key, model):
        return trial(truth, model, key)

    @eqx.filter_jit
    def smoothed_sensor_errors(channel, observations):
        model = channel.discretise(DT)
        out = kalman_filter(model, observations, zeros, ins_initial_covariance(channel))
        return rts_smoother(model, out).smoothed_means[:, 2:]

    rows = []
    for iteration in range(iterations + 1):
        estimates = smoothed_sensor_errors(assumed, observations)
        row = {
            "iteration": iteration,
            "model": _sensor_fields(assumed),
            **_consistency(one, keys, assumed),
            "smoothed_std_over_true_std": {
                "accelerometer": float(jnp.std(estimates[:, 0]) / jnp.std(states[:, 2])),
                "gyro": float(jnp.std(estimates[:, 1]) / jnp.std(states[:, 3])),
            },
        }
        rows.append(row)
        if iteration == iterations:
            break
        which = "paper" if estimator == "rule_15" else "ml"
        fits = {
            "accelerometer": identify_series(estimates[:, 0], throw=False),
            "gyro": identify_series(estimates[:, 1], throw=False),
        }
        failed = [name for name, fit in fits.items() if not fit["paper_ok"]]
        if failed:
            row["stopped"] = (
                f"rule (15) finds no lag with r_j > 0 in the smoothed {' and '.join(failed)} "
                "estimates (they look white): nothing to retune with"
            )
            break
        row["ml_converged"] = {name: fit["ml_converged"] for name, fit in fits.items()}
        accel, gyro = fits["accelerometer"][which], fits["gyro"][which]
        assumed = eqx.tree_at(
            lambda c: (
                c.accel_sigma,
                c.accel_correlation_time,
                c.gyro_sigma,
                c.gyro_correlation_time,
            ),
            assumed,
            tuple(
                jnp.float64(v)
                for v in (accel["sigma"], accel["tau_s"], gyro["sigma"], gyro["tau_s"])
            ),
        )
    direct = {
        "accelerometer": identify_series(states[:, 2])["ml"],
        "gyro": identify_series(states[:, 3])["ml"],
    }
    return {
        "iterations": rows,
        "oracle": {"model": _sensor_fields(truth), **_consistency(one, keys, truth)},
        "identified_from_the_true_sensor_errors_of_the_same_log": direct,
        "log_hours": log_hours,
        "runs": runs,
        "hours": hours,
        "estimator": estimator,
        "method": "batch: RTS-smoothed means of Δa, Δω over the whole log, "
        + (
            "rule (15) over r_j > e⁻¹ on each (the paper's rule)"
            if estimator == "rule_15"
            else "exact Gauss-Markov ML on each (rule (15) as its start)"
        )
        + "; the real-time variant is the in-flight part (noise_in_flight.py)",
    }


# --- 4. Allan deviation ----------------------------------------------------------------


def allan_case(n: int, key, quick: bool = False) -> dict:
    """A gyro-drift-like record: white (ARW) + Gauss-Markov + rate random walk [rad/s]."""
    white, gm_sigma, gm_tau, rrw = 1e-6, 2e-7, 300.0, 1e-14
    truth = NoiseSum((WhiteNoise(white), GaussMarkov(gm_sigma, gm_tau), RandomWalk(rrw)))
    x = simulate_noise(truth, DT, n, key=key)
    sizes = sorted({int(round(v)) for v in np.logspace(0, np.log10((n - 1) // 4), 20)})
    # The overlapping ADEV with ±1σ intervals from equivalent degrees of freedom
    # (allantools' noise identification and Greenhall EDF).
    intervals = allan_deviation_intervals(x, DT, sizes)
    taus, adev = intervals.taus, intervals.deviation
    coeff = allan_coefficients(taus, adev)
    stationary = NoiseSum((WhiteNoise(white), GaussMarkov(gm_sigma, gm_tau)))
    theory = np.sqrt(
        np.asarray(allan_variance_of_model(stationary, DT, sizes)) + rrw * np.asarray(taus) / 3
    )
    inside = (intervals.lower <= theory) & (theory <= intervals.upper)  # truth within ±1σ
    # The IEEE Std 952 terms with 95 % parametric-bootstrap intervals (a term the record
    # does not support is an upper bound only), and the fitted model's ADEV over the record's.
    terms = fit_allan_terms(np.asarray(x), DT, n_bootstrap=79 if quick else 199, seed=1)
    return {
        "truth": {
            "white_sigma_rad_per_s": white,
            "gm_sigma_rad_per_s": gm_sigma,
            "gm_tau_s": gm_tau,
            "rate_random_walk_q_rad2_per_s3": rrw,
        },
        "tau_s": np.asarray(taus).tolist(),
        "adev_rad_per_s": np.asarray(adev).tolist(),
        "theory_rad_per_s": theory.tolist(),
        "interval_1sigma_rad_per_s": {
            "lower": intervals.lower.tolist(),
            "upper": intervals.upper.tolist(),
            "edf": intervals.edf.tolist(),
            "noise_alpha": [None if np.isnan(a) else int(a) for a in intervals.alpha],
            "true_adev_inside": int(np.sum(inside)),
            "n_taus": int(inside.size),
            "method": "chi-square interval for Greenhall's EDF of the overlapping ADEV, the "
            "noise type identified at each tau by allantools' lag-1 autocorrelation test "
            "(white FM where too few clusters); nominal coverage 0.683 per tau, the taus "
            "of one record are correlated",
        },
        "slopes": np.asarray(coeff.slopes).tolist(),
        "coefficients": {
            "white_N": float(coeff.white),
            "white_N_true": white * np.sqrt(DT),
            "bias_instability_B": float(coeff.bias_instability),
            "rate_random_walk_K": float(coeff.random_walk),
            "rate_random_walk_K_true": float(np.sqrt(rrw)),
        },
        "note": "B absorbs the Gauss-Markov hump (the standard model has no GM term): Allan slopes name the regimes, the likelihood identifies the model.",
        "ieee_terms": {
            "terms": terms.terms,
            "confidence": terms.confidence,
            "n_bootstrap": terms.n_bootstrap,
            "method": terms.method,
            "model_adev_rad_per_s": terms.deviation_at(np.asarray(taus)).tolist(),
            "white_N_true": white * np.sqrt(DT),
            "rate_random_walk_K_true": float(np.sqrt(rrw)),
        },
    }


# --- the study -------------------------------------------------------------------------


@study_run(compile_bound_when_quick=False)
def run(out_dir: Path, *, quick: bool = False, seed: int = 20261122) -> dict:
    """Run the study; write OUT/result.json and figures; return the result dict."""
    out_dir = Path(out_dir)
    started = time.perf_counter()
    key = jax.random.key(seed)
    k_rec, k_sel, k_kal, k_allan = jax.random.split(key, 4)
    runs = 6 if quick else 64
    n = 1200 if quick else 4000
    rec = recovery(runs, n, k_rec)
    rule_15 = rule_15_statistics(200 if quick else 2000, n, jax.random.fold_in(k_rec, 15))
    timing = {"recovery": time.perf_counter() - started}
    # --quick is compile-bound after the recovery batch: the rest compiles with most XLA
    # optimisations off (accel_jax._runtime.fast_compile). Measured on the 2-core CPU, quick, cache
    # off: structure 14.6 → 7.5, Kalman 9.9 → 6.2, Allan 3.9 → 1.7 CPU-s; the recovery
    # batch of ML fits runs longer so (15.1 → 17.7) and keeps the default.
    with fast_compile(quick):
        structure = structure_case(1200 if quick else 5000, k_sel, quick)
        timing["structure"] = time.perf_counter() - started
        kal, traces = kalman_study(
            runs=2 if quick else 64,
            hours=1.0 if quick else 4.0,
            record_hours=8.0 if quick else 48.0,
            key=k_kal,
        )
        timing["kalman"] = time.perf_counter() - started
        loop = {
            estimator: filter_identification_loop(
                iterations=2 if quick else 4,
                log_hours=8.0 if quick else 48.0,
                runs=2 if quick else 64,
                hours=1.0 if quick else 4.0,
                key=jax.random.fold_in(k_kal, 1),
                estimator=estimator,
            )
            for estimator in ("rule_15", "ml")
        }
        # The loop's identification map from the spectra (NumPy float64; quick: a 2^18
        # grid, which gives the full 2^20 grid's figures to the digits shown at 8 h), and
        # the loop's identification alone on 8 (quick) or 16 more logs.
        loop["rule_15"]["spectral_map"] = noise_batch_bias.batch_bias(
            loop["rule_15"],
            INS_TRUE,
            DT,
            logs=8 if quick else 16,
            key=jax.random.fold_in(k_kal, 2),
            fft_size=1 << 18 if quick else None,
        )
        timing["filter_loop"] = time.perf_counter() - started
        allan = allan_case(5000 if quick else 100000, k_allan, quick)
        timing["allan"] = time.perf_counter() - started
        in_flight = noise_in_flight.in_flight_study(
            runs=2 if quick else 64,
            hours=12 if quick else 48,
            key=jax.random.fold_in(k_kal, 2),
            quick=quick,
        )
        timing["in_flight"] = time.perf_counter() - started

    gm_ml = rec["gauss_markov"]["maximum_likelihood"]
    ec_ml = rec["exp_cosine"]["maximum_likelihood"]
    result = {
        "title": "Noise-model identification and the Kalman filter it tunes (Chernodarov, "
        "Patrikeev & Ivanov)",
        "gauss_markov": {
            "tau_true": GM_TRUE["tau"],
            "tau_fit": gm_ml["tau_s"]["mean"],
            "sigma_true": GM_TRUE["sigma"],
            "sigma_fit": gm_ml["sigma"]["mean"],
            "estimators": {
                k: {kk: vv for kk, vv in v.items() if kk != "tau_samples"}
                for k, v in rec["gauss_markov"].items()
            },
            "rule_15_large_sample": rule_15,
        },
        "exp_cosine": {
            "alpha_true": EC_TRUE["alpha"],
            "alpha_fit": ec_ml["alpha_per_s"]["mean"],
            "beta_true": EC_TRUE["beta"],
            "beta_fit": ec_ml["beta_rad_per_s"]["mean"],
            "sigma_true": EC_TRUE["sigma"],
            "estimators": {
                k: {kk: vv for kk, vv in v.items() if kk not in ("alpha_samples", "beta_samples")}
                for k, v in rec["exp_cosine"].items()
            },
        },
        "structure_selection": {k: v for k, v in structure.items() if k != "curves"},
        "kalman": kal,
        "filter_identification_loop": loop,
        "in_flight": in_flight,
        "allan": allan,
        "assumptions": {
            "sample_interval_s": DT,
            "records": f"{runs} simulated records of {n} samples per model (exact discrete-time simulation)",
            "gauss_markov_truth": GM_TRUE,
            "exp_cosine_truth": EC_TRUE,
            "autocorrelation_lags": rec["max_lag"],
            "paper_rule_15": "sum over lags j ≥ 1 up to the first r_j ≤ 0 (paper) or r_j ≤ e⁻¹ (truncated)",
            "exp_cosine_realisation": "damped-rotation state (exact e^{-α|τ|} cos βτ); the paper's shaping filter (17), read as σ√(2α)(p + b)/(p² + 2αp + b²) with b² = α² + β², has the same autocorrelation (16)",
            "ml": "exact Gaussian likelihood conditional on the first sample, BFGS in log-parameters, 95 % CI from the observed information",
            "ins_truth": INS_TRUE,
            "wrong_model": f"drift 1/τ ×{WRONG_DRIFT:g} and diffusion 2σ²/τ ×{WRONG_DIFFUSION:g} for both sensors (so σ ÷ 10 and τ ÷ 10: an over-confident filter)",
            "identified_model": "σ, τ of each sensor by ML on a static record of the sensor error at 1 Hz (record_hours in kalman.identification); the filter prior uses the identified σ",
            "ins_prior": "ΔV ~ N(0, 0.1² m²/s²), δ ~ N(0, 1e-4² rad²), sensors at their stationary variance",
            "precision": "float64",
            "in_flight": in_flight["settings"],
        },
        "provenance": provenance(
            seeds={"root": seed},
            precision="float64",
            extra={
                "compiled_with_most_xla_optimisations_off": (
                    "structure selection, Kalman filter, Allan deviation, in-flight loop"
                    if quick
                    else "nothing"
                )
            },
        ),
    }
    result["summary"] = _summary_rows(result)
    result["figures"] = make_figures(out_dir, result, rec, structure, traces)
    timing["figures"] = time.perf_counter() - started
    result["provenance"]["wall_time_s"] = time.perf_counter() - started
    result["provenance"]["cumulative_time_s"] = timing
    write_json_atomic(out_dir / "result.json", result)
    return result


def _summary_rows(result: dict) -> list[dict]:
    gm = result["gauss_markov"]["estimators"]
    ec = result["exp_cosine"]["estimators"]
    kal = result["kalman"]
    rows = []
    for name in (
        "paper_r_positive",
        "paper_r_above_1_over_e",
        "least_squares",
        "maximum_likelihood",
    ):
        s = gm[name]["tau_s"]
        rows.append(
            {
                "quantity": f"GM τ_c = {GM_TRUE['tau']:g} s, {name}: bias / rms [%]",
                "ours": f"{100 * s['relative_bias']:+.1f} / {100 * s['relative_rms']:.1f}",
                "paper": "rule (15), no numbers" if name.startswith("paper") else "—",
                "note": f"{s['count']} records",
            }
        )
    large = result["gauss_markov"]["rule_15_large_sample"]
    for name, st in large["estimators"].items():
        q25, q75 = st["interquartile"]
        rows.append(
            {
                "quantity": f"GM τ_c, {name} over {st['runs']} records: mean / median bias, "
                "spread [%]",
                "ours": f"{100 * st['mean_bias']:+.1f} ± {100 * st['mean_bias_standard_error']:.1f}"
                f" / {100 * st['median_bias']:+.1f}, σ {100 * st['spread_std']:.0f} "
                f"(quartiles {100 * q25:+.0f}, {100 * q75:+.0f})",
                "paper": "rule (15), no numbers",
                "note": f"{st['usable']} usable; {large['samples_per_record']} samples per record"
                + (
                    "; skewed: its mean and median bias differ in sign"
                    if st["mean_bias"] * st["median_bias"] < 0
                    else ""
                ),
            }
        )
    for name in ("paper_rules_19_21", "least_squares", "maximum_likelihood"):
        a, b = ec[name]["alpha_per_s"], ec[name]["beta_rad_per_s"]
        rows.append(
            {
                "quantity": f"exp-cos α, β, {name}: bias [%]",
                "ours": f"α {100 * a['relative_bias']:+.1f}, β {100 * b['relative_bias']:+.1f} (rms {100 * a['relative_rms']:.1f}, {100 * b['relative_rms']:.1f})",
                "paper": "rules (19)-(21), no numbers" if name.startswith("paper") else "—",
                "note": "",
            }
        )
    rows.append(
        {
            "quantity": "ML 95 % CI coverage of τ_c",
            "ours": f"{gm['maximum_likelihood']['ci95_coverage_tau']:.2f}",
            "paper": "—",
            "note": "should be ≈ 0.95",
        }
    )
    rows.append(
        {
            "quantity": "structure chosen (BIC) for white + exp-cos record",
            "ours": result["structure_selection"]["chosen"],
            "paper": "exp-cosine needed (Fig. 3)",
            "note": "",
        }
    )
    loop = result["filter_identification_loop"]["rule_15"]
    for row in loop["iterations"]:
        last = row["iteration"] == loop["iterations"][-1]["iteration"]
        model = row["model"]
        entry = {
            "quantity": f"the §4 paper's loop (rule (15) on the smoothed estimates), iteration "
            f"{row['iteration']}: vertical error outside ±3σ [% of time] / NEES",
            "ours": f"{100 * row['fraction_outside_3sigma']:.2f} / {row['mean_nees']:.1f}",
            "paper": "consistent after retuning (Fig. 5)" if last else "—",
            "note": f"τ_a {model['accel_correlation_time']:.3g} s, σ_a "
            f"{model['accel_sigma']:.2g}, τ_ω {model['gyro_correlation_time']:.3g} s, σ_ω "
            f"{model['gyro_sigma']:.2g}; smoothed Δa std "
            f"{row['smoothed_std_over_true_std']['accelerometer']:.2f} × the true one"
            + ("; the initial (wrong) model" if row["iteration"] == 0 else ""),
        }
        if last:
            oracle = loop["oracle"]
            # Consistent as the paper claims: at most 1 % of the time outside ±3σ (a
            # consistent filter: 0.27 %) and a NEES within 1.5× the oracle's.
            consistent = (
                row["fraction_outside_3sigma"] <= 0.01
                and row["mean_nees"] <= 1.5 * oracle["mean_nees"]
            )
            entry["status"] = "reproduced" if consistent else "differs"
            first = loop["iterations"][0]
            entry["explanation"] = (
                f"the loop takes the filter from {100 * first['fraction_outside_3sigma']:.0f} % "
                f"to {100 * row['fraction_outside_3sigma']:.2f} % outside ±3σ in "
                f"{row['iteration']} iterations (oracle "
                f"{100 * oracle['fraction_outside_3sigma']:.2f} %, NEES "
                f"{oracle['mean_nees']:.1f}); the smoothed estimates it identifies from are "
                "conditional means (low-passed, shrunk where weakly observable), not the sensor "
                f"errors, so the models stay biased (τ_ω {model['gyro_correlation_time']:.3g} s "
                f"against {INS_TRUE['gyro_correlation_time']:g} s); the next row predicts that "
                "bias from the spectra, and what the smoothed covariances this fit ignores "
                "change"
            )
        rows.append(entry)
    if "spectral_map" in loop:
        rows.append(
            noise_batch_bias.batch_bias_row(
                loop["spectral_map"], INS_TRUE["gyro_correlation_time"]
            )
        )
    ml_last = result["filter_identification_loop"]["ml"]["iterations"][-1]
    rows.append(
        {
            "quantity": f"the same loop with ML instead of rule (15), iteration "
            f"{ml_last['iteration']}: outside ±3σ [%] / NEES",
            "ours": f"{100 * ml_last['fraction_outside_3sigma']:.2f} / {ml_last['mean_nees']:.3g}",
            "paper": "—",
            "note": f"τ_a {ml_last['model']['accel_correlation_time']:.3g} s, τ_ω "
            f"{ml_last['model']['gyro_correlation_time']:.3g} s: the smoothed series is "
            "smoother than any Gauss-Markov record, and ML reads it as a near random walk"
            + (f"; the loop stopped: {ml_last['stopped']}" if "stopped" in ml_last else ""),
        }
    )
    oracle = loop["oracle"]
    rows.append(
        {
            "quantity": "the §4 paper's loop, oracle (the true models): outside ±3σ [%] / NEES",
            "ours": f"{100 * oracle['fraction_outside_3sigma']:.2f} / {oracle['mean_nees']:.1f}",
            "paper": "—",
            "note": f"{loop['runs']} runs of {loop['hours']:g} h; log {loop['log_hours']:g} h. "
            "This batch loop retunes INSChannel's Gauss–Markov states; the real-time loop and "
            "the batch loop with the exponential-cosine structure are the in-flight rows below",
        }
    )
    rows.extend(_in_flight_rows(result["in_flight"]))
    for name, paper in (
        ("wrong_model", "diverges: Δδ > 3σ_δ (Fig. 4)"),
        ("identified", "consistent (Fig. 5)"),
        ("true_model", "—"),
    ):
        rows.append(
            {
                "quantity": f"vertical error outside ±3σ, {name.replace('_', ' ')} [% of time]",
                "ours": f"{100 * kal[name]['fraction_outside_3sigma']:.2f} (NEES {kal[name]['mean_nees']:.1f})",
                "paper": paper,
                "note": "consistent: 0.27 % and NEES 4",
            }
        )
    return rows


def _transient_switches(configs: dict) -> str:
    """The largest share of logs, over the blocks, whose Gauss–Markov sensor the loop held
    as exponential-cosine at one time (a switch it may undo later; the row counts the end)."""
    parts = []
    for name, c in configs.items():
        shares = c["structure"].get("exp_cosine_share_by_block")
        if shares is None:
            continue
        sensors = ["accelerometer"] + (["gyro"] if c["gyro_truth"] == "gauss_markov" else [])
        parts += [f"{s} {100 * max(shares[s]):.0f} % ({name})" for s in sensors]
    if not parts:
        return ""
    return "; Gauss–Markov sensors held as exponential-cosine at one time, at most: " + ", ".join(
        parts
    )


def _information_text(c: dict) -> str:
    """What the log holds at best (`noise_in_flight._information`), as a clause."""
    info = c.get("information_true_over_best_gauss_markov")
    if not info:
        return ""
    return (
        f"; what the log can tell at best — the true models over the best Gauss–Markov drift "
        f"(true σ, τ on a grid of {len(info['gauss_markov_tau_grid_over_correlation_time'])}) "
        f"over the second half: a median {info['median']:.1f} nats (10th–90th percentiles "
        f"{info['p10_p90'][0]:.1f}, {info['p10_p90'][1]:.1f}), above the loop's price "
        f"{info['loop_price']:.1f} on {100 * info['share_above_loop_price']:.0f} % of logs"
        + (
            f"; and the drift itself, noise-free every {perfect['lag_time_s']:g} s for "
            f"{perfect['hours']:g} h (the loop's window; NumPy, {perfect['realisations']} "
            f"realisations), holds a median {perfect['median']:.1f} nats "
            f"({perfect['p10_p90'][0]:.1f}, {perfect['p10_p90'][1]:.1f}) for the true "
            "structure over the best Gauss–Markov: a test with perfect candidates on a perfect "
            f"record would pass the price on {100 * perfect['share_above_loop_price']:.0f} %"
            if (perfect := info.get("drift_itself_noise_free"))
            else ""
        )
    )


def _in_flight_rows(fl: dict) -> list[dict]:
    """The in-flight part's rows: each configuration's consistency after the loop settles,
    the structure switches, and the causes where the loop differs."""
    rows = []
    configs = fl["configurations"]
    where = f"{fl['runs']} logs of {fl['hours']} h at 1 Hz; settled = the second half"
    for name in ("too_large", "too_small"):
        c = configs[name]
        v = c["variants"]
        oracle = v["oracle"]
        real = v["real_time_loop"]
        # A consistent filter has 0.27 % outside ±3σ; the oracle's own share is noisy
        # over few logs, so the factor 2 is taken against the larger of the two.
        reference = max(oracle["outside_3sigma_settled"], 0.0027)
        within = real["outside_3sigma_settled"] <= 2 * reference
        shown = ", ".join(
            f"{k.replace('_', ' ')} {100 * m['outside_3sigma_settled']:.2f} % "
            f"(NEES {m['nees_settled']:.2f}, NIS {m['nis_settled']:.2f})"
            for k, m in v.items()
        )
        gyro = c["identified_final"]["gyro"]["median"]
        accel = c["identified_final"]["accelerometer"]["median"]
        entry = {
            "quantity": f"in flight, filter started with drift and diffusion "
            f"×{c['start_factor']:g}: vertical error outside ±3σ after the loop settles, "
            "real-time loop against the oracle",
            "ours": f"{100 * real['outside_3sigma_settled']:.2f} % against "
            f"{100 * oracle['outside_3sigma_settled']:.2f} % (× "
            f"{real['outside_3sigma_settled'] / max(oracle['outside_3sigma_settled'], 1e-9):.1f}; "
            f"× {real['outside_3sigma_settled'] / reference:.1f} against the larger of the "
            "oracle's and a consistent filter's 0.27 %)",
            "paper": "the real-time loop keeps the filter consistent (section 1, Fig. 2)",
            "note": f"{shown}; {where}",
            "status": "reproduced" if within else "differs",
        }
        entry["explanation"] = (
            f"identified at the end (medians): gyro {gyro['structure']} τ_c "
            f"{gyro['correlation_time_s']:.3g} s (true exp-cos 1/α 3600 s, βτ_c 2.5), σ "
            f"{gyro['sigma']:.3g}; accelerometer τ {accel['correlation_time_s']:.3g} s (600 s). "
            + (
                "The loop never retuned: the window's shrinkage-corrected autocovariance, "
                "dominated by the filter's own covariance carried with the (too slow) starting "
                "model, gives a correlation time the 24 h window cannot hold 10 times, so the "
                "guard keeps the starting model (which is conservative here)"
                if not any(any(r) for r in c["structure"]["retuned_share"])
                else "Without the shrinkage correction the same loop ends at "
                f"{100 * v['real_time_loop_without_shrinkage_correction']['outside_3sigma_settled']:.1f} % "
                "outside: the estimates it fits shrink as the filter trusts its model more"
                if "real_time_loop_without_shrinkage_correction" in v
                else ""
            )
        )
        rows.append(entry)
        sage = v.get("sage_husa")
        if sage is not None:
            rows.append(
                {
                    "quantity": f"in flight ×{c['start_factor']:g}: innovation-based adaptive "
                    "filter (simplified Sage–Husa) against the identification loop, settled "
                    "outside ±3σ",
                    "ours": f"{100 * sage['outside_3sigma_settled']:.1f} % against "
                    f"{100 * real['outside_3sigma_settled']:.2f} %",
                    "paper": "identification of the sensor models, not adaptation to the "
                    "innovations, is what restores consistency",
                    "note": f"NIS {sage['nis_settled']:.2f} (matched to the innovations) but "
                    f"NEES {sage['nees_settled']:.3g}: Q̂ = K ν² Kᵀ is rank one along the gain, "
                    "so the innovations are matched while the tilt and drift covariance "
                    "collapse",
                    "status": "reproduced"
                    if sage["outside_3sigma_settled"] > real["outside_3sigma_settled"]
                    else "differs",
                }
            )
    ec_rate = configs["too_large"]["structure"]["gyro_exp_cosine_at_end"]
    ec_rate_small = configs["too_small"]["structure"]["gyro_exp_cosine_at_end"]
    shrink = configs["too_large"]["filtered_estimate_variance_over_true_oracle"]
    lik = configs["too_large"]["log_likelihood_second_half"]
    rows.append(
        {
            "quantity": "in flight: logs whose gyro drift the loop ends modelling as "
            "exponential-cosine (the truth), started ×10 / ÷10",
            "ours": f"{100 * ec_rate:.0f} % / {100 * ec_rate_small:.0f} %",
            "paper": "switches to the exponential-cosine model (16)–(17) when the "
            "correlation calls for it (section 2, Fig. 3)",
            "note": "target ≥ 90 %; " + where,
            "status": "reproduced" if min(ec_rate, ec_rate_small) >= 0.9 else "differs",
            "explanation": "the structure is not observable enough from velocity aiding. The "
            "velocity log itself barely prefers the truth: over the second half its "
            "log-likelihood under the true models exceeds that under the models the loop "
            f"ended with by a median {lik['true_minus_identified_median']:.1f} nats (quartiles "
            f"{lik['true_minus_identified_quartiles'][0]:.1f}, "
            f"{lik['true_minus_identified_quartiles'][1]:.1f}), above the BIC price of the "
            f"extra parameter ({lik['bic_price']:.1f}) on "
            f"{100 * lik['share_above_bic_price']:.0f} % of logs"
            + _information_text(configs["too_large"])
            + ", so no likelihood test on these logs can choose the structure on ≥ 90 % of "
            "them. The oracle filter's "
            f"running estimate of Δω keeps {100 * shrink['gyro']:.0f} % of the drift's variance "
            f"(Δa {100 * shrink['accelerometer']:.0f} %), the rest shared with tilt through "
            "the Schuler loop"
            + (
                "; on a log that carries the structure (strong_oscillation: the drift ten "
                "times larger, βτ_c 37.7, a 0.01 m/s reference) the loop switches on "
                f"{100 * configs['strong_oscillation']['structure']['gyro_exp_cosine_at_end']:.0f} % "
                "of logs"
                if "strong_oscillation" in configs
                else ""
            )
            + ". A test on the estimates' own autocorrelation (a Whittle test, tried first) "
            "switched the Gauss–Markov accelerometer on about half the logs started ÷10: the "
            "estimates' shape follows the filter's model",
        }
    )
    informative = [configs[n] for n in ("informative_too_large", "informative_too_small") if n in configs]
    if informative:
        rates = [c["structure"]["gyro_exp_cosine_at_end"] for c in informative]
        wrong = [c["structure"]["accelerometer_exp_cosine_at_end"] for c in informative]
        rows.append(
            {
                "quantity": "in flight, a log that holds more of the structure (βτ_c 3, "
                "σ 5e-7 rad/s, 1/α 20 min, 0.01 m/s reference): logs whose gyro drift the "
                "loop ends modelling as exponential-cosine, started ×10 / ÷10",
                "ours": " / ".join(f"{100 * r:.0f} %" for r in rates)
                + " (the Gauss–Markov accelerometer taken as exponential-cosine: "
                + " / ".join(f"{100 * r:.0f} %" for r in wrong)
                + ")",
                "paper": "switches to the exponential-cosine model when the correlation "
                "calls for it",
                "note": "target ≥ 90 %; " + where,
                "status": "reproduced" if min(rates) >= 0.9 and max(wrong) <= 0.05 else "differs",
                "explanation": _information_text(informative[0]).removeprefix("; ")
                + "; the loop's candidates are the paper's rules on its own estimates: "
                + "; ".join(
                    f"×{c['start_factor']:g}: gyro ends {c['identified_final']['gyro']['median']['structure']} "
                    f"τ_c {c['identified_final']['gyro']['median']['correlation_time_s']:.3g} s, β "
                    f"{c['identified_final']['gyro']['median']['angular_frequency_rad_per_s']:.3g} rad/s"
                    for c in informative
                )
                + " (true 1/α 1200 s, β 2.5e-3 rad/s): rule (19)'s first zero and rule "
                "(21)'s lags before it, on estimates whose shape follows the filter's model, "
                "give a candidate that loses more than the margin the log holds",
            }
        )
    false_rate = configs["gauss_markov_truth"]["structure"]["gyro_exp_cosine_at_end"]
    rows.append(
        {
            "quantity": "in flight: logs with a Gauss–Markov gyro drift that the loop ends "
            "modelling as exponential-cosine",
            "ours": f"{100 * false_rate:.0f} %",
            "paper": "—",
            "note": "target ≤ 5 %; " + where + _transient_switches(configs),
            "status": "reproduced" if false_rate <= 0.05 else "differs",
        }
    )
    batch = configs["too_large"]["variants"].get("batch_loop")
    if batch is not None:
        ratio = batch["smoothed_variance_over_true_last_iteration"]
        bg = batch["final_models_median"]["gyro"]
        rows.append(
            {
                "quantity": "in flight ×10: the batch loop with the same structure test "
                f"({batch['iterations']} iterations over the whole log), settled outside ±3σ",
                "ours": f"{100 * batch['outside_3sigma_settled']:.2f} %",
                "paper": "—",
                "note": f"gyro {bg['structure']} τ_c {bg['correlation_time_s']:.3g} s; the "
                f"smoothed estimates keep {100 * ratio['gyro']:.0f} % (Δω) and "
                f"{100 * ratio['accelerometer']:.0f} % (Δa) of the true variance, and the fit "
                "ignores the smoothed covariances: the bias of the batch τ is that shrinkage",
                "status": "explained",
            }
        )
    return rows


def _in_flight_figure(figures, fl):
    configs = fl["configurations"]
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.4))
    for ax, name in zip(axes[:2], ("too_large", "too_small")):
        c = configs[name]
        for k, v in c["variants"].items():
            per_hour = 100 * np.asarray(v["outside_3sigma_per_hour"])
            ax.semilogy(np.arange(1, per_hour.size + 1), np.maximum(per_hour, 1e-2), label=k)
        ax.axhline(0.27, color="k", lw=0.8, ls=":")
        ax.set_xlabel("hour of the log")
        ax.set_ylabel("vertical error outside ±3σ [% of the hour]")
        ax.set_title(f"start: drift and diffusion ×{c['start_factor']:g}")
        ax.legend(fontsize=6)
        ax.grid(alpha=0.3, which="both")
    ax = axes[2]
    for name in ("too_large", "too_small", "gauss_markov_truth"):
        tr = configs[name]["identified_trajectory_median"]
        hours = tr["block_hours"] * np.arange(len(tr["gyro"]["correlation_time_s"]))
        ax.semilogy(hours, tr["gyro"]["correlation_time_s"], label=f"{name}: gyro 1/α")
    ax.axhline(3600, color="k", lw=0.8, ls=":")
    ax.set_xlabel("hour of the log")
    ax.set_ylabel("identified gyro correlation time [s] (median over logs)")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3, which="both")
    figures.save(
        fig,
        "in_flight.png",
        (
            f"In flight ({fl['runs']} simulated logs of {fl['hours']} h at 1 Hz per configuration; "
            "gyro drift exponential-cosine, 1/α = 3600 s, βτ_c = 2.5; accelerometer Gauss–Markov "
            "600 s). Left and middle: share of each hour with the vertical error outside ±3σ for "
            "the wrong starting model, the real-time identification loop (retuned every 30 min "
            "from a 24 h sliding window of its own estimates every 30 s), the same loop without "
            "the shrinkage correction, the batch loop, the simplified Sage–Husa adaptive filter "
            "and the oracle (an hour with none outside is drawn at 0.01 %); dotted: 0.27 %, a "
            "consistent filter. Right: the gyro correlation "
            "time the loop identifies over the log (median over logs); dotted: the truth."
        ),
    )


def make_figures(out_dir, result, rec, structure, traces) -> list[dict]:
    figures = Figures(out_dir)
    # Recovery distributions.
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    gm = rec["gauss_markov"]
    names = ["paper_r_positive", "paper_r_above_1_over_e", "least_squares", "maximum_likelihood"]
    labels = ["rule (15), r>0", "rule (15), r>1/e", "LS on R", "ML"]
    axes[0].boxplot([np.asarray(gm[k]["tau_samples"]) for k in names], tick_labels=labels)
    axes[0].axhline(GM_TRUE["tau"], color="k", ls="--", label="truth")
    axes[0].set_ylabel("estimated τ_c [s]")
    axes[0].set_title("Gauss-Markov")
    axes[0].legend()
    ec = rec["exp_cosine"]
    names = ["paper_rules_19_21", "least_squares", "maximum_likelihood"]
    labels = ["rules (19)-(21)", "LS on R", "ML"]
    axes[1].boxplot([np.asarray(ec[k]["alpha_samples"]) for k in names], tick_labels=labels)
    axes[1].axhline(EC_TRUE["alpha"], color="k", ls="--", label="truth")
    axes[1].set_ylabel("estimated α [1/s]")
    axes[1].set_title("exponential-cosine: decay")
    axes[1].legend()
    axes[2].boxplot([np.asarray(ec[k]["beta_samples"]) for k in names], tick_labels=labels)
    axes[2].axhline(EC_TRUE["beta"], color="k", ls="--", label="truth")
    axes[2].set_ylabel("estimated β [rad/s]")
    axes[2].set_title("exponential-cosine: frequency")
    axes[2].legend()
    for ax in axes:
        ax.tick_params(axis="x", labelsize=8)
        ax.grid(alpha=0.3)
    figures.save(
        fig,
        "recovery.png",
        (
            f"Parameter recovery over {rec['runs']} simulated records of {rec['samples_per_record']} samples at "
            f"{DT:g} s: Gauss-Markov σ = {GM_TRUE['sigma']:g}, τ_c = {GM_TRUE['tau']:g} s (left) and "
            f"exponential-cosine σ = {EC_TRUE['sigma']:g}, α = {EC_TRUE['alpha']:g} /s, β = {EC_TRUE['beta']:g} rad/s "
            f"(middle, right). Autocorrelation (11) up to lag {rec['max_lag']}. Rule (15) summed to the first "
            "r_j ≤ 0 (paper) or r_j ≤ 1/e; LS: Levenberg-Marquardt on R_0..R_K; ML: exact likelihood of the "
            "discrete state-space form. Boxes: quartiles; dashed: truth."
        ),
    )

    # Autocorrelation fits and residual whiteness (paper's Fig. 3).
    c = structure["curves"]
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.2))
    axes[0].plot(c["lag_s"], c["sample"], "k.", ms=2, label="sample r (11)")
    axes[0].plot(c["lag_s"], c["white+gauss_markov"], "tab:blue", label="white + exponential (ML)")
    axes[0].plot(c["lag_s"], c["white+exp_cosine"], "tab:red", label="white + exp-cosine (ML)")
    axes[0].set_xlabel("lag τ [s]")
    axes[0].set_ylabel("normalised autocorrelation r(τ)")
    axes[0].legend()
    axes[0].grid(alpha=0.3)
    resid = structure["residual_autocorrelation"]
    n_rec = structure["samples"]
    for name, color in (("white+gauss_markov", "tab:blue"), ("white+exp_cosine", "tab:red")):
        rho = np.asarray(resid[name])
        axes[1].plot(np.arange(1, rho.size + 1) * DT, rho, "o-", ms=3, color=color, label=name)
    band = 1.96 / np.sqrt(n_rec)
    axes[1].axhspan(-band, band, color="0.85", label="±1.96/√N (white)")
    axes[1].set_xlabel("lag [s]")
    axes[1].set_ylabel("autocorrelation of standardised innovations")
    axes[1].legend()
    axes[1].grid(alpha=0.3)
    table = {row["structure"]: row for row in structure["table"]}
    figures.save(
        fig,
        "structure_fig3.png",
        (
            "Structure identification (cf. paper Fig. 3) on one record of white (σ = 0.3) + exponential-cosine "
            "noise. Left: sample autocorrelation and the ML fits of the exponential and exponential-cosine "
            "structures. Right: autocorrelation of each fit's standardised Kalman innovations; the exponential "
            f"model leaves structure (Ljung-Box p = {table['white+gauss_markov']['ljung_box_p']:.2g}), the "
            f"exponential-cosine does not (p = {table['white+exp_cosine']['ljung_box_p']:.2g}). Grey band: "
            f"approximate 95 % band for white residuals (N = {n_rec}). "
            f"BIC chooses {structure['chosen']}."
        ),
    )

    # Kalman divergence (paper's Figs. 4 and 5).
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.2), sharey=False)
    for ax, name, title in (
        (
            axes[0],
            "wrong_model",
            f"drift ×{WRONG_DRIFT:g}, diffusion ×{WRONG_DIFFUSION:g} (cf. Fig. 4)",
        ),
        (axes[1], "identified", "identified by ML (cf. Fig. 5)"),
    ):
        err, sig = traces[name]
        t_h = np.arange(err.size) * DT / 3600
        ax.plot(t_h, err * 1e6, "k", lw=0.8, label="actual error Δδ")
        ax.plot(t_h, 3 * sig * 1e6, "tab:red", lw=1, label="±3σ_δ (filter)")
        ax.plot(t_h, -3 * sig * 1e6, "tab:red", lw=1)
        frac = result["kalman"][name]["fraction_outside_3sigma"]
        ax.set_title(f"{title}\noutside ±3σ: {100 * frac:.1f} % of time (mean of runs)")
        ax.set_xlabel("time [h]")
        ax.set_ylabel("vertical error δ − δ̂ [µrad]")
        ax.legend(fontsize=8)
        ax.grid(alpha=0.3)
    kal = result["kalman"]
    figures.save(
        fig,
        "kalman_fig4_fig5.png",
        (
            "Single-channel INS Kalman filter, velocity observations at 1 Hz (one Monte Carlo run shown; "
            f"percentages over {kal['runs']} runs of {kal['hours']:g} h). Truth: σ_a = 1e-3 m/s², τ_a = 600 s, "
            "σ_ω = 5e-8 rad/s, τ_ω = 3600 s, velocity noise 0.1 m/s. Left: the filter's sensor models have drift "
            f"×{WRONG_DRIFT:g} and diffusion ×{WRONG_DIFFUSION:g}; right: σ, τ identified by ML from "
            f"{kal['identification']['record_hours']:g} h static records of each sensor error."
        ),
    )

    # Allan deviation.
    al = result["allan"]
    fig, ax = plt.subplots(figsize=(7, 4.5))
    band = al["interval_1sigma_rad_per_s"]
    adev = np.asarray(al["adev_rad_per_s"])
    ax.errorbar(
        al["tau_s"],
        adev,
        yerr=[adev - np.asarray(band["lower"]), np.asarray(band["upper"]) - adev],
        fmt="o",
        ms=4,
        capsize=2,
        label="overlapping ADEV of the record, ±1σ (EDF)",
    )
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.loglog(al["tau_s"], al["theory_rad_per_s"], "k--", label="exact ADEV of the true model")
    taus = np.asarray(al["tau_s"])
    co = al["coefficients"]
    ax.loglog(
        taus, co["white_N"] / np.sqrt(taus), ":", label=f"slope −1/2: N = {co['white_N']:.2e}"
    )
    ax.loglog(
        taus,
        co["rate_random_walk_K"] * np.sqrt(taus / 3),
        ":",
        label=f"slope +1/2: K = {co['rate_random_walk_K']:.2e}",
    )
    ieee = al["ieee_terms"]
    shown = ", ".join(
        f"{k} {v['value']:.2e}" if v["supported"] else f"{k} < {v['upper']:.1e}"
        for k, v in ieee["terms"].items()
    )
    ax.loglog(
        taus, ieee["model_adev_rad_per_s"], "-", color="C3", lw=1.2, label=f"IEEE terms: {shown}"
    )
    ax.set_xlabel("averaging time τ [s]")
    ax.set_ylabel("Allan deviation [rad/s]")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3, which="both")
    figures.save(
        fig,
        "allan.png",
        (
            "Allan deviation (overlapping) of a simulated gyro-drift record at 1 Hz: white noise 1e-6 rad/s per "
            "sample + Gauss-Markov (2e-7 rad/s, 300 s) + rate random walk (q = 1e-14 rad²/s³). Dotted: the "
            "fitted standard slopes (−1/2 angle random walk N, +1/2 rate random walk K); red: the IEEE "
            "Std 952 five-term fit (Q, N, B, K, R; weighted non-negative least squares, 95 % "
            "parametric-bootstrap intervals in the result, an unsupported term shown as an upper "
            "bound; B absorbs the Gauss-Markov hump); dashed: the exact "
            "Allan deviation of the true model (autocovariance formula plus K²τ/3). Error bars: ±1σ χ² "
            "intervals from Greenhall's equivalent degrees of freedom for the noise identified at each τ "
            f"(allantools); they contain the true model's ADEV at {band['true_adev_inside']} of "
            f"{band['n_taus']} τ (nominal 68 % each; the τ of one record are correlated)."
        ),
    )
    _in_flight_figure(figures, result["in_flight"])
    return figures.entries


def main(argv=None) -> int:
    return study_main(run, __file__, __doc__, argv=argv)


if __name__ == "__main__":
    sys.exit(main())
