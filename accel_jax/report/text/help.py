"""The `accel-jax` help as `--help` prints it: each command's description (`COMMANDS`, the
group's under "main") and each option's help by command and flag (`OPTIONS`), with the
help of the options several commands share (`device_help`, `out_help`)."""

from __future__ import annotations

COMMANDS = {
    "main": """accel-jax: servo (pendulum compensating) accelerometer design studies.

Run `accel-jax report` for the full design-study report, or `accel-jax info` for the
closed-form characteristics of the reference device.

Compiled XLA programs are kept in ~/.cache/accel_jax/xla, so a second `diagnose` or
`identify` of a record of the same kind starts faster ($ACCEL_JAX_CACHE_DIR moves it,
`off` disables it).""",
    "report": """Run every study and write a self-contained HTML report (OUT/index.html).

Interrupted runs resume: a study that finished with the same options and code is not
redone. Nothing is deleted unless --force.""",
    "info": "Print the closed-form characteristics of the reference device (Raspopov's values).",
    "tolerance": """Admissible nonlinearity coefficients A1, k2..k5, m for a vibration environment.

Limits by the paper's fixed budget shares (docs/models.md §3, eqs. 7-15) and by exact
sensitivities (jax.grad of the vibration error, same shares), in ppm units. With --unit,
each passport coefficient is judged against the gradient limit, and the unit's total
vibration error δ_V at the mean a3 against δ*. Example (the paper's Cyclone-4):
--budget 5e-4 --mean-accel 2 --sine 1.2 1.2 0.5 --psd examples/bands.csv --unit aks05""",
    "identify": """Identify the scale factor K_a from your own test-signal step record.

FILE is a CSV with a header row and columns t [s], u_test [V], u_out [V] (uniform
sampling, u_test held between samples). The first change of u_test is used. Prints the
paper's graph-analytic estimate (docs/models.md §1) and a least-squares fit of the whole
response: each parameter against the nominal device with its σ, the fit percentage and
NRMSE as MATLAB's compare defines them, and a Ljung-Box test of the residual's whiteness.

Several FILES of one device: each small-step record is identified as above; a record
whose test levels drive the pendulum onto its stops gives k_dp·k_y by eq. (11) from the
output's two plateaus and the device's h_max.""",
    "diagnose": """Diagnose the sim-to-real gap of one experiment (CSV, SI units, header row).

Several step records of one device (FILES: small steps, stop-level steps, acceleration
steps with an a_in column) are diagnosed together: one shared device, per-record
nuisances, and with cannot_tell the experiment that would break the tie.""",
    "noise": """Analyse a static record: Allan deviation, IEEE noise terms, effects, exports.

FILE is a noise CSV (header t,a_out; seconds and g; uniform sampling). Prints the
IEEE terms (Q, N, B, K, R) with their intervals (a term the data do not support is
given as an upper bound only), the effects the record shows (quantisation, periodic
lines, low-pass, flicker, Gauss-Markov, exponential-cosine, random walk, start-up
transient; what they leave is 'unexplained'), and the export.""",
}

_RECORDS_FORCE = "Replace an existing --json or --plot file."

OPTIONS = {
    "report": {
        "--out": "Folder for index.html; each study writes its own folder beside it.",
        "--quick": "Smaller sweeps (about 13 minutes on a 2-core CPU, most of it the blind "
        "validation's step records), compiled for compile speed "
        "on the CPU (XLA options recorded in each result's provenance; results equal to "
        "round-off).",
        "--force": "Replace earlier results in the output folders (by default finished "
        "studies are reused and folders from a different run are left alone).",
        "--no-progress": "No progress bars (e.g. in logs).",
        "--jobs": "Studies run at a time, each in its own process. Default: one per CPU core, "
        "at most 4 and at most one per 4 GiB of memory (the same on a GPU host: the "
        "processes share the GPU, none claiming its memory up front).",
        "--compile-cache/--no-compile-cache": "Keep compiled XLA programs on disk "
        "($ACCEL_JAX_CACHE_DIR, default ~/.cache/accel_jax/xla) so that later runs skip most "
        "of the compilation.",
        "--params": "Your device (TOML: ServoParams fields, value or {value, uncertainty}) for "
        "the studies of the closed loop; default the reference device (Raspopov's values, "
        "T_dm = T_f = 10 µs).",
    },
    "tolerance": {
        "--budget": "Admissible vibration error δ* [g], 0 < δ* ≤ 1 g (the paper's Cyclone-4: "
        "5e-4, i.e. 0.5 mg).",
        "--mean-accel": "Mean acceleration a3 along the input axis during flight [g].",
        "--sine": "Sinusoidal vibration amplitudes on the output, pendulum and input axes [g] "
        "(in phase).",
        "--sine-freq": "[Hz].",
        "--rms": "RMS of the random vibration on every axis [g] (fully correlated, as the "
        "paper's cross-coupling limit assumes). Or give --psd.",
        "--psd": "Random vibration as band PSDs: CSV with f_low,f_high,psd[,eta] (Hz, Hz, "
        "g²/Hz, 1); σ by the paper's formula sqrt((1/n) Σ η S Δf) (the vibration-error "
        "paper). Example: examples/bands.csv.",
        "--unit": "Check a unit's passport coefficients (Table 4) against the gradient limits, "
        "and its total vibration error δ_V at a3 against δ*.",
        "--json": "Also write the limits as JSON here.",
        "--force": "Replace an existing --json file.",
    },
    "identify": {
        "--params": "Nominal device (TOML: ServoParams fields, value or {value, uncertainty}); "
        "gives k_dp·k_y, γ, T_f and T_dm. Default: the reference device (Raspopov's values).",
        "--method": "Graph-analytic method; auto tries the oscillatory one and falls back to "
        "the aperiodic one when the response does not oscillate.",
        "--gamma": "Shape factor γ in K_a = γ T² k_dp k_y: 'exact' (m l²/J), 'paper' (3/4) or "
        "a number.",
        "--json": "Also write the result as JSON here.",
        "--plot": "Draw measured vs fitted model (graph method's t1, t2, A1, A2 marked), the "
        "residual in its ±2σ noise band and its autocorrelation here (PNG, or PDF or SVG by the "
        "suffix).",
        "--force": _RECORDS_FORCE,
    },
    "diagnose": {
        "--kind": "Force the kind of record (default: inferred from the CSV columns).",
        "--params": "Nominal device (TOML: ServoParams fields, value or {value, uncertainty}); "
        "default the reference device (Raspopov's values, T_dm = T_f = 10 µs, taken as "
        "known) with J, μ, c, k_dm known to ±5 %.",
        "--input-delay": "Step records: the input channels' known delay behind u_out's, in "
        "seconds (an ADC's skew, an anti-alias filter's group delay). Default: unknown, and "
        "for a measured u_test fitted, where it can take up a lag of the loop of its size.",
        "--discover/--no-discover": "Step records: where no library effect explains the record "
        "(unexplained), look for the missing term in a library of terms at named places in "
        "the loop (pickoff, spring, damping, torquer, output, forcing) and report it as a "
        "hypothesis: the term, its coefficient ± σ, the held-out gap it closes, its "
        "evidence and stability (on by default; about 1.8× a cold diagnosis of such a "
        "record on a CPU). Also for a record named a noise effect whose misfit a predictor "
        "partly foresees: a credible term that brings the held-out gap to the floor, where "
        "the noise does not, makes it unexplained. Vibration tables: the same search in a "
        "library of static terms (the library's k2…k5, A1, m31, m32 and k6, k7, |a3|a3, "
        "a1², a2², a1a2, a3a1²), which makes the verdict unexplained where such terms fit "
        "the table better than the named effect (well under a second a table).",
        "--ceiling": "Step records, with --discover: also fit a small network of the loop's "
        "states as a residual moment and output, and report how much of the held-out gap it "
        "removes and how much of that the discovered term reaches (an estimate of what a "
        "term of the states could do, never a verdict; 1–2 minutes more on a CPU).",
        "--json": "Write the diagnosis as JSON here.",
        "--plot": "Draw measured vs simulated, residuals, spectrum and ranking here (PNG, or "
        "PDF or SVG by the suffix).",
        "--force": _RECORDS_FORCE,
    },
    "noise": {
        "--json": "Write the analysis as JSON here.",
        "--plot": "Draw the Allan deviation with its ±1σ bands and the fitted IEEE terms, and "
        "the effects found step by step here (PNG, or PDF or SVG by the suffix).",
        "--export": "Print the identified model in this format (kalibr: imu.yaml "
        "accelerometer entries; gnss-ins-sim: its IMU error dictionary; ieee: IEEE Std "
        "952/1293 names).",
        "--confidence": "Confidence of the IEEE terms' intervals (parametric bootstrap).",
        "--force": _RECORDS_FORCE,
    },
}


def device_help(latency_bound: bool) -> str:
    """`--device`: where a command's work runs (`latency_bound`: small programs run once)."""
    where = (
        "auto runs this command's work (small programs, run once) on the CPU even where "
        "a GPU is present"
        if latency_bound
        else "auto runs the latency-bound work on the CPU and the Monte Carlo sweeps on a "
        "GPU where one is present"
    )
    return (
        f"Where the work runs: {where}; cpu or gpu put all of it there. Recorded in the provenance."
    )


def out_help(command: str) -> str:
    """`--out DIR` of a command writing `command`.json, .png and .txt."""
    return (
        f"Write everything under this folder: {command}.json, {command}.png and "
        f"{command}.txt (the printed summary); a relative --json or --plot goes under it too."
    )
