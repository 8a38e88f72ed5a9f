"""Study: in-flight identification of the scale factor K_a from a test-signal step response.

Reproduces docs/models.md §1 (Mironov, Fominov, Maletin): the oscillatory method's δK_a = 0.141 %
and the aperiodic method's δK_a = 0.682 %, decomposes the oscillatory error into its
causes, sweeps δK_a against ξ, noise ε and the torquer lag T_dm for both methods (the
paper's Fig. 3 and Fig. 5) as vmapped Monte Carlo batches sharded across devices, checks
the autodiff slope dδK_a/dξ, dδK_a/dT_dm against the sweep, and compares the paper's
graph-analytic method with a least-squares fit of the step response.

Writes OUT/result.json and PNG figures. Run: `python studies/scale_factor_identification.py
[--out DIR] [--quick]` (float64 throughout: δK_a at the 0.1 % level and crossing times to
1e-9 s need it).
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
from accel_jax.report import (  # noqa: E402
    Figures,
    identification_figure,
    provenance,
    study_main,
    study_run,
    write_json_atomic,
)

STUDY = "scale_factor_identification"

# --- assumptions (the paper states none of these; ours are recorded in the output) -------
SAMPLE_RATE = 1e6  # Hz
IDENTIFY_SEED = 7  # the noise of the one record drawn as `accel-jax identify` shows it
OSC_DURATION = 10e-3  # s: the response has decayed to ~2e-8 of the step (envelope e^{-ξt/T})
XI_SWEEP_DURATION = 60e-3  # s: at ξ = 0.1 the envelope needs ~18 T/ξ ≈ 53 ms to reach 1e-8
APER_DURATION = 20e-3  # s: ~18 slow time constants T3 ≈ 1.12 ms
TAIL_FRACTION = 0.2  # steady state = mean of the last 20 % of the record
TEST_VOLTAGE = 1.0  # V, the identification step
STOP_VOLTAGE = 5.0  # V, ±U_test driving the pendulum onto its stops for eq. (11)
CROSSING = "linear"  # steady-state crossings by linear interpolation between samples
EXTREMUM = "parabolic"  # A1, A2 by 3-point parabolic peak interpolation
# Aperiodic slope by a Savitzky-Golay local cubic over 101 samples (0.1 ms ≈ 1.3 T4): on the
# noise-free reference record it moves δK_a by −0.02 % against raw central differences, and at
# ε = 1e-5 V it cuts the spread from ±10.6 % to ±0.8 % (a 31-sample moving average of the
# central difference: +0.35 % bias, ±2.5 %). 201 samples: −0.33 % bias; 401: −5 %.
APER_DERIVATIVE = "savgol"
APER_SMOOTHING = 101


def _grid(duration: float, rate: float) -> jnp.ndarray:
    n = int(round(duration * rate)) + 1
    return jnp.arange(n, dtype=jnp.float64) / rate


# --- one trajectory ---------------------------------------------------------------------


def _record(params, key, ts, noisy=True):
    return aj.simulate_linear(params, ts, TEST_VOLTAGE, key=key if noisy else None)


def _outcome(scale_factor, result, params):
    """(δK_a [%], whether the method succeeded) for one record."""
    ok = result == aj.IdentificationResult.successful
    return aj.relative_error_percent(scale_factor, aj.scale_factor(params)), ok


def _method_error(identify, params, key, gamma, gain, *, ts, noisy, **options):
    """δK_a [%] of `identify` (the oscillatory or the aperiodic method, with its own
    `options`) on one simulated record, and whether it succeeded."""
    est = identify(
        ts,
        _record(params, key, ts, noisy),
        pickoff_amplifier_gain=gain,
        shape_factor=gamma,
        tail_fraction=TAIL_FRACTION,
        throw=False,
        **options,
    )
    return _outcome(est.scale_factor, est.result, params)


def _oscillatory_error(params, key, gamma, gain, *, ts, crossing, extremum, noisy, period="full"):
    """δK_a [%] of the oscillatory method on one simulated record, and whether it succeeded."""
    return _method_error(
        aj.identify_oscillatory, params, key, gamma, gain, ts=ts, noisy=noisy,
        crossing=crossing, extremum=extremum, period=period,
    )


def _aperiodic_error(params, key, gamma, gain, lag, *, ts, noisy, smoothing):
    """The same for the aperiodic method, with the lag correction (16) `lag` [s]."""
    return _method_error(
        aj.identify_aperiodic, params, key, gamma, gain, ts=ts, noisy=noisy,
        lag_correction=lag, derivative=APER_DERIVATIVE, smoothing_window=smoothing,
    )


def _fit_error(params, key, gamma, gain, known_filter=None, *, ts, order):
    """The same for a least-squares fit. Order 3 takes `known_filter` (traced, so that both
    cases share one compiled fit): true, the fit is given the design T_f and K_test (as a
    designer knows them); false, it ignores T_f and takes K = 1."""
    extra = {}
    if order == 3:
        extra = dict(
            feedback_fraction=jnp.where(known_filter, aj.closed_loop_test_gain(params), 1.0),
            filter_time_constant=jnp.where(known_filter, params.filter_time_constant, 0.0),
        )
    fit = aj.fit_step_response(ts, _record(params, key, ts), order=order, throw=False, **extra)
    kahat, _ = aj.scale_factor_from_fit(fit, gain, gamma)
    return _outcome(kahat, fit.result, params)


# One kernel object per configuration, shared by every sweep that uses it: `aj.sweep`
# compiles once per (kernel, shape), and a fresh `functools.partial` is a new kernel.
# Every Monte Carlo sweep is cut into chunks of SWEEP_CHUNK trajectories (the batch padded
# up to a whole chunk), so the headline and the parameter sweeps run one compiled shape
# instead of one per batch size (a batch smaller than a chunk, as the fit comparison's 8
# records in --quick, runs at its own size).
SWEEP_CHUNK = 16


@functools.cache
def _kernel(method: str, duration: float, **static):
    """The per-trajectory error function of `method` ('oscillatory', 'aperiodic', 'fit') on
    a 1 MHz record of `duration` [s], with its static options."""
    ts = _grid(duration, SAMPLE_RATE)
    if method == "oscillatory":
        return functools.partial(
            _oscillatory_error, ts=ts, crossing=CROSSING, extremum=EXTREMUM, **static
        )
    if method == "aperiodic":
        return functools.partial(_aperiodic_error, ts=ts, smoothing=APER_SMOOTHING, **static)
    return functools.partial(_fit_error, ts=ts, **static)


# --- k_dp·k_y from the stops (eq. 11), nonlinear simulation ----------------------------


def identify_pickoff_gain(params, *, key, duration=3e-3, rate=SAMPLE_RATE, h_design=None):
    """k_dp k_y from ±STOP_VOLTAGE driving the pendulum onto its stops (eq. 11).

    The settled output at each stop is the mean of the last half of the record (the noise
    averages out); eq. (11) divides by `h_design` [m], the stop displacement the user
    believes (default the device's own, `params.stop_displacement`).
    """
    ts = _grid(duration, rate)
    k_plus, k_minus = jax.random.split(key)
    u_plus = aj.simulate_nonlinear(params, ts, STOP_VOLTAGE, key=k_plus)
    u_minus = aj.simulate_nonlinear(params, ts, -STOP_VOLTAGE, key=k_minus)
    half = ts.shape[0] // 2
    h = params.stop_displacement if h_design is None else h_design
    return aj.pickoff_gain_from_stops(jnp.mean(u_plus[half:]), jnp.mean(u_minus[half:]), h, h)


# Stop-displacement errors of the tolerance sweep: the device's stops at h_max (1 + e) while
# eq. (11) uses the design h_max.
STOP_ERRORS = (-0.02, -0.01, -0.005, 0.0, 0.005, 0.01, 0.02)


def stop_tolerance_sweep(ref, gain_true) -> dict:
    """δK_a of k_dp k_y from the stops when the real stops sit at h_max (1 + e): eq. (11)
    divides outputs ∝ h_max (1 + e) by the design h_max, so K̂_a (∝ k_dp k_y, eq. (7))
    carries (1 + e) one for one. Noise-free nonlinear records; δK_a here is that of the
    gain alone (the oscillatory method's own error is the decomposition's business)."""
    h = float(ref.stop_displacement)

    @jax.jit
    def gain_for(error):
        device = eqx.tree_at(lambda p: p.stop_displacement, ref, h * (1 + error))
        noiseless = eqx.tree_at(lambda p: p.noise_std, device, jnp.float64(0.0))
        return identify_pickoff_gain(noiseless, key=jax.random.key(0), h_design=h)

    errors = np.asarray(STOP_ERRORS)
    gains = np.asarray([float(gain_for(jnp.float64(e))) for e in errors])
    dka = 100 * (gains / gain_true - 1)
    slope = float(np.polyfit(100 * errors, dka, 1)[0])
    return {
        "stop_error_percent": (100 * errors).tolist(),
        "dKa_percent": dka.tolist(),
        "slope_percent_per_percent": slope,
        "note": "the real stops at h_max (1 + e), eq. (11) with the design h_max; "
        "noise-free nonlinear records (±5 V onto the stops, 3 ms at 1 MHz)",
    }


# --- batched Monte Carlo ---------------------------------------------------------------


def _params_batch(base: aj.ServoParams, field: str, values: np.ndarray, seeds: int):
    """A batch of devices: each swept value repeated `seeds` times (value-major)."""
    repeated = jnp.repeat(jnp.asarray(values, dtype=jnp.float64), seeds)
    return eqx.filter_vmap(lambda v: eqx.tree_at(lambda p: getattr(p, field), base, v))(repeated)


def _summarise(errors: np.ndarray, codes: np.ndarray, n_values: int, seeds: int) -> dict:
    errors = errors.reshape(n_values, seeds)
    ok = codes.reshape(n_values, seeds).astype(bool)
    count = ok.sum(axis=1)
    safe = np.where(ok, errors, 0.0)
    mean = safe.sum(axis=1) / np.maximum(count, 1)
    var = (np.where(ok, errors - mean[:, None], 0.0) ** 2).sum(axis=1) / np.maximum(count, 1)
    rms = np.sqrt((safe**2).sum(axis=1) / np.maximum(count, 1))
    none = count == 0  # no usable record at this point: reported as null, not as a number
    return {
        "mean": np.where(none, np.nan, mean).tolist(),
        "std": np.where(none, np.nan, np.sqrt(var)).tolist(),
        "rms": np.where(none, np.nan, rms).tolist(),
        "usable_fraction": ok.mean(axis=1).tolist(),
    }


def _traced(*values):
    """Shared scalars (γ, k_dp k_y, lag) as float64 arrays: as Python floats they would be
    static to the compiled sweep, and every new value would compile it again."""
    return tuple(jnp.asarray(v, jnp.float64) for v in values)


def _run_sweep(one, base, field, values, seeds, key, shared_args):
    shared_args = _traced(*shared_args)
    batch = _params_batch(base, field, values, seeds)
    keys = jax.random.split(key, len(values) * seeds)
    errors, codes = aj.sweep(
        one,
        batch,
        keys,
        *shared_args,
        in_axes=(0, 0) + (None,) * len(shared_args),
        chunk_size=SWEEP_CHUNK,
    )
    return _summarise(np.asarray(errors), np.asarray(codes), len(values), seeds)


def _mu_for(base: aj.ServoParams, ratios) -> np.ndarray:
    """μ giving damping ratio ξ (eq. (5) solved for μ; `aj.damping_for_ratio`)."""
    return np.asarray(aj.damping_for_ratio(base, ratios))


# --- the study -------------------------------------------------------------------------


def _devices(params: aj.ServoParams | None) -> tuple[aj.ServoParams, aj.ServoParams, str]:
    """The oscillatory and aperiodic devices: the docs/models.md pair, or a user's device and its
    twin with the damping μ changed to the reference pair's other damping ratio."""
    if params is None:
        return aj.ServoParams.reference(), aj.ServoParams.reference_aperiodic(), "reference"
    xi = float(aj.damping_ratio(params))
    other = {
        True: float(aj.damping_ratio(aj.ServoParams.reference_aperiodic())),
        False: float(aj.damping_ratio(aj.ServoParams.reference())),
    }[xi < 1]
    twin = eqx.tree_at(
        lambda p: p.damping, params, jnp.asarray(_mu_for(params, other), jnp.float64)
    )
    label = f"user's device (ξ = {xi:.3g}; its twin with ξ = {other:.3g} for the other method)"
    return (params, twin, label) if xi < 1 else (twin, params, label)


@study_run(compile_bound_when_quick=False)
def run(
    out_dir: Path,
    *,
    quick: bool = False,
    seed: int = 20261122,
    params: aj.ServoParams | None = None,
) -> dict:
    """Run the study; write OUT/result.json and figures; return the result dict.

    `params`: a device to study instead of the docs/models.md reference pair (its twin with the
    other damping regime is made by changing μ); the published numbers belong to the
    reference device only."""
    out_dir = Path(out_dir)
    started = time.perf_counter()
    seeds = 16 if quick else 64
    key = jax.random.key(seed)
    k_stop, k_head, k_osc, k_ap, k_fit = jax.random.split(key, 5)

    ref, ref_ap, device_label = _devices(params)
    gain_true = float(ref.pickoff_gain * ref.amplifier_gain)
    # --quick is compile-bound: the parts that compile programs to run them once or on a few
    # records compile with most XLA optimisations off (accel_jax._runtime.fast_compile); the Monte
    # Carlo kernels (headline, sweeps), run on many chunks, keep the default. Measured on
    # the 2-core CPU, quick, cache off: 59 → 42 CPU-s (the sweeps alone, if compiled
    # fast too, take 26 CPU-s instead of 12).
    fast = functools.partial(fast_compile, quick)
    with fast():
        gain_stops = float(identify_pickoff_gain(ref, key=k_stop))
    gamma_exact = float(aj.shape_factor(ref))
    ts_osc = _grid(OSC_DURATION, SAMPLE_RATE)
    lag_ref = float(ref.filter_time_constant + ref.torquer_time_constant)

    osc = _kernel("oscillatory", OSC_DURATION, noisy=True)
    aper = _kernel("aperiodic", APER_DURATION, noisy=True)

    # Headline numbers: the full reference device, noise, Monte Carlo over seeds.
    def headline(one, base, gamma, *extra, key):
        keys = jax.random.split(key, seeds)
        batch = _params_batch(base, "damping", np.array([float(base.damping)]), seeds)
        errors, codes = aj.sweep(
            one,
            batch,
            keys,
            *_traced(gamma, gain_stops),
            # The lag correction per record, as the aperiodic sweeps pass it: one program.
            *(jnp.full(seeds, value, jnp.float64) for value in extra),
            in_axes=(0, 0, None, None) + (0,) * len(extra),
            chunk_size=SWEEP_CHUNK,
        )
        s = _summarise(np.asarray(errors), np.asarray(codes), 1, seeds)
        return {k: v[0] for k, v in s.items()}

    head = {
        "oscillatory_gamma_exact": headline(osc, ref, gamma_exact, key=k_head),
        "oscillatory_gamma_3_4": headline(osc, ref, aj.PAPER_GAMMA, key=k_head),
        "aperiodic_gamma_exact_lag_compensated": headline(
            aper, ref_ap, gamma_exact, lag_ref, key=k_head
        ),
        "aperiodic_gamma_3_4_lag_compensated": headline(
            aper, ref_ap, aj.PAPER_GAMMA, lag_ref, key=k_head
        ),
        "aperiodic_gamma_3_4_uncompensated": headline(
            aper, ref_ap, aj.PAPER_GAMMA, 0.0, key=k_head
        ),
    }

    with fast():
        decomposition = {
            "oscillatory": decompose_oscillatory(ref, gain_true, gain_stops),
            "stop_tolerance": stop_tolerance_sweep(ref, gain_true),
            "aperiodic": decompose_aperiodic(ref_ap, gain_true),
            "oscillatory_candidates_for_0_141": oscillatory_candidates(ref, gain_true),
        }
    sweeps = run_sweeps(ref, ref_ap, gain_stops, gamma_exact, seeds, k_osc, k_ap, quick)
    with fast():
        gradients = gradient_checks(ref, gain_true, gamma_exact)
        fits = compare_fit(ref, gain_true, gamma_exact, 8 if quick else 32, k_fit)

    result = {
        "title": "Scale-factor identification from a test-signal step (Mironov, Fominov & Maletin)",
        "dKa_percent": {
            "oscillatory": head["oscillatory_gamma_3_4"]["mean"],
            "aperiodic": head["aperiodic_gamma_3_4_lag_compensated"]["mean"],
        },
        "headline": head,
        "pickoff_amplifier_gain": {
            "true_V_per_m": gain_true,
            "from_stops_V_per_m": gain_stops,
            "relative_error": gain_stops / gain_true - 1,
        },
        "decomposition": decomposition,
        "sweeps": sweeps,
        "gradients": gradients,
        "least_squares_fit": fits,
        "assumptions": {
            "sample_rate_Hz": SAMPLE_RATE,
            "record_s": {"oscillatory": OSC_DURATION, "aperiodic": APER_DURATION},
            "steady_state": f"mean of the last {TAIL_FRACTION:.0%} of the record",
            "crossing_detection": CROSSING + " interpolation between samples",
            "extremum_detection": EXTREMUM,
            "aperiodic_slope": f"{APER_DERIVATIVE} (local cubic least squares) over {APER_SMOOTHING} samples",
            "test_voltage_V": TEST_VOLTAGE,
            "initial_state": "settled under M_v (constant), test voltage switched on at t=0",
            "simulator": "exact ZOH discretisation (linear loop; 1 V never reaches the stops)",
            "kdp_ky": f"from ±{STOP_VOLTAGE} V onto the stops (eq. 11), diffrax nonlinear loop",
            "gamma": "3/4 (paper) unless marked exact (m l²/J)",
            "monte_carlo_seeds_per_point": seeds,
            "precision": "float64",
            "dKa_definition": "100·(K̂_a − K_a)/K̂_a",
            "device": device_label,
        },
        "provenance": provenance(
            seeds={"root": seed},
            precision="float64",
            extra={
                "params": ref.as_dict(),
                "params_aperiodic": ref_ap.as_dict(),
                "compiled_with_most_xla_optimisations_off": (
                    "stop identification, decompositions, gradient checks, fit comparison"
                    if quick
                    else "nothing"
                ),
                "wall_time_s": time.perf_counter() - started,
            },
        ),
    }
    result["summary"] = _summary_rows(result)
    result["figures"] = make_figures(out_dir, result, ref, gain_true, gamma_exact, ts_osc)
    result["provenance"]["wall_time_s"] = time.perf_counter() - started
    write_json_atomic(out_dir / "result.json", result)
    return result


def decompose_oscillatory(ref, gain_true, gain_stops) -> dict:
    """δK_a of the oscillatory method, noise-free unless stated, one cause at a time."""
    gamma_exact = float(aj.shape_factor(ref))
    ideal = eqx.tree_at(
        lambda p: (p.torquer_time_constant, p.filter_time_constant),
        ref,
        (jnp.float64(0.0), jnp.float64(0.0)),
    )

    def error(
        params,
        *,
        gamma=gamma_exact,
        gain=gain_true,
        rate=10e6,
        crossing="linear",
        extremum=EXTREMUM,
        duration=OSC_DURATION,
        key=None,
        from_rest=False,
        moment_drift=0.0,
    ):
        ts = _grid(duration, rate)
        # A drifting external moment: M_v(t) = M_v (1 + drift · t/duration).
        moment = params.external_moment * (1.0 + moment_drift * ts / ts[-1])
        u = aj.simulate_linear(
            params,
            ts,
            TEST_VOLTAGE,
            external_moment=moment,
            key=key,
            initial_state=jnp.zeros(4) if from_rest else None,
        )
        est = aj.identify_oscillatory(
            ts,
            u,
            pickoff_amplifier_gain=gain,
            shape_factor=gamma,
            tail_fraction=TAIL_FRACTION,
            crossing=crossing,
            extremum=extremum,
            throw=False,
        )
        if not bool(est.result == aj.IdentificationResult.successful):
            return float("nan")
        return float(aj.relative_error_percent(est.scale_factor, aj.scale_factor(params)))

    cases = {
        "ideal (T_dm = T_f = 0, γ exact, 10 MHz, no noise)": error(ideal),
        "γ rounded to 3/4": error(ideal, gamma=aj.PAPER_GAMMA),
        "T_dm = 1e-5 s": error(
            eqx.tree_at(lambda p: p.torquer_time_constant, ideal, ref.torquer_time_constant)
        ),
        "T_f = 1e-5 s": error(
            eqx.tree_at(lambda p: p.filter_time_constant, ideal, ref.filter_time_constant)
        ),
        "sampling 1 MHz": error(ideal, rate=1e6),
        "sampling 1 MHz, nearest-sample crossings": error(ideal, rate=1e6, crossing="nearest"),
        "sampling 1 MHz, max-sample extrema": error(ideal, rate=1e6, extremum="sample"),
        "record 5 ms instead of 10 ms": error(ideal, duration=5e-3),
        "k_dp k_y from the stops (eq. 11)": error(ideal, gain=gain_stops),
        "noise ε = 1e-5 V (one seed)": error(ideal, key=jax.random.key(1)),
        "M_v switched on with the test step (device not settled)": error(ideal, from_rest=True),
        "M_v drifting by +1 % over the record": error(ideal, moment_drift=0.01),
        "all: reference device, γ exact, 1 MHz": error(ref, rate=1e6, gain=gain_stops),
        "all: reference device, γ = 3/4, 1 MHz": error(
            ref, rate=1e6, gain=gain_stops, gamma=aj.PAPER_GAMMA
        ),
        "all: reference device, γ = 3/4, 10 MHz": error(
            ref, rate=10e6, gain=gain_stops, gamma=aj.PAPER_GAMMA
        ),
    }
    with_lag = eqx.tree_at(lambda p: p.torquer_time_constant, ideal, ref.torquer_time_constant)
    return {
        "dKa_percent": cases,
        "T_dm_row_predicted_from_dominant_poles": dominant_pole_prediction(
            with_lag, gamma_exact, gain_true
        ),
        "note": "each row adds one cause to the ideal row (noise-free, 10 MHz unless marked)",
    }


def dominant_pole_prediction(params, gamma, gain) -> float:
    """δK_a [%] the oscillatory method converges to (noise-free, fine sampling), predicted
    independently of the simulation from the dominant pole pair
    (`aj.dominant_pole_scale_factor`)."""
    estimate = aj.dominant_pole_scale_factor(params, gamma, gain)
    return 100.0 * (estimate - float(aj.scale_factor(params))) / estimate


def oscillatory_candidates(ref, gain_true) -> list[dict]:
    """Which unstated assumptions reproduce the paper's 0.141 %? Noise-free δK_a over the
    grid γ × T_dm × T_f × sampling rate × crossing detection, sorted by distance to 0.141."""
    rows = []
    gamma_exact = float(aj.shape_factor(ref))
    for rate in (1e6, 10e6):
        ts = _grid(OSC_DURATION, rate)
        for crossing in ("linear", "nearest"):
            for t_dm in (0.0, float(ref.torquer_time_constant)):
                for t_f in (0.0, float(ref.filter_time_constant)):
                    params = eqx.tree_at(
                        lambda p: (p.torquer_time_constant, p.filter_time_constant),
                        ref,
                        (jnp.float64(t_dm), jnp.float64(t_f)),
                    )
                    u = aj.simulate_linear(params, ts, TEST_VOLTAGE)
                    for gname, gamma in (("m l²/J", gamma_exact), ("3/4", aj.PAPER_GAMMA)):
                        est = aj.identify_oscillatory(
                            ts,
                            u,
                            pickoff_amplifier_gain=gain_true,
                            shape_factor=gamma,
                            tail_fraction=TAIL_FRACTION,
                            crossing=crossing,
                            extremum=EXTREMUM,
                            throw=False,
                        )
                        rows.append(
                            {
                                "gamma": gname,
                                "T_dm_s": t_dm,
                                "T_f_s": t_f,
                                "sample_rate_Hz": rate,
                                "crossing": crossing,
                                "dKa_percent": float(
                                    aj.relative_error_percent(
                                        est.scale_factor, aj.scale_factor(params)
                                    )
                                ),
                            }
                        )
    return sorted(rows, key=lambda r: abs(r["dKa_percent"] - 0.141))


def decompose_aperiodic(ref_ap, gain_true) -> dict:
    """δK_a of the aperiodic method (noise-free, 1 MHz, true k_dp k_y), lag by lag, with and
    without the compensation (16), for both γ."""
    ts = _grid(APER_DURATION, SAMPLE_RATE)
    gamma_exact = float(aj.shape_factor(ref_ap))

    def error(t_dm, t_f, lag, gamma, from_rest=False, derivative="central", window=1):
        params = eqx.tree_at(
            lambda p: (p.torquer_time_constant, p.filter_time_constant),
            ref_ap,
            (jnp.float64(t_dm), jnp.float64(t_f)),
        )
        u = aj.simulate_linear(
            params, ts, TEST_VOLTAGE, initial_state=jnp.zeros(4) if from_rest else None
        )
        est = aj.identify_aperiodic(
            ts,
            u,
            pickoff_amplifier_gain=gain_true,
            shape_factor=gamma,
            lag_correction=lag,
            tail_fraction=TAIL_FRACTION,
            derivative=derivative,
            smoothing_window=window,
            throw=False,
        )
        if not bool(est.result == aj.IdentificationResult.successful):
            return float("nan")
        return float(aj.relative_error_percent(est.scale_factor, aj.scale_factor(params)))

    t_dm, t_f = float(ref_ap.torquer_time_constant), float(ref_ap.filter_time_constant)
    rows = {
        "no lags": (0.0, 0.0, 0.0),
        "T_dm only, uncompensated": (t_dm, 0.0, 0.0),
        "T_dm only, compensated (16)": (t_dm, 0.0, t_dm),
        "T_f only, uncompensated": (0.0, t_f, 0.0),
        "T_f only, compensated (16)": (0.0, t_f, t_f),
        "T_dm and T_f, uncompensated": (t_dm, t_f, 0.0),
        "T_dm and T_f, only T_f compensated": (t_dm, t_f, t_f),
        "T_dm and T_f, compensated (16)": (t_dm, t_f, t_dm + t_f),
    }
    table = {
        name: {"gamma_exact": error(*args, gamma_exact), "gamma_3_4": error(*args, 0.75)}
        for name, args in rows.items()
    }
    table["T_dm and T_f, compensated, M_v switched on with the step"] = {
        "gamma_exact": error(t_dm, t_f, t_dm + t_f, gamma_exact, from_rest=True),
        "gamma_3_4": error(t_dm, t_f, t_dm + t_f, 0.75, from_rest=True),
    }
    # The smoothing the noisy runs use, on its own (no lags) and with everything else.
    savgol = dict(derivative=APER_DERIVATIVE, window=APER_SMOOTHING)
    for name, args in (
        ("no lags, Savitzky-Golay slope", (0.0, 0.0, 0.0)),
        ("T_dm and T_f, compensated (16), Savitzky-Golay slope", (t_dm, t_f, t_dm + t_f)),
    ):
        table[name] = {
            "gamma_exact": error(*args, gamma_exact, **savgol),
            "gamma_3_4": error(*args, 0.75, **savgol),
        }
    return {
        "dKa_percent": table,
        "note": (
            "noise-free, 1 MHz, true k_dp k_y; slope by central differences (the paper's "
            "algorithm exactly) except the rows marked Savitzky-Golay (local cubic over "
            f"{APER_SMOOTHING} samples, the slope used on noisy records)"
        ),
    }


def run_sweeps(ref, ref_ap, gain, gamma, seeds, k_osc, k_ap, quick) -> dict:
    n = 7 if quick else 15
    osc = _kernel("oscillatory", OSC_DURATION, noisy=True)
    lag_ref = float(ref.filter_time_constant + ref.torquer_time_constant)
    keys = jax.random.split(k_osc, 6)
    keys_ap = jax.random.split(k_ap, 6)

    xi = np.linspace(0.1, 0.95, n)
    noise = np.logspace(-6, -2, n)
    tdm = np.linspace(0.0, 1e-4, n)
    out = {"oscillatory": {}, "aperiodic": {}}
    osc_long = _kernel("oscillatory", XI_SWEEP_DURATION, noisy=True)
    out["oscillatory"]["damping_ratio"] = {
        "x": xi.tolist(),
        "record_s": XI_SWEEP_DURATION,
        **_run_sweep(osc_long, ref, "damping", _mu_for(ref, xi), seeds, keys[0], (gamma, gain)),
    }
    # The same records (same keys) with ω from the half period 2(t_mid − t1): the crossing
    # t2 is shallow at high ξ, so the paper's t2 − t1 scatters there.
    out["oscillatory"]["damping_ratio_half_period"] = {
        "x": xi.tolist(),
        "record_s": XI_SWEEP_DURATION,
        **_run_sweep(
            _kernel("oscillatory", XI_SWEEP_DURATION, noisy=True, period="half"),
            ref,
            "damping",
            _mu_for(ref, xi),
            seeds,
            keys[0],
            (gamma, gain),
        ),
    }
    out["oscillatory"]["noise_V"] = {
        "x": noise.tolist(),
        **_run_sweep(osc, ref, "noise_std", noise, seeds, keys[1], (gamma, gain)),
    }
    out["oscillatory"]["torquer_time_constant_s"] = {
        "x": tdm.tolist(),
        **_run_sweep(osc, ref, "torquer_time_constant", tdm, seeds, keys[2], (gamma, gain)),
    }
    # Noise-free predictions from the dominant pole pair, beside the Monte Carlo curves.
    for name, field, values in (
        ("damping_ratio", "damping", _mu_for(ref, xi)),
        ("torquer_time_constant_s", "torquer_time_constant", tdm),
        ("noise_V", "noise_std", noise),
    ):
        out["oscillatory"][name]["predicted_noise_free"] = [
            dominant_pole_prediction(
                eqx.tree_at(lambda p, f=field: getattr(p, f), ref, jnp.float64(v)), gamma, gain
            )
            for v in values
        ]

    ratio = np.linspace(1.05, 3.0, n)  # T1/(2 T2) = ξ
    aper = _kernel("aperiodic", APER_DURATION, noisy=True)
    clean = _kernel("aperiodic", APER_DURATION, noisy=False)

    def aperiodic_sweep(field, values, key, lag):
        """Noisy Monte Carlo and the noise-free curve; `lag` is a scalar or per-value."""
        lag = jnp.broadcast_to(jnp.asarray(lag, dtype=jnp.float64), (len(values),))
        batch = _params_batch(ref_ap, field, values, seeds)
        keys = jax.random.split(key, len(values) * seeds)
        e, c = aj.sweep(
            aper,
            batch,
            keys,
            *_traced(gamma, gain),
            jnp.repeat(lag, seeds),
            in_axes=(0, 0, None, None, 0),
            chunk_size=SWEEP_CHUNK,
        )
        summary = {
            "x": list(map(float, values)),
            **_summarise(np.asarray(e), np.asarray(c), len(values), seeds),
        }
        batch1 = _params_batch(ref_ap, field, values, 1)
        e1, c1 = aj.sweep(
            clean,
            batch1,
            jax.random.split(key, len(values)),
            *_traced(gamma, gain),
            lag,
            in_axes=(0, 0, None, None, 0),
        )
        summary["noise_free"] = np.where(np.asarray(c1), np.asarray(e1), np.nan).tolist()
        return summary

    out["aperiodic"]["T1_over_2T2"] = aperiodic_sweep(
        "damping", _mu_for(ref_ap, ratio), keys_ap[0], lag_ref
    )
    out["aperiodic"]["T1_over_2T2"]["x"] = ratio.tolist()
    out["aperiodic"]["noise_V"] = aperiodic_sweep("noise_std", noise, keys_ap[1], lag_ref)
    # The compensation (16) uses the true T_dm (known and constant, as the paper requires).
    out["aperiodic"]["torquer_time_constant_s_compensated"] = aperiodic_sweep(
        "torquer_time_constant", tdm, keys_ap[2], tdm + float(ref_ap.filter_time_constant)
    )
    out["aperiodic"]["torquer_time_constant_s_uncompensated"] = aperiodic_sweep(
        "torquer_time_constant", tdm, keys_ap[2], 0.0
    )
    return out


def gradient_checks(ref, gain, gamma) -> dict:
    """dδK_a/dξ and dδK_a/dT_dm by autodiff through simulate + identify (noise-free, 1 MHz),
    against central differences of the same function."""
    ts = _grid(OSC_DURATION, SAMPLE_RATE)

    def error_of(params):
        e, _ = _oscillatory_error(
            params,
            jax.random.key(0),
            gamma,
            gain,
            ts=ts,
            crossing=CROSSING,
            extremum=EXTREMUM,
            noisy=False,
        )
        return e

    k = float(aj.loop_stiffness(ref))
    J = float(ref.moment_of_inertia)

    def by_both(x):
        # x = [ξ, T_dm]: one compiled value-and-gradient serves both derivatives and the
        # central differences (four programs before: a gradient and a value per variable).
        params = eqx.tree_at(
            lambda p: (p.damping, p.torquer_time_constant), ref, (2 * x[0] * jnp.sqrt(J * k), x[1])
        )
        return error_of(params)

    value_and_grad = jax.jit(jax.value_and_grad(by_both))
    x0 = np.array([float(aj.damping_ratio(ref)), float(ref.torquer_time_constant)])
    _, grad = value_and_grad(jnp.asarray(x0))
    out = {}
    for i, (name, h) in enumerate(
        (
            ("d_dKa_d_damping_ratio_percent", 1e-6),
            ("d_dKa_d_torquer_time_constant_percent_per_s", 1e-9),
        )
    ):
        step = np.zeros(2)
        step[i] = h
        plus, minus = (float(value_and_grad(jnp.asarray(x))[0]) for x in (x0 + step, x0 - step))
        fd = (plus - minus) / (2 * h)
        out[name] = {
            "at": float(x0[i]),
            "autodiff": float(grad[i]),
            "central_difference": fd,
            "step": h,
        }
    out["note"] = (
        "Local derivatives of the identification on one sampled record. δK_a(ξ) is continuous "
        "but has kinks wherever a sample crosses the steady-state line (every ~3e-4 in ξ at "
        "1 MHz), so the local slope swings around the smooth trend; finite differences agree "
        "only with steps that do not straddle a kink. The smooth design trend is the "
        "dominant-pole prediction in the sweeps."
    )
    return out


def compare_fit(ref, gain, gamma, seeds, key) -> dict:
    """Graph-analytic method vs least-squares fits (2nd and 3rd order) on the same records."""
    keys = jax.random.split(key, seeds)
    batch = _params_batch(ref, "damping", np.array([float(ref.damping)]), seeds)
    out = {}
    shared = _traced(gamma, gain)
    e, c = aj.sweep(
        _kernel("oscillatory", OSC_DURATION, noisy=True),
        batch,
        keys,
        *shared,
        in_axes=(0, 0, None, None),
        chunk_size=SWEEP_CHUNK,
    )
    out["graph_analytic"] = {
        k: v[0] for k, v in _summarise(np.asarray(e), np.asarray(c), 1, seeds).items()
    }
    for name, order, known in (
        ("fit_order_2", 2, False),
        ("fit_order_3", 3, False),
        ("fit_order_3_known_filter", 3, True),
    ):
        e, c = aj.sweep(
            _kernel("fit", OSC_DURATION, order=order),
            batch,
            keys,
            *shared,
            jnp.asarray(known),
            in_axes=(0, 0, None, None, None),
            chunk_size=SWEEP_CHUNK,
        )
        out[name] = {k: v[0] for k, v in _summarise(np.asarray(e), np.asarray(c), 1, seeds).items()}
    out["note"] = (
        "γ exact, k_dp k_y true, reference device with noise ε = 1e-5 V. fit_order_3 ignores "
        "the output filter (its T_dm absorbs T_f); fit_order_3_known_filter is given the "
        "design T_f and K_test."
    )
    return out


def _sigmas(stats: dict, value: float) -> float:
    """|mean − value| in standard deviations of the single-record scatter."""
    return abs(stats["mean"] - value) / stats["std"]


def _summary_rows(result: dict) -> list[dict]:
    head = result["headline"]
    fit = result["least_squares_fit"]["fit_order_3_known_filter"]
    rows = [
        {
            "quantity": "δK_a oscillatory, γ = 3/4 [%]",
            "ours": f"{head['oscillatory_gamma_3_4']['mean']:.4f} ± "
            f"{head['oscillatory_gamma_3_4']['std']:.4f}",
            "paper": "0.141",
            "explanation": "with the γ = 3/4 the paper states we are "
            f"{_sigmas(head['oscillatory_gamma_3_4'], 0.141):.1f}σ from its 0.141 %; with "
            "the device's exact γ = m l²/J δK_a = "
            f"{head['oscillatory_gamma_exact']['mean']:.3f} % (next row), close to the "
            "printed value — that the paper used it is our hypothesis, not its statement",
            "note": "mean ± std over noise seeds",
        },
        {
            "quantity": "δK_a oscillatory, γ = m l²/J [%]",
            "ours": f"{head['oscillatory_gamma_exact']['mean']:.4f}",
            "paper": "—",
            "note": "the exact shape factor",
        },
        {
            "quantity": "δK_a aperiodic, γ = 3/4, lag-compensated [%]",
            "ours": f"{head['aperiodic_gamma_3_4_lag_compensated']['mean']:.4f} ± "
            f"{head['aperiodic_gamma_3_4_lag_compensated']['std']:.4f}",
            "paper": "0.682",
            "note": "μ = 1.01e-4 N·m·s; mean ± std over noise seeds: the paper's value is "
            f"{_sigmas(head['aperiodic_gamma_3_4_lag_compensated'], 0.682):.2f}σ of the "
            "single-record scatter away",
        },
        {
            "quantity": "δK_a aperiodic, γ = 3/4, uncompensated [%]",
            "ours": f"{head['aperiodic_gamma_3_4_uncompensated']['mean']:.4f}",
            "paper": "—",
            "note": "",
        },
        {
            "quantity": "δK_a per 1 % error in the stop displacement h_max (eq. (11)) [%/%]",
            "ours": f"{result['decomposition']['stop_tolerance']['slope_percent_per_percent']:.3f}",
            "paper": "—",
            "note": "not in the paper's error budget: h_max enters k_dp k_y and K̂_a one for one "
            "(sweep of ±2 %, noise-free nonlinear records)",
        },
        {
            "quantity": "δK_a least-squares fit, order 3, known T_f and K_test [%]",
            "ours": f"{fit['mean']:.4f} ± {fit['std']:.4f}",
            "paper": "—",
            "note": "beyond the paper: all samples, γ exact, true k_dp k_y, same noisy records",
        },
    ]
    if result["assumptions"]["device"] != "reference":
        # The paper's numbers belong to its device; do not set them beside another one's.
        for row in rows:
            if row["paper"] != "—":
                row["note"] = (
                    f"paper value {row['paper']} is for the paper's reference device; "
                    + row["note"]
                )
                row["paper"] = "—"
    return rows


def _panel(ax, s, xlabel, *, logx=False, symlogy=False, ref_key, ref_label, label=None, style="o-"):
    """One sweep: the noise-free reference line, the Monte Carlo mean ± std, and the share
    of records the method could use where it is below one."""
    ax.plot(s["x"], s[ref_key], "k--", lw=1, label=ref_label)
    mean = np.asarray(s["mean"], dtype=float)
    std = np.asarray(s["std"], dtype=float)
    ax.errorbar(
        s["x"], mean, yerr=std, fmt=style, ms=3, capsize=2, label=label or "Monte Carlo mean ± std"
    )
    unusable = []
    for x, m, frac in zip(s["x"], mean, s["usable_fraction"], strict=True):
        if frac < 1 and np.isfinite(m):
            ax.annotate(
                f"{frac:.0%} usable",
                (x, m),
                textcoords="offset points",
                xytext=(0, 8),
                fontsize=7,
                ha="center",
                color="tab:red",
            )
        elif not np.isfinite(m):
            unusable.append(x)
    if unusable:
        # Where nothing was usable there is no mean: one label at the bottom for the run
        # of such points (one label each would overlap).
        ax.annotate(
            f"no usable record from {min(unusable):.3g} on",
            (min(unusable), 0.04),
            xycoords=("data", "axes fraction"),
            fontsize=7,
            ha="right",
            color="tab:red",
        )
    ax.set_xlabel(xlabel)
    ax.set_ylabel("δK_a [%]")
    if logx:
        ax.set_xscale("log")
    if symlogy:
        ax.set_yscale("symlog", linthresh=0.1)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)


def make_figures(out_dir, result, ref, gain, gamma, ts) -> list[dict]:
    figures = Figures(out_dir)
    sw = result["sweeps"]
    osc = sw["oscillatory"]
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.3))
    common = {"ref_key": "predicted_noise_free", "ref_label": "noise-free, dominant poles"}
    _panel(
        axes[0], osc["damping_ratio"], "damping ratio ξ", label="paper: ω from t2 − t1", **common
    )
    s = osc["damping_ratio_half_period"]
    axes[0].errorbar(
        s["x"],
        s["mean"],
        yerr=s["std"],
        fmt="s:",
        ms=3,
        capsize=2,
        label="ω from 2(t_mid − t1)",
    )
    axes[0].legend(fontsize=8)
    _panel(axes[1], osc["noise_V"], "output noise ε [V]", logx=True, symlogy=True, **common)
    _panel(axes[2], osc["torquer_time_constant_s"], "torquer time constant T_dm [s]", **common)
    fig.suptitle("Oscillatory method: δK_a vs ξ, noise, T_dm (cf. paper Fig. 3)")
    figures.save(
        fig,
        "fig3_oscillatory_sweeps.png",
        (
            "Oscillatory method, δK_a = 100(K̂_a − K_a)/K̂_a versus damping ratio (a, "
            f"{XI_SWEEP_DURATION * 1e3:g} ms records), output noise (b, symmetric-log axis) and "
            f"torquer lag (c, {OSC_DURATION * 1e3:g} ms records); reference device otherwise "
            "(T_dm = T_f = 1e-5 s, ε = 1e-5 V), γ = m l²/J, k_dp k_y from the stops, "
            f"{SAMPLE_RATE / 1e6:g} MHz sampling, linear-interpolated crossings, parabolic "
            "extrema. Markers: mean, bars: std over "
            f"{result['assumptions']['monte_carlo_seeds_per_point']} noise seeds; dashed: the "
            "noise-free error predicted from the dominant closed-loop poles (no simulation). "
            "Red labels: share of records the method could use (none once the undershoot A2 "
            "is below the noise band, from ξ ≈ 0.85). Squares in (a): the same records with "
            "ω from the half period between the first two (steep) crossings."
        ),
    )

    ap = sw["aperiodic"]
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.3))
    common = {"ref_key": "noise_free", "ref_label": "noise-free record"}
    _panel(axes[0], ap["T1_over_2T2"], "T1 / (2 T2) (= ξ)", symlogy=True, **common)
    _panel(axes[1], ap["noise_V"], "output noise ε [V]", logx=True, symlogy=True, **common)
    _panel(
        axes[2],
        ap["torquer_time_constant_s_compensated"],
        "torquer time constant T_dm [s]",
        label="with lag compensation (16)",
        **common,
    )
    s = ap["torquer_time_constant_s_uncompensated"]
    axes[2].errorbar(
        s["x"], s["mean"], yerr=s["std"], fmt="s--", ms=3, capsize=2, label="without compensation"
    )
    axes[2].plot(s["x"], s["noise_free"], "k:", lw=1)
    axes[2].legend(fontsize=8)
    fig.suptitle("Aperiodic method: δK_a vs T1/2T2, noise, T_dm (cf. paper Fig. 5)")
    figures.save(
        fig,
        "fig5_aperiodic_sweeps.png",
        (
            "Aperiodic method (μ = 1.01e-4 N·m·s device, ξ = 2.07), δK_a versus T1/2T2 (a), "
            "output noise (b) and T_dm with and without the lag compensation (16) (c); "
            "symmetric-log axes where the spread spans decades. γ = m l²/J, k_dp k_y from the "
            f"stops, {SAMPLE_RATE / 1e6:g} MHz sampling, {APER_DURATION * 1e3:g} ms records, "
            f"slope by a Savitzky-Golay local cubic over {APER_SMOOTHING} samples. "
            "Markers: Monte Carlo mean ± std over noise seeds (ε = 1e-5 V unless swept); "
            "dashed/dotted: the same identification on the noise-free record."
        ),
    )

    dec = result["decomposition"]["oscillatory"]["dKa_percent"]
    fig, ax = plt.subplots(figsize=(9, 5))
    labels = list(dec)
    ax.barh(labels, [dec[k] for k in labels], color="tab:blue")
    ax.axvline(0.141, color="tab:red", ls="--", label="paper: 0.141 %")
    ax.set_xlabel("δK_a [%]")
    ax.invert_yaxis()
    ax.legend()
    ax.grid(alpha=0.3, axis="x")
    figures.save(
        fig,
        "decomposition.png",
        (
            "Oscillatory δK_a, one cause at a time, from the ideal second-order case (noise-free "
            "unless marked; 10 MHz unless marked) to the full reference device."
        ),
    )

    # What `accel-jax identify` shows a user for one record of the reference device.
    ts_id = _grid(OSC_DURATION, SAMPLE_RATE)
    u_test = np.where(ts_id >= 1e-3, 1.0, 0.0)
    u_out = aj.simulate_linear(
        ref, jnp.asarray(ts_id), jnp.asarray(u_test), key=jax.random.key(IDENTIFY_SEED)
    )
    record = aj.StepData(np.asarray(ts_id), u_test, np.asarray(u_out))
    identified = aj.identify_step_record(record, ref)
    fig = identification_figure(identified, title="one record of the reference device")
    fit = identified.fit
    quality = fit.quality  # (a failed fit, which has none, stops the study here)
    figures.save(
        fig,
        "identify_record.png",
        (
            "One test step of the reference device as `accel-jax identify` shows it "
            f"({SAMPLE_RATE / 1e6:g} MHz, ε = {float(ref.noise_std):.0e} V white, a +1 V step "
            "at 1 ms, float64): measured vs the order-3 fit with the graph method's t1, t2, "
            f"A1, A2 marked (fit {quality.fit_percent:.2f} %, MATLAB compare); the residual "
            "with its ±2σ noise band; its autocorrelation with the 95 % band and the Ljung–Box "
            "test. Graph-method δK_a "
            f"{identified.graph.dKa_percent:+.3f} %, fit δK_a "
            f"{fit.dKa_percent:+.4f} ± {fit.dKa_std_percent:.4f} %."
        ),
    )
    return figures.entries


def main(argv=None) -> int:
    def add_arguments(parser):
        parser.add_argument(
            "--params", type=Path, default=None, help="device TOML (default: the reference device)"
        )

    def options(args):
        if args.params is None:
            return {}, {}
        try:
            params = aj.read_params_toml(args.params).params
        except aj.DataError as error:  # its message names the file
            raise ValueError(str(error)) from None
        fields = {k: float(v) for k, v in params.as_dict().items()}
        return {"params": params}, {"params": fields}

    return study_main(
        run, __file__, __doc__, argv=argv, add_arguments=add_arguments, options=options
    )


if __name__ == "__main__":
    sys.exit(main())
