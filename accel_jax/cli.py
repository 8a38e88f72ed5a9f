"""The `accel-jax` command: a thin layer that parses, calls the library and prints."""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path

import click

_FILE = click.Path(dir_okay=False, path_type=Path)


def _file_option(flag: str, dest: str, help: str):
    """An option naming a file (not a folder), default none."""
    return click.option(flag, dest, type=_FILE, default=None, help=help)


STUDIES = (
    "scale_factor_identification",
    "sensing_element_ml",
    "vibration_compensation",
    "tolerance_limits",
    "noise_identification",
    "sim_to_real_validation",
    "table5_gap",
)
# Wall time of each study in a full report on a 2-core CPU, two at a time, each process
# pinned to one core (a fresh clone with a cold compilation cache, 2026-11-25) [s]: the
# report starts the longest first when it runs studies side by side (its order stays
# STUDIES).
TYPICAL_SECONDS = {
    "scale_factor_identification": 92,
    "sensing_element_ml": 113,
    "vibration_compensation": 16,
    "tolerance_limits": 10,
    "noise_identification": 245,  # with the §4 paper's filter loop (issue 23), alone, 2026-11-25
    "sim_to_real_validation": 815,  # 520 blind records (issue 19)
    "table5_gap": 1,
}


def _device_option(latency_bound: bool):
    """`--device auto|cpu|gpu` (default `$ACCEL_JAX_DEVICE`, else auto)."""
    where = (
        "auto runs this command's work (small programs, run once) on the CPU even where "
        "a GPU is present"
        if latency_bound
        else "auto runs the latency-bound work on the CPU and the Monte Carlo sweeps on a "
        "GPU where one is present"
    )
    return click.option(
        "--device",
        type=click.Choice(["auto", "cpu", "gpu"]),
        default="auto",
        envvar="ACCEL_JAX_DEVICE",
        show_default=True,
        help=f"Where the work runs: {where}; cpu or gpu put all of it there. Recorded in "
        "the provenance.",
    )


def _place(device: str, *, latency_bound: bool, shared: bool = False) -> None:
    """Apply `--device` before JAX starts its backend; a device that is not there is one
    line and exit status 1."""
    from ._runtime import DeviceError, apply_device

    try:
        apply_device(device, latency_bound=latency_bound, shared=shared)
    except DeviceError as error:
        raise click.ClickException(str(error)) from None


def _provenance() -> dict:
    """The provenance block of a command's JSON (versions, where the work ran, XLA options
    in effect and skipped, date), as each study's result carries it."""
    from ._io import provenance

    return {"provenance": provenance(precision="float64")}


def _studies_dir() -> Path:
    # Studies are scripts in the repository's studies/ folder, next to the package.
    return Path(__file__).resolve().parent.parent / "studies"


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="accel_jax")
@click.pass_context
def main(ctx):
    """accel-jax: servo (pendulum compensating) accelerometer design studies.

    Run `accel-jax report` for the full design-study report, or `accel-jax info` for the
    closed-form characteristics of the reference device.

    Compiled XLA programs are kept in ~/.cache/accel_jax/xla, so a second `diagnose` or
    `identify` of a record of the same kind starts faster ($ACCEL_JAX_CACHE_DIR moves it,
    `off` disables it).
    """
    from ._runtime import apply_fast_compile, enable_compilation_cache, quiet_xla_logs

    # The XLA:CPU deadlock workaround was applied by `import accel_jax` (see _runtime.py).
    quiet_xla_logs()  # no XLA log lines on the user's terminal (unless they ask)
    if ctx.invoked_subcommand != "report":  # report has its own --compile-cache switch
        # Single records are compile-bound: the persistent cache serves a second record of
        # the same kind, and the faster-compiling emitters (FAST_COMPILE_FLAGS) cut a cold
        # `diagnose` of a step record from 21.7 to 18.6 s in-process on the 2-core CPU; a
        # joint three-record diagnosis ran 48 s instead of 52 s, with the same evidence.
        enable_compilation_cache()
        apply_fast_compile()


@main.command()
@click.option(
    "--out",
    "out_dir",
    type=click.Path(file_okay=False, path_type=Path),
    default=Path("out/report"),
    show_default=True,
    help="Folder for index.html; each study writes its own folder beside it.",
)
@click.option(
    "--quick",
    is_flag=True,
    help="Smaller sweeps (a smoke run, minutes not tens), compiled for compile speed on the "
    "CPU (XLA options recorded in each result's provenance; results equal to round-off).",
)
@click.option(
    "--force",
    is_flag=True,
    help="Replace earlier results in the output folders (by default finished studies are "
    "reused and folders from a different run are left alone).",
)
@click.option("--no-progress", is_flag=True, help="No progress bars (e.g. in logs).")
@click.option(
    "--jobs",
    type=click.IntRange(min=1),
    default=None,
    help="Studies run at a time, each in its own process. Default: one per CPU core, at "
    "most 4 and at most one per 4 GiB of memory (1 on a GPU, whose memory every process "
    "would claim).",
)
@click.option(
    "--compile-cache/--no-compile-cache",
    default=True,
    show_default=True,
    help="Keep compiled XLA programs on disk ($ACCEL_JAX_CACHE_DIR, default "
    "~/.cache/accel_jax/xla) so that later runs skip most of the compilation.",
)
@_device_option(latency_bound=False)
@_file_option(
    "--params",
    "params_file",
    "Your device (TOML: ServoParams fields, value or {value, uncertainty}) for the "
    "studies of the closed loop; default the reference device (Raspopov's values, "
    "T_dm = T_f = 10 µs).",
)
def report(
    out_dir: Path,
    quick: bool,
    force: bool,
    no_progress: bool,
    jobs: int | None,
    compile_cache: bool,
    device: str,
    params_file,
):
    """Run every study and write a self-contained HTML report (OUT/index.html).

    Interrupted runs resume: a study that finished with the same options and code is not
    redone. Nothing is deleted unless --force.
    """
    from ._runtime import apply_fast_compile, enable_compilation_cache

    if quick:
        # Before anything starts JAX's backend: the quick report is compile-bound (most of
        # its programs run once or a few times), see FAST_COMPILE_FLAGS.
        apply_fast_compile()
    import jax

    # Studies measure effects below float32 resolution (δK_a at 0.1 %): run them in float64.
    jax.config.update("jax_enable_x64", True)
    from ._data import DataError, read_params_toml

    if compile_cache:
        folder = enable_compilation_cache()
        if folder is not None:
            click.echo(f"compilation cache: {folder}")
    # Latency-bound work on the CPU, sweeps on an accelerator (auto); the studies run side
    # by side, so none of them may claim a GPU's memory up front.
    _place(device, latency_bound=False, shared=True)
    from .report._run import ReportError, StudiesFailed, run_report

    params = None
    if params_file is not None:
        try:
            params = read_params_toml(params_file).params
        except DataError as error:
            raise click.ClickException(str(error)) from None
    try:
        index = run_report(
            out_dir,
            studies=STUDIES,
            studies_dir=_studies_dir(),
            quick=quick,
            force=force,
            progress=not no_progress,
            echo=click.echo,
            params=params,
            params_label=str(params_file) if params_file else None,
            jobs=jobs,
            typical_seconds=TYPICAL_SECONDS,
        )
    except StudiesFailed as error:
        click.echo(f"report written: {error.index}")
        click.echo(f"Error: {error}", err=True)
        sys.exit(1)
    except ReportError as error:
        raise click.ClickException(str(error)) from None
    except KeyboardInterrupt:
        click.echo(
            "\ninterrupted: finished studies are kept; run the same command again to resume.",
            err=True,
        )
        sys.exit(130)
    click.echo(f"report written: {index}")


@main.command()
def info():
    """Print the closed-form characteristics of the reference device (Raspopov's values)."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import accel_jax as aj

    for label, params in (
        ("oscillatory (reference)", aj.ServoParams.reference()),
        ("aperiodic (μ = 1.01e-4)", aj.ServoParams.reference_aperiodic()),
    ):
        click.echo(f"{label}:")
        click.echo(f"  scale factor K_a      = {float(aj.scale_factor(params)):.6g} V/(m/s²)")
        click.echo(f"  time constant T       = {float(aj.time_constant(params)):.6g} s")
        click.echo(f"  damping ratio ξ       = {float(aj.damping_ratio(params)):.6g}")
        click.echo(f"  test gain K_test      = {float(aj.closed_loop_test_gain(params)):.6g}")
        click.echo(f"  shape factor γ=ml²/J  = {float(aj.shape_factor(params)):.6g}")


def _out_option(command: str):
    """`--out DIR`: everything the command writes goes under DIR (created if missing)."""
    return click.option(
        "--out",
        "out_dir",
        type=click.Path(file_okay=False, dir_okay=True, path_type=Path),
        default=None,
        help=f"Write everything under this folder: {command}.json, {command}.png and "
        f"{command}.txt (the printed summary); a relative --json or --plot goes under it too.",
    )


def _route(out_dir: Path | None, command: str, **paths) -> dict:
    """The output paths with `--out DIR`: a path not given becomes DIR/<command>.<ext>, a
    relative one goes under DIR, an absolute one stays; plus `text`, DIR/<command>.txt.
    Without --out the paths are as given (and no text file)."""
    if out_dir is None:
        return {**paths, "text": None}
    if out_dir.exists() and not out_dir.is_dir():
        raise click.BadParameter(f"{out_dir} is a file, not a folder.", param_hint="--out")
    extension = {"json_out": "json", "plot_out": "png"}
    routed = {}
    for key, path in paths.items():
        if path is None:
            routed[key] = out_dir / f"{command}.{extension[key]}"
        else:
            routed[key] = path if path.is_absolute() else out_dir / path
    routed["text"] = out_dir / f"{command}.txt"
    return routed


def _write_text(path: Path | None, text: str, what: str = "summary") -> None:
    if path is None:
        return
    from ._io import _atomic_write_bytes

    path.parent.mkdir(parents=True, exist_ok=True)
    _atomic_write_bytes(path, (text.rstrip("\n") + "\n").encode())
    click.echo(f"{what} written: {path}")


def _writable(path: Path | None, force: bool, option: str) -> None:
    """Refuse to replace an existing output file unless --force (no user file is lost)."""
    if path is not None and path.exists() and not force:
        raise click.ClickException(
            f"{option} {path} already exists; pass --force to replace it, or choose another path."
        )


def _read_psd(path: Path):
    """A band-PSD CSV (header f_low,f_high,psd[,eta]; Hz, Hz, g²/Hz, 1) as a BandSpectrum."""
    import csv

    from ._vibration import BandSpectrum

    try:
        with open(path, newline="") as handle:
            rows = list(csv.DictReader(handle))
    except FileNotFoundError:
        raise click.ClickException(f"{path}: no such file.") from None
    except (OSError, UnicodeDecodeError, csv.Error) as error:
        raise click.ClickException(f"{path}: cannot be read ({error}).") from None
    if not rows:
        raise click.ClickException(f"{path}: no bands (a header f_low,f_high,psd[,eta] and rows).")
    missing = {"f_low", "f_high", "psd"} - set(rows[0])
    if missing:
        raise click.ClickException(
            f"{path}: missing column(s) {sorted(missing)}; expected f_low,f_high,psd[,eta] "
            "(Hz, Hz, g²/Hz, 1)."
        )
    columns = {}
    for name in ("f_low", "f_high", "psd", "eta"):
        if name not in rows[0]:
            continue
        try:
            columns[name] = [float(row[name]) for row in rows]
        except (TypeError, ValueError):
            raise click.ClickException(
                f"{path}: column {name!r} has a non-numeric value."
            ) from None
    try:
        return BandSpectrum(**columns)
    except ValueError as error:
        raise click.ClickException(f"{path}: {error}") from None


@main.command()
@click.option(
    "--budget",
    type=float,
    required=True,
    help="Admissible vibration error δ* [g], 0 < δ* ≤ 1 g (the paper's Cyclone-4: 5e-4, "
    "i.e. 0.5 mg).",
)
@click.option(
    "--mean-accel",
    type=float,
    default=1.0,
    show_default=True,
    help="Mean acceleration a3 along the input axis during flight [g].",
)
@click.option(
    "--sine",
    "sine",
    type=(float, float, float),
    default=(0.0, 0.0, 0.0),
    show_default=True,
    metavar="OA PA IA",
    help="Sinusoidal vibration amplitudes on the output, pendulum and input axes [g] (in phase).",
)
@click.option("--sine-freq", type=float, default=30.0, show_default=True, help="[Hz].")
@click.option(
    "--rms",
    type=float,
    default=None,
    help="RMS of the random vibration on every axis [g] (fully correlated, as the paper's "
    "cross-coupling limit assumes). Or give --psd.",
)
@_file_option(
    "--psd",
    "psd_file",
    "Random vibration as band PSDs: CSV with f_low,f_high,psd[,eta] (Hz, Hz, g²/Hz, 1); "
    "σ by the paper's formula sqrt((1/n) Σ η S Δf) (the vibration-error paper). "
    "Example: examples/bands.csv.",
)
@click.option(
    "--unit",
    type=click.Choice(["none", "aks05", "al1m"]),
    default="none",
    show_default=True,
    help="Check a unit's passport coefficients (Table 4) against the gradient limits, and "
    "its total vibration error δ_V at a3 against δ*.",
)
@_file_option(
    "--json",
    "json_out",
    "Also write the limits as JSON here.",
)
@click.option("--force", is_flag=True, help="Replace an existing --json file.")
def tolerance(budget, mean_accel, sine, sine_freq, rms, psd_file, unit, json_out, force):
    """Admissible nonlinearity coefficients A1, k2..k5, m for a vibration environment.

    Limits by the paper's fixed budget shares (docs/models.md §3, eqs. 7-15) and by exact
    sensitivities (jax.grad of the vibration error, same shares), in ppm units. With --unit,
    each passport coefficient is judged against the gradient limit, and the unit's total
    vibration error δ_V at the mean a3 against δ*. Example (the paper's Cyclone-4):
    --budget 5e-4 --mean-accel 2 --sine 1.2 1.2 0.5 --psd examples/bands.csv --unit aks05
    """
    import math

    import jax

    from ._format import number, precise

    # Limits are ratios of O(1e-4 g) budgets to exact sensitivities: float64 for ppm.
    jax.config.update("jax_enable_x64", True)
    from ._io import write_json_atomic
    from ._static import PPM_UNITS, StaticTransferFunction
    from ._tolerance import (
        TOLERANCED,
        ToleranceScenario,
        error_contributions,
        gradient_limits,
        paper_limits,
    )
    from ._vibration import VibrationEnvironment

    # A vibration-error budget above 1 g is a unit slip (mg or ppm typed as g): refused.
    max_budget = 1.0
    _writable(json_out, force, "--json")
    if rms is not None and psd_file is not None:
        raise click.UsageError("give the random vibration by --rms or by --psd, not both.")
    if not (math.isfinite(budget) and 0 < budget <= max_budget):
        raise click.BadParameter(
            f"{precise(budget)}; the budget must be positive and at most {max_budget:g} g: it "
            "is the admissible vibration error δ* in g (e.g. 5e-4 for 0.5 mg).",
            param_hint="--budget",
        )
    if not (math.isfinite(mean_accel) and mean_accel != 0):
        raise click.BadParameter(
            f"{precise(mean_accel)} g; it must be finite and non-zero (the multiplicative limits "
            "divide by it).",
            param_hint="--mean-accel",
        )
    if not all(math.isfinite(b) and b >= 0 for b in sine):
        raise click.BadParameter(
            f"{' '.join(repr(b) for b in sine)} g; the amplitudes (OA PA IA) must be finite "
            "and non-negative, e.g. 1.2 1.2 0.5.",
            param_hint="--sine",
        )
    if not (math.isfinite(sine_freq) and sine_freq > 0):
        raise click.BadParameter(
            f"{precise(sine_freq)} Hz; the frequency must be finite and positive.",
            param_hint="--sine-freq",
        )
    if rms is not None and not (math.isfinite(rms) and rms >= 0):
        raise click.BadParameter(
            f"{precise(rms)} g; the RMS must be finite and non-negative.", param_hint="--rms"
        )
    source = "none given"
    sigma = 0.0
    if psd_file is not None:
        spectrum = _read_psd(psd_file)
        sigma = float(spectrum.rms(paper=True))
        source = f"{psd_file}: {len(spectrum.psd)} bands, paper's σ formula"
    elif rms is not None:
        sigma, source = rms, "--rms"
    if sigma == 0 and not any(sine):
        raise click.UsageError(
            "no vibration given (every limit would be unbounded): give --sine amplitudes, "
            "--rms or --psd."
        )
    try:
        env = VibrationEnvironment(
            sine_amplitude=sine,
            sine_frequency=sine_freq,
            random_std=sigma,
            random_correlation=1.0,
        )
        scenario = ToleranceScenario(budget, mean_accel, env, [0.0], [mean_accel])
    except ValueError as error:
        raise click.ClickException(str(error)) from None
    paper = paper_limits(scenario)
    grad = gradient_limits(scenario)
    passport = {"aks05": StaticTransferFunction.aks05, "al1m": StaticTransferFunction.al1m}
    device = passport[unit]() if unit != "none" else None
    unit_ppm = device.as_ppm() if device is not None else {}
    # Each coefficient's signed part s_k·k of the unit's δ_V at a3; they add up to δ_V.
    parts = error_contributions(device, env, mean_accel) if device is not None else {}
    rows = {}
    for name in TOLERANCED:
        row = {
            "unit": PPM_UNITS[name],
            "paper_method": float(paper[name]) * 1e6,
            "gradient_paper_shares": float(grad["paper_shares"][name]) * 1e6,
            "gradient_full_budget": float(grad["full_budget"][name]) * 1e6,
            "sensitivity_g_per_ppm": float(grad["sensitivity"][name]) * 1e-6,
        }
        if unit_ppm:
            value = abs(unit_ppm.get(name, 0.0))
            row["passport"] = value
            row["within"] = bool(value <= row["gradient_paper_shares"])
            row["vibration_error_part_g"] = float(parts[name])
        rows[name] = row
    total = float(sum(parts.values())) if parts else None
    total_within = total is not None and abs(total) <= budget

    def num(value, width=10):  # 4 significant figures; ∞ where a term has no sensitivity
        return f"{number(value):>{width}}"

    axes = ("OA", "PA", "IA")
    amplitudes = ", ".join(f"{axis} {b:g}" for axis, b in zip(axes, sine, strict=True))
    click.echo(f"budget δ* = {budget:g} g, mean a3 = {mean_accel:g} g")
    click.echo(f"vibration: sine {amplitudes} g at {sine_freq:g} Hz (in phase)")
    click.echo(f"           random σ = {sigma:.4g} g on every axis ({source})")
    click.echo("limits on |coefficient|, in each row's unit (column unit):")
    click.echo("  paper     the paper's fixed budget shares and closed forms, eqs. (13), (15)")
    click.echo(
        f"  gradient  the paper's share of δ* over the exact sensitivity |∂δ_V/∂k| at "
        f"a3 = {mean_accel:g} g (jax.grad)"
    )
    click.echo("  full δ*   δ* over |∂δ_V/∂k|: that coefficient alone using the whole budget")
    if unit_ppm:
        # (Worded without "EXCEEDS", which marks only a coefficient over its limit.)
        click.echo(
            f"check: |{unit} passport coefficient| against the gradient limit (not the paper "
            "column): ok or over it"
        )
        click.echo("δ_V part: ∂δ_V/∂k · k, that coefficient's share of the unit's δ_V at a3 [g]")
    header = f"{'coef':<5}{'unit':<7}{'paper':>10}{'gradient':>10}{'full δ*':>10}"
    if unit_ppm:
        header += f"{unit + ' |k|':>11}{'δ_V part [g]':>14}  check"
    click.echo(header)
    for name, row in rows.items():
        line = (
            f"{'A1' if name == 'asymmetry' else name:<5}{row['unit']:<7}"
            f"{num(row['paper_method'])}{num(row['gradient_paper_shares'])}"
            f"{num(row['gradient_full_budget'])}"
        )
        if unit_ppm:
            mark = "ok" if row["within"] else "EXCEEDS"
            line += f"{num(row['passport'], 11)}{num(row['vibration_error_part_g'], 14)}  {mark}"
        click.echo(line)
    if total is None:
        click.echo(
            "total vibration error δ_V: no device coefficients given (--unit aks05 or al1m "
            "checks a passport's total against δ*)"
        )
    else:
        click.echo(
            f"{unit} passport: Table 4 of the vibration-error paper ('Improving the accuracy "
            "of a navigation accelerometer in rocket flight'), which gives no m31, m32 (taken "
            "as 0)"
        )
        click.echo(
            f"δ_V: the exact shift of the mean output at a3 = {mean_accel:g} g, the sum of the "
            "parts above"
        )
        click.echo(
            f"total vibration error δ_V = {total:.3g} g against the budget δ* = {budget:g} g: "
            f"{'within' if total_within else 'EXCEEDS'}"
        )
    if json_out is not None:
        check = {}
        if total is not None:
            check = {
                "unit_check": {
                    "passport": unit,
                    "judged_against": "gradient_paper_shares",
                    "total_vibration_error_g": total,
                    "within_budget": total_within,
                }
            }
        write_json_atomic(
            json_out,
            {
                "budget_g": budget,
                "mean_acceleration_g": mean_accel,
                "sine_amplitude_g": list(sine),
                "sine_frequency_Hz": sine_freq,
                "random_rms_g": sigma,
                "random_source": source,
                "limits_ppm": rows,
                **check,
                "assumptions": {
                    "paper_method": "fixed budget shares, eqs. (13), (15) of the "
                    "vibration-error paper",
                    "gradient": "exact sensitivities by jax.grad of the vibration error at "
                    "the mean a3, the paper's share per coefficient",
                    "random_vibration": "Gaussian, same σ on every axis, fully correlated",
                    "precision": "float64",
                },
            },
        )
        click.echo(f"json written: {json_out}")


@main.command()
@click.argument("files", nargs=-1, required=True, type=_FILE)
@_file_option(
    "--params",
    "params_file",
    "Nominal device (TOML: ServoParams fields, value or {value, uncertainty}); gives "
    "k_dp·k_y, γ, T_f and T_dm. Default: the reference device (Raspopov's values).",
)
@click.option(
    "--method",
    type=click.Choice(["auto", "oscillatory", "aperiodic"]),
    default="auto",
    show_default=True,
    help="Graph-analytic method; auto tries the oscillatory one and falls back to the "
    "aperiodic one when the response does not oscillate.",
)
@click.option(
    "--gamma",
    default="exact",
    show_default=True,
    help="Shape factor γ in K_a = γ T² k_dp k_y: 'exact' (m l²/J), 'paper' (3/4) or a number.",
)
@_file_option(
    "--json",
    "json_out",
    "Also write the result as JSON here.",
)
@_file_option(
    "--plot",
    "plot_out",
    "Draw measured vs fitted model (graph method's t1, t2, A1, A2 marked), the residual in "
    "its ±2σ noise band and its autocorrelation (PNG) here.",
)
@_out_option("identify")
@click.option("--force", is_flag=True, help="Replace an existing --json or --plot file.")
@_device_option(latency_bound=True)
def identify(files, params_file, method, gamma, json_out, plot_out, out_dir, force, device):
    """Identify the scale factor K_a from your own test-signal step record.

    FILE is a CSV with a header row and columns t [s], u_test [V], u_out [V] (uniform
    sampling, u_test held between samples). The first change of u_test is used. Prints the
    paper's graph-analytic estimate (docs/models.md §1) and a least-squares fit of the whole
    response: each parameter against the nominal device with its σ, the fit percentage and
    NRMSE as MATLAB's compare defines them, and a Ljung-Box test of the residual's whiteness.

    Several FILES of one device: each small-step record is identified as above; a record
    whose test levels drive the pendulum onto its stops gives k_dp·k_y by eq. (11) from the
    output's two plateaus and the device's h_max.
    """
    paths = _route(out_dir, "identify", json_out=json_out, plot_out=plot_out)
    json_out, plot_out = paths["json_out"], paths["plot_out"]
    _writable(json_out, force, "--json")  # refused before the work, not after it
    _writable(plot_out, force, "--plot")
    _writable(paths["text"], force, "--out")
    _place(device, latency_bound=True)
    import jax

    # δK_a at the 0.1 % level and crossing times to 1e-9 s are below float32 resolution.
    jax.config.update("jax_enable_x64", True)
    from ._data import DataError, NominalDevice, read_csv, read_params_toml
    from ._identify import report
    from ._identify.step_record import identify_step_record
    from ._io import save_figure_atomic, write_json_atomic

    try:
        gamma_value = gamma if gamma in ("exact", "paper") else float(gamma)
    except ValueError:
        raise click.BadParameter(
            f"{gamma!r} is not 'exact', 'paper' or a number.", param_hint="--gamma"
        ) from None
    if len(files) > 1:
        _identify_set(files, params_file, method, gamma_value, json_out, paths["text"])
        if plot_out is not None:
            click.echo("note: --plot draws one record; with several files it is not drawn")
        return
    file = files[0]
    try:
        data = read_csv(file, kind="step")
        nominal = read_params_toml(params_file) if params_file else NominalDevice.reference()
        result = identify_step_record(data, nominal.params, method=method, gamma=gamma_value)
    except DataError as error:
        raise click.ClickException(str(error)) from None
    click.echo(report.identification_summary(result))
    _write_text(paths["text"], report.identification_summary(result))
    if json_out is not None:
        # The traces (the record and the model, sample by sample) stay out of the JSON.
        payload = {k: v for k, v in result.items() if k != "traces"}
        write_json_atomic(json_out, {"source": str(file), **payload, **_provenance()})
        click.echo(f"json written: {json_out}")
    if plot_out is not None:
        save_figure_atomic(report.identification_figure(result, title=str(file)), plot_out)
        click.echo(f"plot written: {plot_out}")


def _identify_set(files, params_file, method, gamma_value, json_out, text_out) -> None:
    """`identify A.csv B.csv …`: small-step records by the graph method and the fit,
    stop-level records by eq. (11)."""
    from ._data import DataError, NominalDevice, read_csv, read_params_toml
    from ._identify import report
    from ._identify.step_record import identify_step_record
    from ._identify.stops import stop_record_gain
    from ._io import write_json_atomic
    from ._servo import closed_loop_test_gain

    if len(set(files)) != len(files):
        raise click.ClickException("a file is named twice; give each record once.")
    lines, payload = [], []
    try:
        nominal = read_params_toml(params_file) if params_file else NominalDevice.reference()
        params = nominal.params
        reach = 0.5 * float(params.pickoff_gain * params.amplifier_gain * params.stop_displacement)
        k_test = float(closed_loop_test_gain(params))
        datasets = [read_csv(file, kind="step") for file in files]
        for file, data in zip(files, datasets, strict=True):
            if float(abs(data.u_test).max()) * k_test >= reach:
                stops = stop_record_gain(data, params)
                lines.append(
                    f"{file}: stop-level record, eq. (11): k_dp·k_y = "
                    f"{stops['pickoff_amplifier_gain_V_per_m']:.6g} V/m (nominal "
                    f"{stops['nominal_V_per_m']:.6g}, {stops['shift_relative']:+.2%}) from "
                    f"U⁺ = {stops['u_plus_V']:.5g} V, U⁻ = {stops['u_minus_V']:.5g} V, h_max = "
                    f"{stops['h_max_m']:.4g} m (the device's); output offset "
                    f"{stops['offset_V']:+.4g} V"
                )
                payload.append({"source": str(file), "stops": stops})
            else:
                result = identify_step_record(data, params, method=method, gamma=gamma_value)
                lines.append(f"{file}:\n" + report.identification_summary(result))
                payload.append(
                    {"source": str(file), **{k: v for k, v in result.items() if k != "traces"}}
                )
    except DataError as error:
        raise click.ClickException(str(error)) from None
    text = "\n".join(lines)
    click.echo(text)
    _write_text(text_out, text)
    if json_out is not None:
        write_json_atomic(json_out, {"records": payload, **_provenance()})
        click.echo(f"json written: {json_out}")


@main.command()
@click.argument("files", nargs=-1, required=True, type=_FILE)
@click.option(
    "--kind",
    type=click.Choice(["step", "vibration", "noise"]),
    default=None,
    help="Force the kind of record (default: inferred from the CSV columns).",
)
@_file_option(
    "--params",
    "params_file",
    "Nominal device (TOML: ServoParams fields, value or {value, uncertainty}); "
    "default the reference device (Raspopov's values, T_dm = T_f = 10 µs, taken as "
    "known) with J, μ, c, k_dm known to ±5 %.",
)
@_file_option(
    "--json",
    "json_out",
    "Write the diagnosis as JSON here.",
)
@_file_option(
    "--plot",
    "plot_out",
    "Draw measured vs simulated, residuals, spectrum and ranking (PNG) here.",
)
@_out_option("diagnosis")
@click.option("--force", is_flag=True, help="Replace an existing --json or --plot file.")
@_device_option(latency_bound=True)
def diagnose(
    files: tuple[Path, ...], kind, params_file, json_out, plot_out, out_dir, force, device
):
    """Diagnose the sim-to-real gap of one experiment (CSV, SI units, header row).

    Several step records of one device (FILES: small steps, stop-level steps, acceleration
    steps with an a_in column) are diagnosed together: one shared device, per-record
    nuisances, and with cannot_tell the experiment that would break the tie."""
    paths = _route(out_dir, "diagnosis", json_out=json_out, plot_out=plot_out)
    json_out, plot_out = paths["json_out"], paths["plot_out"]
    _writable(json_out, force, "--json")  # refused before the work, not after it
    _writable(plot_out, force, "--plot")
    _writable(paths["text"], force, "--out")
    _place(device, latency_bound=True)
    import jax

    # Evidence compares log-likelihoods of ~1e4 to within ~1: float64.
    jax.config.update("jax_enable_x64", True)
    from ._data import DataError, NominalDevice, read_csv, read_params_toml
    from .diagnose import diagnose as run_diagnosis
    from .diagnose.report import save_plot, write_json

    if len(files) > 1:
        _diagnose_set(files, kind, params_file, json_out, plot_out, paths["text"])
        return
    file = files[0]
    try:
        data = read_csv(file, kind=kind)
        nominal = read_params_toml(params_file) if params_file else NominalDevice.reference()
        result = run_diagnosis(data, nominal)
    except DataError as error:
        raise click.ClickException(str(error)) from None
    click.echo(result.summary())
    _write_text(paths["text"], result.summary())
    if params_file is not None and data.kind != "step":
        click.echo(
            f"note: --params is not used by the {data.kind} diagnosis (its nominal model "
            "has no servo-loop parameters)"
        )
    if json_out is not None:
        write_json(result, json_out, source=file, extra=_provenance())
        click.echo(f"json written: {json_out}")
    if plot_out is not None:
        save_plot(result, plot_out)
        click.echo(f"plot written: {plot_out}")


def _diagnose_set(files, kind, params_file, json_out, plot_out, text_out) -> None:
    """`diagnose A.csv B.csv …`: the joint diagnosis of several step records of one device."""
    from ._data import DataError, NominalDevice, read_csv, read_params_toml
    from ._io import save_figure_atomic, write_json_atomic
    from .diagnose.report import set_figure
    from .diagnose.step_joint_verdict import diagnose_step_set

    if kind not in (None, "step"):
        raise click.ClickException(
            f"several files are diagnosed together only as step records of one device; "
            f"--kind {kind} takes one file."
        )
    if len(set(files)) != len(files):
        raise click.ClickException("a file is named twice; give each record once.")
    try:
        datasets = [read_csv(file) for file in files]
        kinds = {str(file): d.kind for file, d in zip(files, datasets, strict=True)}
        if set(kinds.values()) != {"step"}:
            listed = ", ".join(f"{f} ({k})" for f, k in kinds.items())
            raise DataError(
                "several files are diagnosed together only when every one is a step record "
                f"(t, u_test, u_out[, a_in]) of one device; got {listed}."
            )
        nominal = read_params_toml(params_file) if params_file else NominalDevice.reference()
        result = diagnose_step_set(datasets, nominal, names=[str(f) for f in files])
    except DataError as error:
        raise click.ClickException(str(error)) from None
    click.echo(result.summary())
    _write_text(text_out, result.summary())
    if json_out is not None:
        payload = {"sources": [str(f) for f in files], **result.to_dict(), **_provenance()}
        write_json_atomic(json_out, payload)
        click.echo(f"json written: {json_out}")
    if plot_out is not None:
        save_figure_atomic(set_figure(result), plot_out)
        click.echo(f"plot written: {plot_out}")


@main.command()
@click.argument("file", type=_FILE)
@_file_option("--json", "json_out", "Write the analysis as JSON here.")
@_file_option(
    "--plot",
    "plot_out",
    "Draw the Allan deviation with its ±1σ bands and the fitted IEEE terms, and the "
    "effects found step by step (PNG) here.",
)
@click.option(
    "--export",
    "export_format",
    type=click.Choice(["kalibr", "gnss-ins-sim", "ieee"]),
    default=None,
    help="Print the identified model in this format (kalibr: imu.yaml accelerometer "
    "entries; gnss-ins-sim: its IMU error dictionary; ieee: IEEE Std 952/1293 names).",
)
@click.option(
    "--confidence",
    type=click.FloatRange(0.5, 0.999),
    default=0.95,
    show_default=True,
    help="Confidence of the IEEE terms' intervals (parametric bootstrap).",
)
@_out_option("noise")
@click.option("--force", is_flag=True, help="Replace an existing --json or --plot file.")
@_device_option(latency_bound=True)
def noise(file: Path, json_out, plot_out, export_format, confidence, out_dir, force, device):
    """Analyse a static record: Allan deviation, IEEE noise terms, effects, exports.

    FILE is a noise CSV (header t,a_out; seconds and g; uniform sampling). Prints the
    IEEE terms (Q, N, B, K, R) with their intervals (a term the data do not support is
    given as an upper bound only), the effects the record shows (quantisation, periodic
    lines, low-pass, flicker, Gauss-Markov, exponential-cosine, random walk, start-up
    transient; what they leave is 'unexplained'), and the export.
    """
    paths = _route(out_dir, "noise", json_out=json_out, plot_out=plot_out)
    json_out, plot_out = paths["json_out"], paths["plot_out"]
    export_out = None
    if out_dir is not None and export_format is not None:
        suffix = {"kalibr": "imu.yaml", "gnss-ins-sim": "gnss_ins_sim.json", "ieee": "ieee.json"}
        export_out = out_dir / f"noise_{suffix[export_format]}"
    for path, option in (
        (json_out, "--json"),
        (plot_out, "--plot"),
        (paths["text"], "--out"),
        (export_out, "--out"),
    ):
        _writable(path, force, option)
    _place(device, latency_bound=True)
    printed: list[str] = []

    def say(text: str = "") -> None:
        printed.append(text)
        click.echo(text)

    import jax

    # Whittle log-likelihoods of up to 10^6 samples compared to within a unit: float64.
    jax.config.update("jax_enable_x64", True)
    from ._data import DataError, read_csv
    from ._io import write_json_atomic
    from ._noise import analysis, export
    from ._noise.sensor import UNEXPLAINED_Z
    from ._noise.sensor_text import (
        level_shift_sentence,
        non_gaussian_sentence,
        saturation_sentence,
        spectral_change_sentence,
    )

    try:
        data = read_csv(file, kind="noise")
        result = analysis.analyse_static_record(
            data.a_out, data.sample_period, unit="g", confidence=confidence
        )
    except (DataError, ValueError) as error:
        raise click.ClickException(str(error)) from None
    terms, selection = result["terms"], result["selection"]
    say(
        f"{data.a_out.size} samples at {1 / data.sample_period:.6g} Hz "
        f"({data.a_out.size * data.sample_period:.6g} s)"
    )
    say(f"IEEE noise terms ({terms.confidence:.0%} intervals; method in --json):")
    for name, entry in terms.terms.items():
        unit = entry["unit"].replace("u", "g")  # the record's unit
        if entry["supported"]:
            say(
                f"  {name} = {entry['value']:.4g} {unit} "
                f"[{entry['lower']:.3g}, {entry['upper']:.3g}]"
            )
        elif entry["upper"] > 0:
            say(f"  {name}: not supported by the data (< {entry['upper']:.3g} {unit})")
        else:
            say(f"  {name}: not supported by the data (its whole interval is below 0)")
    if "sinusoid" in selection.effects or "bandlimit" in selection.effects:
        say(
            "  (the five terms describe the ADEV alone: the periodic lines and the low-pass "
            "found below also shape it, mostly as B and N)"
        )
    say(f"effects: {selection.verdict}")
    for step in selection.steps[1:]:
        was = f" (added as {step['replaced']}, exchanged below)" if "replaced" in step else ""
        say(
            f"  + {step['added']}{was}: 2 ln B = {step['evidence']:.1f}, explained "
            f"{step['explained_fraction']:.1%} of the held-out excess"
        )
    for entry in selection.held_out.get("removed", []):
        say(
            f"  − {entry['effect']}: added on the way, dropped by the backward check "
            f"(2 ln B = {entry['evidence']:.1f} against the final model)"
        )
    for entry in selection.held_out.get("exchanged", []):
        say(
            f"  ⇄ {entry['by']} in place of {entry['effect']}: "
            f"2 ln B = {entry['evidence']:.1f} in its favour"
        )
    for entry in selection.held_out.get("ties", []):
        say(
            f"  ? {entry['effect']} or {entry['alternative']}: the record cannot tell them "
            f"apart (2 ln B = {entry['evidence']:.1f}, < {entry['bar']:g})"
        )
    held = selection.held_out
    for shift in held.get("level_shifts", []):
        say(f"  unexplained: {level_shift_sentence(shift)}")
    if held.get("more_level_shifts"):
        say("  unexplained: more steps in the level than were taken out")
    for rail in held.get("saturation", []):
        say(f"  unexplained: {saturation_sentence(rail)}")
    if held.get("non_gaussian", {}).get("significant") and not held.get("bursts"):
        say(f"  unexplained: {non_gaussian_sentence(held['non_gaussian'])}")
    if held.get("spectral_change", {}).get("significant"):
        duration = selection.n_samples * selection.sample_interval
        say(f"  unexplained: {spectral_change_sentence(held['spectral_change'], duration)}")
    for burst in held.get("bursts", [])[:5]:
        say(
            f"  unexplained: an impulsive event at {burst['start_s']:.4g} s (peak "
            f"{burst['peak']:.3g} g from the median level)"
        )
    if selection.unexplained and held["z"] > UNEXPLAINED_Z:
        say(
            f"  unexplained: the held-out spectrum stays {held['z']:.1f} standard "
            "errors above the final model's"
        )
    elif held.get("drifting") and not held.get("bursts"):
        say(
            f"  unexplained: the level drifts {held['drift']['slope_per_s']:.3g} g/s "
            f"({held['drift']['t']:.0f} standard errors), which no named effect makes"
        )
    if selection.quantization is not None:
        say(f"  output grid: step {selection.quantization['step']:.4g} g")
    if export_format is not None:
        t = result["export_terms"]
        if export_format == "kalibr":
            if t.random_walk is None:
                # kalibr needs a random walk > 0: the data's upper bound, said so
                bound = terms.terms["K"]["upper"] if "K" in terms.terms else 0.0
                if not bound > 0:
                    raise click.ClickException(
                        "kalibr needs accelerometer_random_walk > 0 and the record gives no "
                        "bound on K (choose --export gnss-ins-sim or ieee)."
                    )
                t = dataclasses.replace(t, random_walk=bound)
                say(
                    f"note: K is not supported by the data; kalibr gets its {terms.confidence:.0%}"
                    f" upper bound {bound:.3g} g/√s (conservative)"
                )
            exported = export.kalibr_yaml(t)
        elif export_format == "gnss-ins-sim":
            exported = json.dumps(export.to_gnss_ins_sim(t), indent=1, default=_plain)
        else:
            exported = json.dumps(export.to_ieee(t), indent=1, default=_plain)
        if export_out is None:
            say(exported)
        else:
            _write_text(export_out, exported, what=f"{export_format} export")
    _write_text(paths["text"], "\n".join(printed))
    if json_out is not None:
        payload = {"source": str(file), **analysis.analysis_to_json(result), **_provenance()}
        write_json_atomic(json_out, payload)
        click.echo(f"json written: {json_out}")
    if plot_out is not None:
        analysis.plot_analysis(result, plot_out, title=str(file))
        click.echo(f"plot written: {plot_out}")


def _plain(value):
    import numpy as np

    return np.asarray(value).tolist()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
