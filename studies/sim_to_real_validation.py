"""Study: blind validation of the sim-to-real diagnosis (docs/models.md §5) on step records,
vibration tables and static noise records.

For each kind a truth simulator makes datasets in which one unmodelled effect of the kind's
library (or none) is drawn at random with a random realistic magnitude, on a device whose
nominal values are themselves drawn within their uncertainty. The datasets are written as
CSV files (the user's formats); the diagnosis then runs on the files in a separate process
that is given only the folders (never the effects, magnitudes or devices), and writes its
verdicts. Only afterwards does this script compare them with the truth, which it kept in
memory (and writes to truth.json after the diagnosis has finished).

Truth simulators (none of them the diagnosis's own model code):
- step: `simulate_linear` (exact ZOH) for the lags, the drift and the noise;
  `simulate_nonlinear` (diffrax, stiff inelastic stop contact) for the stops.
- vibration: the time average of the static transfer function (`indicated_acceleration`)
  over a simulated record per test row — the sinusoid sampled over whole periods, the
  random vibration as independent Gaussian samples (centred) — plus the row's measurement
  noise; the diagnosis uses the exact expectation by quadrature instead.
- noise: `simulate_noise` (exact discrete-time sampling of white + Gauss–Markov /
  exponential-cosine / random-walk processes); the diagnosis uses its own filter.

Writes OUT/result.json, OUT/truth.json, the datasets and PNG figures. Run:
`python studies/sim_to_real_validation.py [--out DIR] [--quick] [--kinds step,vibration,noise]`
(float64). Spread over machines: every machine runs the same draw with `--shard k/n`
(k = 0 … n−1; it diagnoses records k, k+n, … of each kind and writes them unscored), then
`--merge OUT_0/result.json … OUT_n-1/result.json --out DIR` scores them as one run.
"""

from __future__ import annotations

import hashlib
import json
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
from accel_jax import NoiseData, StepData, VibrationData, write_csv  # noqa: E402
from accel_jax._runtime import report_cpus  # noqa: E402
from accel_jax.diagnose.step.assess import NESTED_ABSOLUTE, NESTED_RESTART_ABOVE  # noqa: E402
from accel_jax.report import (  # noqa: E402
    Figures,
    provenance,
    save_figure_atomic,
    study_main,
    study_run,
    write_json_atomic,
)

sys.path.insert(0, str(Path(__file__).resolve().parent))
import step_truth  # noqa: E402  (the independent truth simulator, beside this study)
from shards import parse_shard, run_blind_side_by_side, shard_indices  # noqa: E402
from verdict_family import family  # noqa: E402

STUDY = "sim_to_real_validation"

KINDS = ("step", "step_independent", "vibration", "noise")

# --- step: assumptions (recorded in the output) --------------------------------------------
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
VERDICTS = EFFECTS[1:] + ("stop_contact", "none", "cannot_tell", "unexplained")


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
    records, noises = [], []
    dt = 1 / SAMPLE_RATE
    for truth, y, key in zip(truths, outputs, keys, strict=True):
        if not np.all(np.isfinite(y)):
            raise RuntimeError(f"truth simulation failed for {truth}")
        # The noise the simulators added (their own draw from `key`), kept for the scoring.
        noise = truth["noise_std"] * np.asarray(jax.random.normal(key, y.shape, y.dtype))
        if truth["effect"] == "colored_noise":
            colored = _gauss_markov(rng, y.size, dt, truth["gm_time_s"], truth["gm_std_V"])
            y, noise = y + colored, noise + colored
        records.append(StepData(ts_np, u_np, y))
        noises.append(noise)
    return records, noises


def generate_independent(truths: list[dict], seed: int):
    """Records of the independent truth simulator (`step_truth.make`: SciPy, its own
    conventions) and the noise component of each."""
    rng = np.random.default_rng(seed + 4)
    records, noises = [], []
    for truth in truths:
        t, u, y, noise = step_truth.make(truth, rng)
        records.append(StepData(t, u, y))
        noises.append(noise)
    return records, noises


# --- vibration: assumptions (recorded in the output) ---------------------------------------
VIB_LEVELS = (-1.0, -0.5, 0.0, 0.5, 1.0)  # g along the input axis (dividing head on the shaker)
VIB_SINE = (0.0, 0.5, 1.0, 2.0, 4.0, 8.0)  # g, sinusoid along the input axis
VIB_RANDOM = (2.0, 5.0)  # g RMS, Gaussian random vibration along the input axis
VIB_INCLINED = 4.0  # g, in-phase sinusoid on the input axis and on one cross axis (OA or PA)
VIB_FREQ_RANGE = (20.0, 200.0)  # Hz, uniform per row (a static transfer function ignores it)
VIB_ROW_NOISE = (1e-6, 1e-5)  # g, repeatability of a row's mean output, log-uniform
VIB_BIAS_RANGE = (-1.5e-3, 1.5e-3)  # g, a0 of the device, uniform
VIB_SCALE_SD = 100e-6  # δ of the device, normal
VIB_RECORD = 16384  # samples per row record of the truth (sinusoid over VIB_CYCLES periods)
VIB_CYCLES = 64
# Effect magnitudes, log-uniform with a random sign, in the paper's units (Tables 2 and 4:
# AKS-05 actual ranges to AL-1M passport values): A1 [ppm], k_n [ppm/g^(n−1)], m3i [ppm/g].
VIB_MAGNITUDES = {
    "asymmetry": (3.0, 50.0),
    "k2": (0.3, 30.0),
    "k3": (0.3, 30.0),
    "k4": (0.01, 1.0),
    "k5": (0.003, 0.3),
    "cross_coupling": (1.0, 50.0),
}
VIB_COEFFICIENTS = {
    "asymmetry": ("asymmetry",),
    "k2": ("k2",),
    "k3": ("k3",),
    "k4": ("k4",),
    "k5": ("k5",),
    "cross_coupling": ("m31", "m32"),
}
VIB_EFFECTS = ("none", "k2", "k3", "k4", "k5", "asymmetry", "cross_coupling")

# --- noise: assumptions (recorded in the output) -------------------------------------------
NOISE_DT = 0.01  # s (100 Hz)
NOISE_SAMPLES = 4000  # 40 s static record; the last third is held out
NOISE_WHITE = (5e-6, 5e-5)  # g, white σ_w, log-uniform
NOISE_LEVEL = (-1e-3, 1e-3)  # g, bias about 1 g (input axis vertical), uniform
GM_STD_RATIO = (0.3, 2.0)  # σ_GM / σ_w, log-uniform
GM_TIME = (0.03, 0.3)  # s, τ_c (3–30 samples), log-uniform
EC_STD_RATIO = (0.3, 2.0)  # σ_EC / σ_w, log-uniform
EC_PERIOD = (0.05, 0.5)  # s, 2π/β (5–50 samples), log-uniform
EC_QUALITY = (1.5, 6.0)  # β/α (the oscillation is visible), log-uniform
RW_WALK = (0.5, 5.0)  # √(q T_record) / σ_w, log-uniform
NOISE_EFFECTS = ("none", "gauss_markov", "exp_cosine", "random_walk")

CLASSES = {
    "step": EFFECTS,
    "step_independent": step_truth.CLASSES,
    "vibration": VIB_EFFECTS,
    "noise": NOISE_EFFECTS,
}
OUT_OF_LIBRARY = {"step_independent": step_truth.OUT_OF_LIBRARY}
"""Classes whose effect is outside the diagnosis's library: the right verdict is
`unexplained`."""

# Datasets per class. The step records cost ~1 s of CPU each to diagnose, so the full run
# keeps 20 per class (120 records) to stay within the report's time budget; vibration and
# noise carry more no-effect datasets, which set the false-alarm rate.
PER_CLASS_FULL = {
    "step": {c: 20 for c in EFFECTS},
    "step_independent": {c: (16 if c == "none" else 8) for c in step_truth.CLASSES},
    "vibration": {c: (40 if c == "none" else 25) for c in VIB_EFFECTS},
    "noise": {c: (40 if c == "none" else 30) for c in NOISE_EFFECTS},
}
PER_CLASS_LARGE = {
    "step": {c: (100 if c == "none" else 20) for c in EFFECTS},
    "step_independent": {
        c: (100 if c == "none" else 20 if c in step_truth.IN_LIBRARY else 34)
        for c in step_truth.CLASSES
    },
    "vibration": {c: (100 if c == "none" else 25) for c in VIB_EFFECTS},
    "noise": {c: (100 if c == "none" else 34) for c in NOISE_EFFECTS},
}
"""`--large`: at least 100 blind datasets per kind of dataset (clean, in-library,
out-of-library) for each truth simulator, as issue 19 asks; run by hand, not by the report."""
PER_CLASS_QUICK = {"step": 3, "step_independent": 1, "vibration": 2, "noise": 2}


# --------------------------------------------------------------------------------------
# Vibration truth
# --------------------------------------------------------------------------------------


def _vib_plan() -> dict:
    """The test plan: at every input level, the sinusoids, the random levels and the two
    inclined rows (IA + OA, IA + PA)."""
    rows = []
    for a in VIB_LEVELS:
        rows += [(a, b, 0.0, 0.0, 0.0) for b in VIB_SINE]
        rows += [(a, 0.0, s, 0.0, 0.0) for s in VIB_RANDOM]
        rows += [
            (a, VIB_INCLINED, 0.0, VIB_INCLINED, 0.0),
            (a, VIB_INCLINED, 0.0, 0.0, VIB_INCLINED),
        ]
    r = np.asarray(rows)
    return {
        "a_in": r[:, 0],
        "vib_amp": r[:, 1],
        "vib_rms": r[:, 2],
        "vib_amp_oa": r[:, 3],
        "vib_amp_pa": r[:, 4],
    }


def _vib_draw(rng: np.random.Generator, effect: str) -> dict:
    truth = {
        "effect": effect,
        "bias_g": rng.uniform(*VIB_BIAS_RANGE),
        "scale_factor_error": rng.normal() * VIB_SCALE_SD,
        "row_noise_g": _log_uniform(rng, VIB_ROW_NOISE),
        "coefficients_ppm": {},
    }
    if effect != "none":
        for name in VIB_COEFFICIENTS[effect]:
            value = _log_uniform(rng, VIB_MAGNITUDES[effect]) * rng.choice([-1.0, 1.0])
            truth["coefficients_ppm"][name] = float(value)
    truth["bias_g"], truth["scale_factor_error"] = (
        float(truth["bias_g"]),
        float(truth["scale_factor_error"]),
    )
    truth["row_noise_g"] = float(truth["row_noise_g"])
    return truth


def _vib_device(truth: dict) -> aj.StaticTransferFunction:
    return aj.StaticTransferFunction(
        bias=truth["bias_g"],
        scale_factor_error=truth["scale_factor_error"],
        **{k: v * aj.PPM for k, v in truth["coefficients_ppm"].items()},
    )


@eqx.filter_jit
def _vib_record_means(tf, a_in, b3, b1, b2, sigma, key):
    """Time average of a_F over one simulated record per row: the in-phase sinusoids over
    VIB_CYCLES whole periods (random start phase), the random vibration as independent
    Gaussian samples with their sample mean removed (zero-mean vibration over the record)."""

    def one(a, b3_, b1_, b2_, s, k):
        k_phase, k_noise = jax.random.split(k)
        phase = jax.random.uniform(k_phase, (), a.dtype) * 2 * jnp.pi
        theta = 2 * jnp.pi * VIB_CYCLES * jnp.arange(VIB_RECORD, dtype=a.dtype) / VIB_RECORD
        sine = jnp.sin(theta + phase)
        z = jax.random.normal(k_noise, (VIB_RECORD,), a.dtype)
        a3 = a + b3_ * sine + s * (z - jnp.mean(z))
        return jnp.mean(aj.indicated_acceleration(tf, a3, b1_ * sine, b2_ * sine))

    keys = jax.random.split(key, a_in.shape[0])
    return jax.vmap(one)(a_in, b3, b1, b2, sigma, keys)


def generate_vibration(truths: list[dict], seed: int) -> list[VibrationData]:
    plan = _vib_plan()
    rng = np.random.default_rng(seed + 2)
    keys = jax.random.split(jax.random.key(seed + 2), len(truths))
    args = [
        jnp.asarray(plan[c]) for c in ("a_in", "vib_amp", "vib_amp_oa", "vib_amp_pa", "vib_rms")
    ]
    records = []
    for truth, key in zip(truths, keys, strict=True):
        means = np.asarray(_vib_record_means(_vib_device(truth), *args, key))
        a_out = means + truth["row_noise_g"] * rng.normal(size=means.size)
        freq = rng.uniform(*VIB_FREQ_RANGE, size=means.size)
        records.append(
            VibrationData(
                a_in=plan["a_in"],
                vib_amp=plan["vib_amp"],
                vib_freq=freq,
                vib_rms=plan["vib_rms"],
                a_out=a_out,
                vib_amp_oa=plan["vib_amp_oa"],
                vib_amp_pa=plan["vib_amp_pa"],
            )
        )
    return records


_VIB_DESIGN_NAMES = (
    "bias",
    "scale_factor_error",
    "asymmetry",
    "k2",
    "k3",
    "k4",
    "k5",
    "m31",
    "m32",
)


def _vib_snr(truths: list[dict]) -> list[float]:
    """The effect's signal-to-noise ratio in each table: the norm (over rows) of its
    contribution to the mean output, after removing what bias and scale factor can absorb,
    over the row noise. Harness-side bookkeeping (the diagnosing process never sees it)."""
    plan = _vib_plan()
    table = {
        **plan,
        "vib_freq": np.full(plan["a_in"].size, 50.0),
        "a_out": np.zeros(plan["a_in"].size),
    }
    design = np.asarray(aj.vibration.design_matrix(table, _VIB_DESIGN_NAMES))  # g per ppm
    nominal = design[:, :2]
    out = []
    for truth in truths:
        theta = np.zeros(len(_VIB_DESIGN_NAMES))
        for name, value in truth["coefficients_ppm"].items():
            theta[_VIB_DESIGN_NAMES.index(name)] = value
        signal = design @ theta
        coef, *_ = np.linalg.lstsq(nominal, signal, rcond=None)
        out.append(float(np.linalg.norm(signal - nominal @ coef) / truth["row_noise_g"]))
    return out


# --------------------------------------------------------------------------------------
# Noise truth
# --------------------------------------------------------------------------------------


def _noise_draw(rng: np.random.Generator, effect: str) -> dict:
    white = _log_uniform(rng, NOISE_WHITE)
    truth = {"effect": effect, "white_std_g": white, "level_g": 1.0 + rng.uniform(*NOISE_LEVEL)}
    duration = NOISE_SAMPLES * NOISE_DT
    if effect == "gauss_markov":
        truth["gm_std_g"] = white * _log_uniform(rng, GM_STD_RATIO)
        truth["gm_time_s"] = _log_uniform(rng, GM_TIME)
        truth["variance_ratio"] = (truth["gm_std_g"] / white) ** 2
    elif effect == "exp_cosine":
        truth["ec_std_g"] = white * _log_uniform(rng, EC_STD_RATIO)
        beta = 2 * np.pi / _log_uniform(rng, EC_PERIOD)
        truth["ec_angular_frequency_rad_s"] = beta
        truth["ec_decay_rate_per_s"] = beta / _log_uniform(rng, EC_QUALITY)
        truth["variance_ratio"] = (truth["ec_std_g"] / white) ** 2
    elif effect == "random_walk":
        walk = white * _log_uniform(rng, RW_WALK)
        truth["rw_intensity_g2_per_s"] = walk**2 / duration
        truth["variance_ratio"] = (walk / white) ** 2
    else:
        truth["variance_ratio"] = 0.0
    return {k: (float(v) if not isinstance(v, str) else v) for k, v in truth.items()}


def _noise_model(truth: dict):
    white = aj.noise.WhiteNoise(truth["white_std_g"])
    effect = truth["effect"]
    if effect == "gauss_markov":
        return aj.noise.NoiseSum(
            (white, aj.noise.GaussMarkov(truth["gm_std_g"], truth["gm_time_s"]))
        )
    if effect == "exp_cosine":
        ec = aj.noise.ExponentialCosine(
            truth["ec_std_g"], truth["ec_decay_rate_per_s"], truth["ec_angular_frequency_rad_s"]
        )
        return aj.noise.NoiseSum((white, ec))
    if effect == "random_walk":
        return aj.noise.NoiseSum((white, aj.noise.RandomWalk(truth["rw_intensity_g2_per_s"])))
    return white


@eqx.filter_jit
def _noise_record(model, key):
    return aj.noise.simulate_noise(model, NOISE_DT, NOISE_SAMPLES, key=key)


def generate_noise(truths: list[dict], seed: int) -> list[NoiseData]:
    keys = jax.random.split(jax.random.key(seed + 3), len(truths))
    t = np.arange(NOISE_SAMPLES) * NOISE_DT
    records = []
    for truth, key in zip(truths, keys, strict=True):
        x = np.asarray(_noise_record(_noise_model(truth), key)) + truth["level_g"]
        records.append(NoiseData(t, x))
    return records


# --------------------------------------------------------------------------------------
# The blind diagnosis and the scoring
# --------------------------------------------------------------------------------------

NOMINAL_LAGS = {"torquer_time_constant": 0.0, "filter_time_constant": 0.0}
"""The nominal device the diagnosis is given (as a user gives a data sheet with --params):
the reference device with the lags of the truths' devices, T_dm = T_f = 0. A lag effect is
a departure from these."""

_DIAGNOSE_CODE = (
    f"NOMINAL_LAGS = {NOMINAL_LAGS!r}\n"
    + """
import json, sys, pathlib, signal, time
signal.signal(signal.SIGINT, lambda *_: sys.exit(130))  # Ctrl-C: quiet exit, no traceback
import accel_jax  # applies the XLA:CPU deadlock workaround (accel_jax._runtime)
from accel_jax._placement import apply_device
from accel_jax._cache import enable_compilation_cache
apply_device(latency_bound=True)  # one record at a time: the CPU, as `accel-jax diagnose`
enable_compilation_cache()  # $ACCEL_JAX_CACHE_DIR as the parent process had it
import jax
jax.config.update("jax_enable_x64", True)
from accel_jax import read_csv
from accel_jax import NominalDevice
from accel_jax.diagnose import diagnose_many
out = pathlib.Path(sys.argv[1])
# The device's data sheet, as a user gives it: the reference device with ideal lags.
nominal = NominalDevice.reference(**NOMINAL_LAGS)
answer, seconds = {}, {}
for folder in map(pathlib.Path, sys.argv[2:]):
    files = sorted(folder.glob("*.csv"))
    t0 = time.perf_counter()
    # recommend=False: the next experiment of a lag tie is the multi-record harness's
    # (studies/step_set_harness.py); here it would add ~30 s per tie.
    results = diagnose_many([read_csv(f) for f in files], nominal, recommend=False)
    answer[folder.name] = [
        {"file": f.name, "verdict": r.verdict, "tied": r.tied, "gap": r.gap,
         "reason": r.reason, "explained_fraction": r.explained_fraction,
         "remaining_gap": r.remaining_gap,
         # (a step ranking's nested-fit flags; the vibration and noise rankings have none)
         "ranking": [{**{k: e[k] for k in ("effect", "evidence", "significant", "gap_shrink",
                                          "params")},
                      **{k: e[k] for k in ("fit_failed", "objective_below_nominal",
                                          "objective_round_off",
                                          "log_likelihood_below_nominal", "at_no_effect",
                                          "optimum_log_likelihood_below_nominal") if k in e}}
                     for e in r.ranking],
         "refit": r.refit}
        for f, r in zip(files, results)]
    seconds[folder.name] = time.perf_counter() - t0
answer["_seconds"] = seconds  # wall time of each folder's diagnosis (compilation included)
out.write_text(json.dumps(answer, default=float))
"""
)


SECONDS_PER_RECORD = {"step": 8.1, "step_independent": 16.4, "noise": 2.2, "vibration": 0.25}
"""The blind diagnosis's wall time per record of each kind (compilation included), from the
quick run's timing on the 2-core CPU at 2de5e56 (145.6, 147.9, 17.2 and 1.7 s for 18, 9, 8
and 7 records): what `folder_groups` balances."""


def folder_groups(folders: list[Path], count: int) -> list[list[Path]]:
    """`folders` split into at most `count` groups of about equal cost (`SECONDS_PER_RECORD`
    times the CSV files in each; longest first, each to the group with the least so far).
    A folder is never split: its records are diagnosed in one call, as in one process."""
    cost = {
        Path(f): len(list(Path(f).glob("*.csv"))) * SECONDS_PER_RECORD.get(Path(f).name, 5.0)
        for f in folders
    }
    groups: list[list[Path]] = [[] for _ in range(max(1, min(count, len(folders))))]
    totals = [0.0] * len(groups)
    for folder in sorted(cost, key=lambda f: -cost[f]):
        i = int(np.argmin(totals))
        groups[i].append(folder)
        totals[i] += cost[folder]
    order = {Path(f): k for k, f in enumerate(folders)}
    return [sorted(g, key=order.__getitem__) for g in groups if g]


def diagnose_blind(folders: list[Path], cpus: list[int] | None = None) -> dict[str, list[dict]]:
    """Run the diagnosis on every CSV of each folder in fresh Python processes (they see
    only the files), and return its verdicts by folder name (and `_seconds`, each folder's
    wall time).

    The folders are split into one group per CPU (`folder_groups`; `cpus` default
    `report_cpus()`: the whole report's CPUs, so that the diagnosis, the report's longest
    part, has the CPUs the other studies leave when they finish), each group diagnosed in
    its own process, side by side. Each folder is one `diagnose_many` call whichever
    process makes it, so the verdicts are those of one process (tested)."""
    cpus = report_cpus() if cpus is None else list(cpus)
    # Absolute paths: the child runs in the repository root, which need not be the caller's
    # working folder (e.g. `accel-jax report --out` from elsewhere).
    groups = [
        [str(Path(f).resolve()) for f in group] for group in folder_groups(folders, len(cpus))
    ]
    answer: dict = {}
    seconds: dict = {}
    # (One group: the child keeps this process's CPUs, as `run_blind`'s does.)
    for part in run_blind_side_by_side(_DIAGNOSE_CODE, groups, cpus if len(groups) > 1 else None):
        seconds.update(part.pop("_seconds", {}))
        answer.update(part)
    answer["_seconds"] = seconds
    return answer


def _wilson(successes: int, n: int, z: float = 1.96) -> list[float] | None:
    """Wilson 95 % interval of a proportion (the rates here rest on tens of datasets)."""
    if n == 0:
        return None
    p = successes / n
    centre = (p + z**2 / (2 * n)) / (1 + z**2 / n)
    half = z * np.sqrt(p * (1 - p) / n + z**2 / (4 * n**2)) / (1 + z**2 / n)
    return [float(max(centre - half, 0.0)), float(min(centre + half, 1.0))]


def score(
    truths: list[dict],
    verdicts: list[dict],
    classes=EFFECTS,
    out_of_library=(),
    assurance=None,
) -> dict:
    """Confusion matrix and rates of the blind verdicts against the truth.

    - effects of the library: named (strict; a member of the truth's family counts,
      `verdict_family`: an inelastic stop named as a compliant one), or `cannot_tell`
      naming the truth (lenient);
    - no-effect datasets: false alarms (any verdict but `none`);
    - out-of-library effects (`out_of_library`): `unexplained` is right;
    - `assurance`: per dataset, the true held-out gap over the true noise floor (see
      `true_gaps`); a `none` where it is ≥ 3 is a false assurance.
    """
    library = [c for c in classes[1:] if c not in out_of_library]
    verdict_names = tuple(library) + ("none", "cannot_tell", "unexplained")
    # A verdict outside the classes (a family member such as stop_contact, named for an
    # inelastic stop) gets a column of its own in every row, after the library's.
    seen = dict.fromkeys(v["verdict"] for v in verdicts)
    verdict_names = verdict_names[: len(library)] + tuple(
        v for v in seen if v not in verdict_names
    ) + verdict_names[len(library) :]
    confusion = {t: {v: 0 for v in verdict_names} for t in classes}
    strict, lenient, shrinks, false_alarms, n_none, n_effect = 0, 0, [], 0, 0, 0
    n_outside, unexplained = 0, 0
    per_class = {}
    for truth, verdict in zip(truths, verdicts, strict=True):
        t, v = truth["effect"], verdict["verdict"]
        confusion[t][v] += 1
        if t in out_of_library:
            ok = tied_ok = v == "unexplained"
        else:
            ok = v == t or family(v) == t
            # A tie names the truth as a verdict does: itself or a member of its family.
            tied_ok = v == "cannot_tell" and (
                t in verdict["tied"] or t in map(family, verdict["tied"])
            )
        c = per_class.setdefault(t, {"n": 0, "correct": 0, "correct_or_tied": 0})
        c["n"] += 1
        c["correct"] += ok
        c["correct_or_tied"] += ok or tied_ok
        if t == "none":
            n_none += 1
            false_alarms += v != "none"
            continue
        if t in out_of_library:
            n_outside += 1
            unexplained += ok
            continue
        n_effect += 1
        strict += ok
        lenient += ok or tied_ok
        if ok:
            shrinks.append(verdict["gap"]["shrink"])
    for c in per_class.values():
        c["accuracy"] = c["correct"] / c["n"]
        c["accuracy_incl_cannot_tell"] = c["correct_or_tied"] / c["n"]
    out = {
        "confusion": confusion,
        "accuracy": strict / max(n_effect, 1),
        "accuracy_95ci": _wilson(strict, n_effect),
        "accuracy_incl_cannot_tell_naming_truth": lenient / max(n_effect, 1),
        "accuracy_incl_cannot_tell_95ci": _wilson(lenient, n_effect),
        "false_alarm_rate": false_alarms / max(n_none, 1),
        "false_alarm_rate_95ci": _wilson(false_alarms, n_none),
        "false_alarms": false_alarms,
        "median_gap_shrink": float(np.median(shrinks)) if shrinks else float("nan"),
        "gap_shrink_p10_p90": [float(np.percentile(shrinks, 10)), float(np.percentile(shrinks, 90))]
        if shrinks
        else None,
        "n_datasets": len(truths),
        "n_per_class": {t: per_class.get(t, {}).get("n", 0) for t in classes},
        "per_class": per_class,
    }
    if out_of_library:
        out["out_of_library_unexplained_rate"] = unexplained / max(n_outside, 1)
        out["out_of_library_unexplained_95ci"] = _wilson(unexplained, n_outside)
        out["n_out_of_library"] = n_outside
    if any("fit_failed" in e for v in verdicts for e in v.get("ranking") or ()):
        out["nested_fits"] = nested_failures(verdicts)
    if assurance is not None:
        false = [
            i
            for i, (v, g) in enumerate(zip(verdicts, assurance, strict=True))
            if v["verdict"] == "none" and g is not None and g >= 3
        ]
        out["false_assurance"] = len(false)
        out["false_assurance_datasets"] = false
        out["none_verdicts"] = sum(v["verdict"] == "none" for v in verdicts)
        out["largest_gap_over_floor_with_none"] = max(
            (g for v, g in zip(verdicts, assurance, strict=True) if v["verdict"] == "none"),
            default=None,
        )
    return out


def nested_failures(verdicts: list[dict]) -> dict:
    """The nested fits that ended below the nominal model they contain (the diagnosis flags
    them `fit_failed`: below the solver's penalised objective, or below the nominal's
    reported ln L; never evidence for the effect), counted over the
    datasets: how many fits in all, how many failed, by effect, the datasets with one, and
    the largest shortfall (ln L units: the penalised objective's or the reported ln L's)."""
    by_effect, datasets, n_fits, worst, solver = {}, [], 0, 0.0, 0
    beyond, largest_objective, settled = 0, 0.0, []
    for i, verdict in enumerate(verdicts):
        ranking = verdict.get("ranking") or ()
        n_fits += len(ranking)
        for e in ranking:
            if e.get("at_no_effect"):
                settled.append(e["optimum_log_likelihood_below_nominal"])
            # Every fit, flagged or not: below the nominal's penalised objective beyond the
            # restart threshold and the comparison's round-off share (issue 42's "beyond
            # round-off"; below the flag's 1e-3 such a fit is not flagged).
            below = e.get("objective_below_nominal", 0.0)
            allowed = max(NESTED_RESTART_ABOVE, e.get("objective_round_off", 0.0))
            beyond += below > allowed
            largest_objective = max(largest_objective, below)
        lost = [e for e in ranking if e.get("fit_failed")]
        for e in lost:
            by_effect[e["effect"]] = by_effect.get(e["effect"], 0) + 1
            solver += e["objective_below_nominal"] > NESTED_ABSOLUTE
            worst = max(
                worst, e["objective_below_nominal"], e.get("log_likelihood_below_nominal", 0.0)
            )
        if lost:
            datasets.append(i)
    return {
        "fits": n_fits,
        "failed": sum(by_effect.values()),
        "failed_by_effect": by_effect,
        # of which below the nominal's penalised objective (the solver's) by more than the
        # least shortfall that can count (`NESTED_ABSOLUTE`); the rest only in the reported
        # ln L, which the solver does not maximise
        "failed_objective": solver,
        "datasets_with_a_failed_fit": datasets,
        "largest_shortfall_lnL": worst,
        # every fit (flagged or not) whose penalised objective ended below the nominal's by
        # more than max(`NESTED_RESTART_ABOVE`, its round-off share), and the largest
        # shortfall of the penalised objective over every fit
        "objective_below_beyond_round_off": beyond,
        "largest_objective_below_nominal": largest_objective,
        # fits reported at their no-effect value (the nominal model exactly: the solver's
        # optimum's reported ln L ended below the nominal's, its objective not), and how far
        # the furthest of those optima had ended below
        "at_no_effect": len(settled),
        "largest_optimum_below_at_no_effect": max(settled, default=0.0),
    }


def true_gaps(noises: list[np.ndarray], verdicts: list[dict]) -> list[float | None]:
    """Per step dataset: the held-out gap the diagnosis left with its nominal refit, over
    the noise floor that the truth simulator actually added (the harness knows the noise
    it drew; the diagnosing process never sees it). Both on the diagnosis's own block
    means and held-out blocks (reported in its `gap`): sqrt(max(RMS² − floor², 0))/floor."""
    out = []
    for noise, verdict in zip(noises, verdicts, strict=True):
        gap = verdict["gap"]
        m, used = gap["block_samples"], gap["fitted_samples"]
        blocks = noise[:used].reshape(-1, m).mean(axis=1)
        held = np.concatenate([blocks[a:b] for a, b in gap["held_out_blocks"]])
        floor = float(np.sqrt(np.mean(held**2)))
        rms = gap["rms_before"]
        out.append(float(np.sqrt(max(rms**2 - floor**2, 0.0)) / floor) if floor > 0 else None)
    return out


LAG_PAIR = ("torquer_lag", "output_filter")


def lag_forced_choice(truths: list[dict], verdicts: list[dict]) -> dict:
    """What naming the step effects could reach if every `cannot_tell` between the two lags
    were forced to the lag with the higher evidence (the ideal-observer ceiling here).

    On a test-winding step both lags give an all-pole third-order response, and any record
    that one fits, the other fits exactly with shifted J, μ and T: the data part of their
    evidence is equal and the difference is the ±5 % prior alone. Returns the strict naming
    rate over the effect datasets under that forced rule (measured against the truth), the
    rate the evidence itself expects (each forced pick counted as its posterior probability
    1/(1 + e^{−|Δ|/2}), Δ = 2 ln B between the two lags), and the evidence gaps. A verdict
    of the truth's family (`stop_contact` for an inelastic stop) is named, as in `score`."""
    measured = expected = 0.0
    n_effect, gaps, forced = 0, [], 0
    for truth, verdict in zip(truths, verdicts, strict=True):
        t, v = truth["effect"], verdict["verdict"]
        if v == "cannot_tell" and set(verdict["tied"]) == set(LAG_PAIR):
            ev = {e["effect"]: e["evidence"] for e in verdict["ranking"]}
            delta = ev[LAG_PAIR[0]] - ev[LAG_PAIR[1]]
            v = LAG_PAIR[0] if delta > 0 else LAG_PAIR[1]
            forced += 1
            gaps.append(abs(delta))
            p_pick = 1 / (1 + np.exp(-abs(delta) / 2))
        else:
            # named as `score` counts it: a member of the truth's family (`verdict_family`)
            p_pick = float(v == t or family(v) == t)
        if t == "none":
            continue
        n_effect += 1
        measured += v == t or family(v) == t
        expected += p_pick
    return {
        "forced_datasets": forced,
        "accuracy_forced": measured / max(n_effect, 1),
        "accuracy_forced_95ci": _wilson(int(measured), n_effect),
        "accuracy_expected_by_evidence": expected / max(n_effect, 1),
        "evidence_gap_median": float(np.median(gaps)) if gaps else None,
        "evidence_gap_max": float(np.max(gaps)) if gaps else None,
    }


def _by_snr(truths, verdicts, snr, edges) -> list[dict]:
    """Correct-naming rate of the effect datasets in bins of their signal-to-noise ratio."""
    rows = []
    effect = [
        (s, v["verdict"] == t["effect"], v["verdict"])
        for t, v, s in zip(truths, verdicts, snr, strict=True)
        if t["effect"] != "none"
    ]
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        inside = [(ok, v) for s, ok, v in effect if lo <= s < hi]
        values = [s for s, _, _ in effect if lo <= s < hi]
        rows.append(
            {
                "snr_range": [lo, hi],
                "median_snr": float(np.median(values)) if values else None,
                "n": len(inside),
                "correct": sum(ok for ok, _ in inside),
                "cannot_tell": sum(v == "cannot_tell" for _, v in inside),
                "none": sum(v == "none" for _, v in inside),
            }
        )
    return rows


def _lag_breakdown(truths, verdicts):
    """Verdicts of the lag datasets against the lag: the two lags are exactly degenerate
    on a test-winding step except through the damping prior (see the summary note)."""
    rows = []
    for truth, verdict in zip(truths, verdicts, strict=True):
        if truth["effect"] in LAG_PAIR:
            lag = truth["torquer_time_constant"] or truth["filter_time_constant"]
            rows.append({"effect": truth["effect"], "lag_s": lag, "verdict": verdict["verdict"]})
    return rows


def _confusion_panel(ax, confusion: dict, rows, cols):
    """A confusion matrix drawn as row fractions with the counts written in; the image."""
    matrix = np.array([[confusion[t].get(v, 0) for v in cols] for t in rows], dtype=float)
    shown = matrix / np.maximum(matrix.sum(1, keepdims=True), 1)
    im = ax.imshow(shown, cmap="Blues", vmin=0, vmax=1, aspect="auto")
    ax.set_xticks(range(len(cols)), cols, rotation=30, ha="right", fontsize=11)
    ax.set_yticks(range(len(rows)), rows, fontsize=11)
    for i in range(len(rows)):
        for j in range(len(cols)):
            if matrix[i, j]:
                ax.text(
                    j,
                    i,
                    int(matrix[i, j]),
                    ha="center",
                    va="center",
                    fontsize=12,
                    color="white" if shown[i, j] > 0.55 else "black",
                )
    return im


def _three_panels():
    """The confusion matrix across the top (legible at the page width), two panels below."""
    fig = plt.figure(figsize=(13, 10.5))
    grid = fig.add_gridspec(2, 2, height_ratios=(1.15, 1))
    return fig, [
        fig.add_subplot(grid[0, :]),
        fig.add_subplot(grid[1, 0]),
        fig.add_subplot(grid[1, 1]),
    ]


def _figures(out_dir, result, lag_rows):
    figures = Figures(out_dir)
    fig, axes = _three_panels()
    ax = axes[0]
    im = _confusion_panel(ax, result["step"]["confusion"], EFFECTS, VERDICTS)
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
    # Plain decade labels: the default minor labels (3×10¹, 4×10¹) collide.
    ax.xaxis.set_minor_formatter(plt.NullFormatter())
    ax.set_xticks([5, 10, 20, 50], ["5", "10", "20", "50"])
    ax.set_ylabel("verdict")
    ax.set_title("lag datasets: verdict vs magnitude")
    ax.legend(fontsize=8)
    figures.save(
        fig,
        "validation.png",
        (
            "Blind validation of the step diagnosis. Top: confusion matrix of true effect "
            "vs blind verdict. Bottom left: held-out gap shrink (RMS prediction error above the "
            "noise floor, on the held-out segments: every third) where the effect was named "
            "correctly. Bottom right: verdicts on the lag datasets against the true lag. "
            f"Assumptions: {SAMPLE_RATE / 1e3:.0f} kHz, {len(PATTERN)} segments of "
            f"{SEGMENT / SAMPLE_RATE * 1e3:.0f} ms at U_test = ±{STEP_VOLTAGE} V, white noise "
            f"{NOISE_RANGE[0]:.0e}–{NOISE_RANGE[1]:.0e} V, J, μ, c, k_dm drawn from their ±5 % "
            "prior; effect magnitudes as in the assumptions block."
        ),
    )
    return figures.entries


def _kind_figure(out_dir, kind, section, snr_label):
    """Confusion matrix, held-out shrink and naming rate against the SNR of one kind."""
    classes = CLASSES[kind]
    verdict_names = tuple(classes[1:]) + ("none", "cannot_tell")
    fig, axes = _three_panels()
    ax = axes[0]
    im = _confusion_panel(ax, section["confusion"], classes, verdict_names)
    ax.set_xlabel("verdict (blind)")
    ax.set_ylabel("true effect")
    ax.set_title(f"{kind}: confusion matrix (counts; colour = row fraction)")
    fig.colorbar(im, ax=ax, fraction=0.046, label="fraction of the true class")
    ax = axes[1]
    shrinks = section["_shrinks"]
    ax.hist(shrinks, bins=20, range=(min(0.0, min(shrinks, default=0)), 1.0), color="C2")
    ax.axvline(0.5, color="k", ls=":", label="target median 0.5")
    if shrinks:
        ax.axvline(section["median_gap_shrink"], color="C3", label="median")
    ax.set_xlabel("held-out gap shrink 1 − after/before [–]")
    ax.set_ylabel("datasets (effect named correctly)")
    ax.set_title(f"{kind}: held-out gap shrink")
    ax.legend(fontsize=8)
    ax = axes[2]
    snr = np.asarray(section["_snr"])
    ok = np.asarray(section["_named"], dtype=float)
    ax.semilogx(
        snr,
        ok + np.random.default_rng(0).uniform(-0.05, 0.05, ok.size),
        "o",
        ms=3,
        color="0.4",
        alpha=0.6,
    )
    bins = section["correct_by_snr"]
    centres = [b["median_snr"] for b in bins if b["n"]]
    rate = [b["correct"] / b["n"] for b in bins if b["n"]]
    ax.semilogx(centres, rate, "s-", color="C0", label="named correctly (bin fraction)")
    ax.axhline(0.9, color="k", ls=":", label="target 0.9")
    ax.set_ylim(-0.1, 1.1)
    ax.set_xlabel(snr_label)
    ax.set_ylabel("named correctly (1) or not (0)")
    ax.set_title(f"{kind}: naming vs signal-to-noise")
    ax.legend(fontsize=8)
    fig.tight_layout()
    name = f"validation_{kind}.png"
    save_figure_atomic(fig, out_dir / name)
    plt.close(fig)
    return name


def _kind_truths(kind, rng, counts):
    draw = {
        "step": _draw,
        "step_independent": step_truth.draw_truth,
        "vibration": _vib_draw,
        "noise": _noise_draw,
    }[kind]
    return [draw(rng, effect) for effect in CLASSES[kind] for _ in range(counts[effect])]


def _generate(kind, truths, seed):
    """(records, noise components or None)."""
    if kind == "step":
        return generate(truths, seed)
    if kind == "step_independent":
        return generate_independent(truths, seed)
    return {"vibration": generate_vibration, "noise": generate_noise}[kind](truths, seed), None


def _assumptions(kind) -> dict:
    if kind == "step_independent":
        st = step_truth
        return {
            "truth_simulator": "studies/step_truth.py: SciPy solve_ivp (DOP853, rtol 1e-10) on "
            "its own loop equations, stops as exact inelastic contact/release events; none of "
            "the library's simulators",
            "sample_rate_Hz_one_of": list(st.RATES),
            "record_s": st.DURATION,
            "test_sequence": f"{st.SEGMENTS} levels from {list(st.LEVELS)} × U_max (U_max uniform "
            "1.5–2.5 V), segments 1.2–2.2 ms, changes at exact times on the DAC's own clock; "
            "u_test column sampled at the record's times",
            "test_winding": "either polarity (50 %), gain 1 ± 2 %",
            "output": "either sign (inverting recorder input, 50 %), offset uniform ±50 mV, "
            f"ADC of {list(st.ADC_BITS)} bits over ±10 V",
            "start": "at rest (50 %) or 0.1–1 ms after an earlier change from another level",
            "device": f"log-normal σ {st.DEVICE_SD} about the reference; M uniform ±2e-6 N·m",
            "noise_V_log_uniform": list(st.NOISE),
            "in_library": {
                "torquer_lag / output_filter": "5–50 µs log-uniform",
                "stop_saturation": "stop at 0.8–1.1 × the largest settled output",
                "disturbance_drift": "2–20 mV over the record, either sign",
                "colored_noise": "Gauss–Markov τ 20–200 µs, σ 0.5–2 × the white σ",
            },
            "out_of_library": {
                "pickoff_nonlinearity": "U_amp = k_dp k_y l θ (1 + p2 x + p3 x²), |p2|, |p3| "
                "2–10 % at full scale",
                "bandpass_sensor": "velocity-output second-order sensor, 100–1000 Hz, ζ 0.3–0.8",
                "periodic_disturbance": "input-axis vibration 200–3000 Hz, output amplitude "
                "5–50 × the noise σ",
            },
            "right_answers": "none for no effect, the effect's name (or cannot_tell naming it) "
            "in the library, unexplained outside it",
            "nominal_device_given": "the reference device with T_dm = T_f = 0 (the truths' "
            "devices without a lag effect); J, μ, c, k_dm under a 5 % prior",
            "held_out": STEP_HELD_OUT,
        }
    if kind == "step":
        return {
            "sample_rate_Hz": SAMPLE_RATE,
            "segments_V": [p * STEP_VOLTAGE for p in PATTERN],
            "segment_s": SEGMENT / SAMPLE_RATE,
            "held_out": STEP_HELD_OUT,
            "nominal_device_given": "the reference device with T_dm = T_f = 0 (the truths' "
            "devices without a lag effect); J, μ, c, k_dm under a 5 % prior",
            "noise_std_V_log_uniform": list(NOISE_RANGE),
            "device_prior": "J, μ, c, k_dm log-normal 5 % (truncated at 2σ) about the reference",
            "external_moment_Nm_uniform": list(MOMENT_RANGE),
            "lag_s_log_uniform": list(LAG_RANGE),
            "stop_output_over_U_uniform": list(STOP_RANGE),
            "drift_V_over_record_log_uniform": list(DRIFT_RANGE),
            "gauss_markov_time_s_log_uniform": list(GM_TIME_RANGE),
            "gauss_markov_std_over_white_uniform": list(GM_RATIO_RANGE),
            "truth_simulators": "simulate_linear (lags, drift, noise); simulate_nonlinear with stops",
        }
    if kind == "vibration":
        plan = _vib_plan()
        return {
            "rows_per_table": int(plan["a_in"].size),
            "input_levels_g": list(VIB_LEVELS),
            "sine_amplitudes_g": list(VIB_SINE),
            "random_rms_g": list(VIB_RANDOM),
            "inclined_rows": f"{VIB_INCLINED} g in phase on IA and OA; {VIB_INCLINED} g on IA and PA",
            "frequency_Hz_uniform": list(VIB_FREQ_RANGE),
            "row_noise_g_log_uniform": list(VIB_ROW_NOISE),
            "device": f"a0 uniform {list(VIB_BIAS_RANGE)} g, δ normal sd {VIB_SCALE_SD}",
            "magnitudes_log_uniform_random_sign": {
                k: {
                    "range": list(v),
                    "unit": {
                        **aj.PPM_UNITS,
                        "cross_coupling": "ppm/g (m31 and m32 each)",
                    }[k],
                }
                for k, v in VIB_MAGNITUDES.items()
            },
            "snr_definition": "‖effect's mean-output contribution over the rows, minus its "
            "projection on the bias and scale-factor columns‖ / row noise σ",
            "truth_simulator": f"time average of indicated_acceleration over a {VIB_RECORD}-sample "
            f"record per row ({VIB_CYCLES} whole sine periods, random start phase; random "
            "vibration as centred independent Gaussian samples) + row noise",
            "held_out": "leave-one-out cross-validation over rows",
        }
    return {
        "sample_interval_s": NOISE_DT,
        "samples": NOISE_SAMPLES,
        "held_out": "the last third of the record",
        "white_std_g_log_uniform": list(NOISE_WHITE),
        "level_g": f"1 + uniform {list(NOISE_LEVEL)}",
        "gauss_markov": {
            "std_over_white_log_uniform": list(GM_STD_RATIO),
            "correlation_time_s_log_uniform": list(GM_TIME),
        },
        "exp_cosine": {
            "std_over_white_log_uniform": list(EC_STD_RATIO),
            "period_s_log_uniform": list(EC_PERIOD),
            "beta_over_alpha_log_uniform": list(EC_QUALITY),
        },
        "random_walk": {"walk_over_record_over_white_log_uniform": list(RW_WALK)},
        "snr_definition": "effect variance / white variance (random walk: q·T_record/σ_w²)",
        "truth_simulator": "simulate_noise (exact discrete-time sampling)",
    }


def _snr(kind, truths) -> list[float]:
    if kind == "vibration":
        return _vib_snr(truths)
    if kind == "noise":
        return [t["variance_ratio"] for t in truths]
    return [float("nan")] * len(truths)


SNR_EDGES = {
    "vibration": [0.0, 3.0, 5.0, 10.0, 20.0, 50.0, 1e9],
    "noise": [0.0, 0.2, 0.5, 1.0, 2.0, 5.0, 1e9],
}
SNR_LABEL = {
    "vibration": "SNR: ‖effect beyond bias & scale factor‖ / row noise",
    "noise": "effect variance / white variance (RW: qT/σ_w²)",
}


def _open_world_rows(kind: str, section: dict) -> list[dict]:
    """Summary rows of issue 19's open-world targets."""
    rows = []
    if "false_assurance" in section:
        worst = section["largest_gap_over_floor_with_none"]
        rows.append(
            {
                "quantity": f"{kind}: false assurance (verdict none with the true held-out gap "
                "≥ 3× the noise floor)",
                "ours": section["false_assurance"],
                "paper": 0,
                "target": "≤",
                "note": "target 0; the gap is the diagnosis's own held-out nominal "
                "residual against the noise the truth simulator drew (never shown to it); "
                f"{section['none_verdicts']} none verdicts, the largest gap among them "
                f"{_fmt_gap(worst)} floors.",
            }
        )
    if "nested_fits" in section:
        nested = section["nested_fits"]
        effects = ", ".join(f"{e} {n}" for e, n in sorted(nested["failed_by_effect"].items()))
        rows.append(
            {
                "quantity": f"{kind}: nested fits that ended below the nominal model they "
                "contain (flagged fit_failed)",
                "ours": nested["failed"],
                "paper": 0,
                "target": "≤",
                "note": "target 0: an effect switched off is the nominal model, so its fit "
                "cannot end below it; flagged, it is never ranked by its evidence. "
                f"{nested['failed']} of {nested['fits']} effect fits on "
                f"{len(nested['datasets_with_a_failed_fit'])} datasets, "
                f"{nested['failed_objective']} of them below the solver's penalised "
                "objective, the rest only in the reported ln L"
                + (f" ({effects}); largest shortfall "
                   f"{nested['largest_shortfall_lnL']:.3g} in ln L." if effects else ".")
                + " Below the nominal's penalised objective beyond its round-off share and "
                f"the restart threshold ({NESTED_RESTART_ABOVE:g} ln L), flagged or not: "
                f"{nested.get('objective_below_beyond_round_off', 0)} fits; the largest "
                "shortfall of that objective over every fit "
                f"{nested.get('largest_objective_below_nominal', 0.0):.3g}.",
            }
        )
    if "out_of_library_unexplained_rate" in section:
        rows.append(
            {
                "quantity": f"{kind}: out-of-library effects answered unexplained",
                "ours": section["out_of_library_unexplained_rate"],
                "paper": 0.90,
                "target": "≥",
                "note": "target ≥ 0.90 (pickoff nonlinearity, a band-pass velocity-"
                "output sensor, a periodic disturbance); 95 % interval "
                f"{_fmt_ci(section['out_of_library_unexplained_95ci'])} over "
                f"{section['n_out_of_library']} datasets.",
            }
        )
    return rows


def _open_world_figure(out_dir, kind, section, truths, verdicts, gaps) -> dict:
    """Confusion matrix of the open-world harness and the true gap behind each verdict."""
    classes = CLASSES[kind]
    verdict_names = list(next(iter(section["confusion"].values())))
    fig, axes = plt.subplots(1, 2, figsize=(15, 5.5))
    ax = axes[0]
    im = _confusion_panel(ax, section["confusion"], classes, verdict_names)
    ax.axhline(len(classes) - len(OUT_OF_LIBRARY.get(kind, ())) - 0.5, color="C3", lw=1)
    ax.set_xlabel("verdict (blind)")
    ax.set_ylabel("true effect (below the red line: outside the library)")
    ax.set_title(f"{kind}: confusion matrix (counts; colour = row fraction)")
    fig.colorbar(im, ax=ax, fraction=0.046)
    ax = axes[1]
    order = {v: k for k, v in enumerate(verdict_names)}
    rng = np.random.default_rng(0)
    for truth, verdict, gap in zip(truths, verdicts, gaps or [None] * len(truths), strict=True):
        if gap is None:
            continue
        outside = truth["effect"] in OUT_OF_LIBRARY.get(kind, ())
        colour = "C3" if outside else ("0.5" if truth["effect"] == "none" else "C0")
        ax.semilogx(
            max(gap, 1e-2),
            order[verdict["verdict"]] + rng.uniform(-0.2, 0.2),
            "o",
            ms=3,
            color=colour,
        )
    ax.axvline(3, color="k", ls=":", label="3× the noise floor")
    ax.set_yticks(range(len(verdict_names)), verdict_names, fontsize=8)
    ax.plot([], [], "o", color="0.5", label="no effect")
    ax.plot([], [], "o", color="C0", label="library effect")
    ax.plot([], [], "o", color="C3", label="outside the library")
    ax.set_xlabel("true held-out gap of the nominal refit / true noise floor (floored at 0.01)")
    ax.set_title("each verdict against the gap it was given")
    ax.legend(fontsize=8)
    fig.tight_layout()
    name = f"validation_{kind}.png"
    save_figure_atomic(fig, out_dir / name)
    plt.close(fig)
    return {
        "file": name,
        "caption": (
            "Blind open-world validation on records of the independent truth simulator "
            "(studies/step_truth.py: SciPy, its own conventions — either test-winding polarity, "
            "ADC offset and quantisation, 0.5–2 MHz, a 7-level test sequence on its own clock, "
            "records that start in a transient). Left: confusion matrix, with the classes "
            "outside the diagnosis's library below the red line (right answer: unexplained). "
            "Right: every verdict against the true held-out gap of the nominal refit in units "
            "of the true noise floor; no none may lie right of the dotted line."
        ),
    }


def _counts(kind, quick, large, per_class) -> dict:
    """Datasets per class of `kind` for a run's options."""
    if per_class is not None:
        return {c: per_class for c in CLASSES[kind]}
    if large:
        return PER_CLASS_LARGE[kind]
    if quick:
        return {c: PER_CLASS_QUICK[kind] for c in CLASSES[kind]}
    return PER_CLASS_FULL[kind]


def _per_class_stated(kind, quick, large, per_class):
    """The datasets per class as the result's assumptions state them."""
    if per_class is not None:
        return per_class
    if large:
        return PER_CLASS_LARGE[kind]
    return PER_CLASS_QUICK[kind] if quick else PER_CLASS_FULL[kind]


def _as_json(payload):
    """`payload` as it reads back from JSON (NumPy scalars and arrays as numbers and lists):
    a run scores exactly what a merge of its shards reads from their files."""
    return json.loads(json.dumps(payload, default=lambda x: np.asarray(x).tolist()))


# A quick run is compile-bound throughout and compiles with most XLA optimisations off
# (study_run(compile_bound_when_quick=True); measured on the 2-core CPU, quick, cache off: the dataset
# simulation, ~55 programs, 13 → 9 CPU-s). The blind diagnosis, run-bound, runs in its own
# process at the default optimisation.
@study_run(compile_bound_when_quick=True)
def run(
    out_dir: Path,
    *,
    quick: bool = False,
    seed: int = 20261122,
    kinds=KINDS,
    per_class=None,
    large: bool = False,
    shard: tuple[int, int] = (0, 1),
    merge=None,
) -> dict:
    """Run the study; write OUT/result.json and figures; return the result dict.

    `kinds`: which kinds to validate; `per_class`: datasets per class (overrides the
    defaults, e.g. for a larger run); `large`: `PER_CLASS_LARGE` (≥ 100 per kind of
    dataset, run by hand).

    Spread over machines: `shard=(k, n)` diagnoses records k, k+n, k+2n, … of each kind's
    draw (every shard draws and simulates the whole draw, then writes and diagnoses only
    its own records) and writes a shard file (OUT/result.json: its rows, not scored);
    `merge`: the shard files (paths) of one draw, every shard once, joined and scored as
    one run — the result of the run without shards, but for the timings and the
    provenance's date (`merge_shards`)."""
    out_dir = Path(out_dir)
    if merge is not None:
        joined = merge_shards([_read_shard(p) for p in merge])
        write_json_atomic(out_dir / "truth.json", _truth_file(joined["rows"]))
        return _score(out_dir, joined["draw"], joined["rows"], joined["timing"], None)
    started = time.perf_counter()
    timing = {}
    rng = np.random.default_rng(seed)
    rows, folders, noises = {}, [], {}
    data_root = out_dir / "datasets"
    for kind in kinds:
        kind_truths = _kind_truths(kind, rng, _counts(kind, quick, large, per_class))
        order = rng.permutation(len(kind_truths))  # file names carry no hint of the class
        kind_truths = [kind_truths[i] for i in order]
        t0 = time.perf_counter()
        records, kind_noises = _generate(kind, kind_truths, seed)
        keep = shard_indices(len(records), shard)
        folder = data_root / kind
        folder.mkdir(parents=True, exist_ok=True)
        for old in folder.glob("*.csv"):
            old.unlink()
        names = [f"{kind}_{i:04d}.csv" for i in keep]
        for name, i in zip(names, keep, strict=True):
            write_csv(folder / name, records[i])
        timing[f"generate_{kind}"] = time.perf_counter() - t0
        rows[kind] = {"index": keep, "file": names, "truth": [kind_truths[i] for i in keep]}
        noises[kind] = None if kind_noises is None else [kind_noises[i] for i in keep]
        folders.append(folder)
    t0 = time.perf_counter()
    answers = diagnose_blind(folders)
    timing["diagnose_all_kinds"] = time.perf_counter() - t0
    for kind, seconds in answers.pop("_seconds", {}).items():
        timing[f"diagnose_{kind}"] = seconds
    for kind in kinds:
        verdicts = answers[kind]
        if [v["file"] for v in verdicts] != rows[kind]["file"]:
            raise RuntimeError(
                f"the diagnosis returned verdicts for other {kind} files than were written"
            )
        rows[kind]["verdict"] = verdicts
        rows[kind]["true_gap"] = (
            true_gaps(noises[kind], verdicts) if noises[kind] is not None else None
        )
    rows = _as_json(rows)
    write_json_atomic(out_dir / "truth.json", _truth_file(rows))
    draw = {
        "seed": seed,
        "kinds": list(kinds),
        "per_class": {k: _per_class_stated(k, quick, large, per_class) for k in kinds},
        "records": {k: sum(_counts(k, quick, large, per_class).values()) for k in kinds},
    }
    if shard[1] == 1:
        return _score(out_dir, draw, rows, timing, started)
    timing["total"] = time.perf_counter() - started
    document = {
        "title": f"Blind validation, shard {shard[0]}/{shard[1]} of one draw (not scored: "
        "join every shard's result.json with --merge)",
        "shard": list(shard),
        "draw": draw,
        "rows": rows,
        "summary": [],
        "figures": [],
        "timing_s": timing,
        "provenance": provenance(seeds={"study": seed}, precision="float64"),
    }
    write_json_atomic(out_dir / "result.json", document)
    return document


def _truth_file(rows: dict) -> dict:
    """truth.json: each kind's truths by file name."""
    return {kind: dict(zip(r["file"], r["truth"], strict=True)) for kind, r in rows.items()}


def _read_shard(path) -> dict:
    """A shard's result.json, or a ValueError that names the file."""
    path = Path(path)
    try:
        document = json.loads(path.read_text())
    except (OSError, ValueError) as error:
        raise ValueError(f"{path}: cannot read a shard's result ({error})") from None
    if not isinstance(document, dict) or not {"shard", "draw", "rows"} <= set(document):
        raise ValueError(f"{path}: not a shard's result (a run with --shard k/n writes one)")
    return document


def merge_shards(documents: list[dict]) -> dict:
    """The shards of one draw (their result.json documents) joined: {"draw", "rows" (each
    kind's rows in the draw's order), "timing" (each shard's)}. Refused (ValueError) unless
    they are the n shards k/n of one draw, each once, run by one version of the package."""
    if not documents:
        raise ValueError("nothing to merge")
    first = documents[0]
    count = first["shard"][1]
    version = first["provenance"]["accel_jax_version"]
    for other in documents[1:]:
        if other["draw"] != first["draw"] or other["shard"][1] != count:
            raise ValueError("the shards are not of one draw (seed, kinds, datasets per class "
                             "or shard count differ)")
        if other["provenance"]["accel_jax_version"] != version:
            raise ValueError("the shards were run by different versions of accel_jax")
    given = sorted(d["shard"][0] for d in documents)
    if given != list(range(count)):
        twice = sorted({k for k in given if given.count(k) > 1})
        missing = sorted(set(range(count)) - set(given))
        problems = [f"given twice: {twice}"] * bool(twice) + [f"missing: {missing}"] * bool(missing)
        raise ValueError(
            f"a merge needs shards 0..{count - 1} of {count}, each once: " + "; ".join(problems)
        )
    draw = first["draw"]
    rows = {}
    for kind in draw["kinds"]:
        joined = sorted(
            (
                (i, d["rows"][kind], j)
                for d in documents
                for j, i in enumerate(d["rows"][kind]["index"])
            ),
            key=lambda row: row[0],
        )
        if [i for i, _, _ in joined] != list(range(draw["records"][kind])):
            raise ValueError(f"the shards' {kind} records are not the draw's, each once")
        rows[kind] = {
            key: (
                None
                if any(r[key] is None for _, r, _ in joined)
                else [r[key][j] for _, r, j in joined]
            )
            for key in ("index", "file", "truth", "verdict", "true_gap")
        }
    timing = {
        f"shard_{d['shard'][0]}_of_{count}": d["timing_s"]["total"]
        for d in sorted(documents, key=lambda d: d["shard"][0])
    }
    return {"draw": draw, "rows": rows, "timing": timing}


def _score(out_dir: Path, draw: dict, rows: dict, timing: dict, started) -> dict:
    """Score the blind verdicts of `rows` (each kind's files, truths, verdicts and true
    gaps, in the draw's order) against their truths; write OUT/result.json and the
    figures; return the result. `started`: the run's start (perf_counter), for its total
    time; None for a merge (its shards' times are in `timing`)."""
    result = {
        "title": "Blind validation of the sim-to-real diagnosis — step, vibration, noise",
    }
    figures, summary, datasets, assumptions = [], [], {}, {}
    target = "target"
    kinds = draw["kinds"]
    truths = {kind: rows[kind]["truth"] for kind in kinds}
    names = {kind: rows[kind]["file"] for kind in kinds}
    for kind in kinds:
        verdicts = rows[kind]["verdict"]
        gaps = rows[kind]["true_gap"]
        section = score(
            truths[kind], verdicts, CLASSES[kind], OUT_OF_LIBRARY.get(kind, ()), assurance=gaps
        )
        snr = _snr(kind, truths[kind])
        section["_shrinks"] = [
            v["gap"]["shrink"]
            for t, v in zip(truths[kind], verdicts, strict=True)
            if v["verdict"] == t["effect"] != "none"
        ]
        if kind in SNR_EDGES:
            effect_rows = [
                (s, v["verdict"] == t["effect"])
                for t, v, s in zip(truths[kind], verdicts, snr, strict=True)
                if t["effect"] != "none"
            ]
            section["_snr"] = [s for s, _ in effect_rows]
            section["_named"] = [ok for _, ok in effect_rows]
            section["correct_by_snr"] = _by_snr(truths[kind], verdicts, snr, SNR_EDGES[kind])
            effect_snr = np.asarray(section["_snr"])
            section["snr_percentiles_p10_p50_p90"] = (
                [float(np.percentile(effect_snr, q)) for q in (10, 50, 90)]
                if effect_snr.size
                else None
            )
            result[kind] = section
            figures.append(
                {
                    "file": _kind_figure(out_dir, kind, section, SNR_LABEL[kind]),
                    "caption": (
                        f"Blind validation of the {kind} diagnosis. Top: confusion matrix of true "
                        "effect vs blind verdict. Bottom left: held-out gap shrink where the effect was "
                        "named correctly. Bottom right: naming against the effect's signal-to-noise ratio "
                        f"({SNR_LABEL[kind]}); squares: fraction per bin. Magnitudes and noise as in "
                        "the assumptions block."
                    ),
                }
            )
        elif kind == "step":
            section["lag_forced_choice"] = lag_forced_choice(truths[kind], verdicts)
            result[kind] = section
            result["lag_breakdown"] = _lag_breakdown(truths[kind], verdicts)
            figures += _figures(out_dir, result, result["lag_breakdown"])
        else:
            result[kind] = section
            figures.append(_open_world_figure(out_dir, kind, section, truths[kind], verdicts, gaps))
        for key in ("_shrinks", "_snr", "_named"):
            section.pop(key, None)
        summary += [
            {
                "quantity": f"{kind}: effects named correctly (strict: verdict = true effect)",
                "ours": section["accuracy"],
                "paper": 0.90,
                "target": "≥",
                "note": f"{target} ≥ 0.90. cannot_tell counts as wrong here. 95 % interval "
                f"{_fmt_ci(section['accuracy_95ci'])} over {sum(section['n_per_class'].values()) - section['n_per_class']['none']} effect datasets.",
            },
            {
                "quantity": f"{kind}: effects named correctly or cannot_tell naming the true effect",
                "ours": section["accuracy_incl_cannot_tell_naming_truth"],
                "paper": 0.90,
                "target": "≥",
                "note": _LENIENT_NOTE[kind],
            },
            *(
                [
                    {
                        "quantity": "step: effects named if every lag cannot_tell were forced to "
                        "the lag with the higher evidence",
                        "ours": section["lag_forced_choice"]["accuracy_forced"],
                        "paper": 0.90,
                        "target": "≥",
                        "note": "the ideal-observer ceiling of strict naming on these datasets: "
                        f"{section['lag_forced_choice']['forced_datasets']} forced picks (median "
                        "evidence gap "
                        f"{_fmt_gap(section['lag_forced_choice']['evidence_gap_median'])} on the "
                        "2 ln B scale, < 6 = odds below 20 : 1); the evidence itself expects "
                        f"{section['lag_forced_choice']['accuracy_expected_by_evidence']:.2f}. "
                        "Forcing breaks the cannot_tell rule, so the diagnosis does not do it.",
                    }
                ]
                if "lag_forced_choice" in section
                else []
            ),
            {
                "quantity": f"{kind}: false-alarm rate on no-effect datasets",
                "ours": section["false_alarm_rate"],
                "paper": 0.05,
                "target": "≤",
                "note": f"{target} ≤ 0.05 ({section['false_alarms']} of "
                f"{section['n_per_class']['none']}; 95 % interval "
                f"{_fmt_ci(section['false_alarm_rate_95ci'])}).",
            },
            {
                "quantity": f"{kind}: median held-out gap shrink (effect named)",
                "ours": section["median_gap_shrink"],
                "paper": 0.5,
                "target": "≥",
                "note": f"{target} ≥ 0.5; {_GAP_NOTE[kind]}",
            },
            *_open_world_rows(kind, section),
        ]
        datasets[kind] = [
            {
                "file": name,
                "truth": truth["effect"],
                "verdict": verdict["verdict"],
                "tied": verdict["tied"],
                "gap_shrink": verdict["gap"]["shrink"],
                "gap_shrink_std": verdict["gap"]["shrink_std"],
                "explained_fraction": verdict.get("explained_fraction"),
                "reason": verdict.get("reason"),
                "failed_nested_fits": [
                    e["effect"] for e in verdict.get("ranking") or () if e.get("fit_failed")
                ],
                "true_gap_over_floor": g,
                "snr": s,
            }
            for name, truth, verdict, s, g in zip(
                names[kind],
                truths[kind],
                verdicts,
                _snr(kind, truths[kind]),
                gaps if gaps is not None else [None] * len(verdicts),
                strict=True,
            )
        ]
        assumptions[kind] = _assumptions(kind)
    if started is not None:
        timing["total"] = time.perf_counter() - started
    result.update(
        {
            "summary": summary,
            "datasets": datasets,
            "figures": figures,
            "assumptions": {
                **assumptions,
                "per_class": draw["per_class"],
                "blindness": "diagnosis in a separate process given only the CSV folders",
                "precision": "float64",
            },
            "timing_s": timing,
            "provenance": provenance(seeds={"study": draw["seed"]}, precision="float64"),
        }
    )
    result["overview"] = [_overview_table(result)]
    write_json_atomic(out_dir / "result.json", result)
    return result


def _fmt_gap(gap) -> str:
    return "n/a" if gap is None else f"{gap:.1f}"


def _fmt_ci(interval) -> str:
    return "n/a" if interval is None else f"[{interval[0]:.2f}, {interval[1]:.2f}]"


_LENIENT_NOTE = {
    "step_independent": "as for the library's own records, the two lags are exactly "
    "degenerate on a test-winding step up to the ±5 % prior; here over records of the "
    "independent simulator with every convention drawn at random.",
    "step": "torquer_lag and output_filter are exactly degenerate on a test-winding step: both "
    "give an all-pole third-order response, and a record one fits, the other fits exactly with "
    "J, μ and T shifted (to first order Δμ = k_dm k_dp k_y l·T). Only the ±5 % prior on J, μ, c, "
    "k_dm separates them, so small lags are honestly cannot_tell.",
    "vibration": "the rectified terms of A1, k2, k4 (and of k3, k5) are nearly collinear over a "
    "shaker plan (cosines 0.94–0.96 after removing bias and scale factor): at moderate SNR the "
    "data honestly cannot tell them apart.",
    "noise": "a Gauss–Markov noise is the β = 0 case of the exponential-cosine noise and tends to "
    "a random walk as τ_c outgrows the record; ties between nested models are resolved by a "
    "likelihood-ratio test, others stay cannot_tell.",
}
STEP_HELD_OUT = (
    "every third segment of constant test voltage from the third on (interleaved; the last "
    "third when a record has fewer than four segments)"
)
_GAP_NOTE = {
    "step_independent": "gap = held-out RMS free-run simulation error above the noise floor "
    "(block means; every third segment of constant test voltage held out).",
    "step": "gap = held-out RMS free-run simulation error above the noise floor (every third "
    "segment of constant test voltage held out).",
    "vibration": "gap = leave-one-out RMS residual above the noise floor, over the rows.",
    "noise": "gap = held-out RMS one-step prediction error above the chosen model's predicted "
    "innovation variance (last third of the record).",
}


def _overview_table(result: dict) -> dict:
    """The blind validation for the report's "At a glance": one row per kind of record."""
    rows = []
    labels = {"step_independent": "step (independent simulator, other conventions)"}
    for kind in ("step", "step_independent", "vibration", "noise"):
        section = result.get(kind)
        if not isinstance(section, dict) or "n_datasets" not in section:
            continue
        assurance = section.get("false_assurance")
        rows.append(
            [
                labels.get(kind, kind),
                section.get("n_datasets"),
                section.get("accuracy"),
                section.get("accuracy_incl_cannot_tell_naming_truth"),
                section.get("false_alarm_rate"),
                section.get("median_gap_shrink"),
                section.get("out_of_library_unexplained_rate", "–"),
                "–" if assurance is None else f"{assurance} of {section.get('none_verdicts')}",
            ]
        )
    return {
        "title": "Sim-to-real diagnosis, checked blind",
        "note": "Targets: ≥ 0.90 named, ≤ 0.05 false alarms, median shrink ≥ 0.5.",
        "columns": [
            "kind",
            "blind datasets",
            "named correctly",
            "… or cannot_tell naming the truth",
            "false alarms",
            "median held-out gap shrink",
            "outside the library: unexplained",
            "false assurance (none with a true gap ≥ 3 floors)",
        ],
        "rows": rows,
    }


def main(argv=None) -> int:
    def add_arguments(parser):
        parser.add_argument("--large", action="store_true", help="≥ 100 datasets per kind (slow)")
        parser.add_argument(
            "--kinds", default=",".join(KINDS), help="comma-separated subset of kinds"
        )
        parser.add_argument("--per-class", type=int, default=None, help="datasets per class")
        parser.add_argument(
            "--shard", type=parse_shard, default=(0, 1), metavar="k/n",
            help="diagnose only records k, k+n, k+2n, … of each kind's draw (spread a run "
            "over machines; join the shards' result.json files with --merge)",
        )
        parser.add_argument(
            "--merge", nargs="+", type=Path, default=None, metavar="RESULT_JSON",
            help="join the result.json files of shards 0/n … n-1/n of one draw and score "
            "them as one run (the draw is theirs: no --kinds, --per-class, --large, "
            "--quick or --shard with it)",
        )

    def options(args):
        if args.merge is not None:
            given = [
                flag
                for flag, value, default in (
                    ("--kinds", args.kinds, ",".join(KINDS)),
                    ("--per-class", args.per_class, None),
                    ("--large", args.large, False),
                    ("--quick", args.quick, False),
                    ("--shard", args.shard, (0, 1)),
                )
                if value != default
            ]
            if given:
                raise ValueError(f"--merge takes the draw from the shards: not with {given}")
            documents = [_read_shard(p) for p in args.merge]
            merge_shards(documents)  # refused here, before anything is written
            # The cache key: the shards' contents (a merge of other shard files is another
            # run, whatever their paths).
            digest = hashlib.sha256(
                json.dumps(documents, sort_keys=True).encode()
            ).hexdigest()[:16]
            return {"merge": [str(p.resolve()) for p in args.merge]}, {"merge": digest}
        kinds = tuple(k for k in args.kinds.split(",") if k)
        unknown = [k for k in kinds if k not in KINDS]
        if unknown:
            raise ValueError(f"unknown kind(s) {unknown}; choose from {list(KINDS)}")
        run_kwargs = {
            "kinds": kinds, "per_class": args.per_class, "large": args.large, "shard": args.shard
        }
        defaults = {"kinds": KINDS, "per_class": None, "large": False, "shard": (0, 1)}
        key = {k: v for k, v in run_kwargs.items() if v != defaults[k]}
        return run_kwargs, key

    def summary(res):
        if "shard" in res:
            k, n = res["shard"]
            counts = {kind: len(r["file"]) for kind, r in res["rows"].items()}
            print(f"shard {k}/{n}: records diagnosed {counts} (not scored: --merge the "
                  f"{n} shards' result.json files)")
            return
        print(json.dumps({k: res[k] for k in ("summary", "timing_s")}, indent=1, default=float))
        for kind in res.get("kinds", KINDS):
            if kind in res:
                print(kind, json.dumps(res[kind]["confusion"], indent=1))

    return study_main(
        run,
        __file__,
        __doc__,
        argv=argv,
        add_arguments=add_arguments,
        options=options,
        summary=summary,
    )


if __name__ == "__main__":
    sys.exit(main())
