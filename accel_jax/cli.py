"""The `accel-jax` command: a thin layer that parses, calls the library, prints what
`accel_jax.report.text` renders (the help too: `report.text.help`) and writes the files
(`report._command`: the options and output rules the commands share)."""

from __future__ import annotations

import functools
import os
import sys
from pathlib import Path

import click

from .report._command import (
    FILE,
    check_outputs,
    device_option,
    json_writer,
    option,
    outputs,
    route,
    write,
)
from .report._studies import STUDIES, TYPICAL_SECONDS
from .report.text.help import COMMANDS

_report, _tolerance, _identify, _diagnose, _noise = (
    functools.partial(option, command)
    for command in ("report", "tolerance", "identify", "diagnose", "noise")
)


def _place(device: str, *, latency_bound: bool, shared: bool = False) -> None:
    """Apply `--device` before JAX starts its backend; a device that is not there is one
    line and exit status 1."""
    from ._placement import DeviceError, apply_device

    try:
        apply_device(device, latency_bound=latency_bound, shared=shared)
    except DeviceError as error:
        raise click.ClickException(str(error)) from None


def _start(command: str, out_dir, force: bool, device: str, json_out, plot_out, *more) -> dict:
    """Before a records command's work: its output paths (`route`), each refused if it exists
    unless --force, as the (path, option) pairs `more`; the work placed (--device); float64
    (evidence to ~1 in ~1e4, δK_a at 0.1 %, crossing times to 1e-9 s: below float32's)."""
    paths = route(out_dir, command, json_out=json_out, plot_out=plot_out)
    checked = ((paths["json_out"], "--json"), (paths["plot_out"], "--plot"))
    check_outputs((*checked, (paths["text"], "--out"), *more), force)
    _place(device, latency_bound=True)
    import jax

    jax.config.update("jax_enable_x64", True)
    return paths


class _refused:
    """Bad user input (`DataError`, or one of `errors`) is one line and exit status 1 (its
    `__exit__` returns None: the type checker sees that it never swallows an exception)."""

    def __init__(self, *errors: type[Exception]):
        self.errors = errors

    def __enter__(self) -> None:
        return None

    def __exit__(self, kind, error, traceback) -> None:
        from . import DataError

        if error is not None and isinstance(error, (DataError, *self.errors)):
            raise click.ClickException(str(error)) from None


def _nominal(params_file: Path | None):
    """The nominal device of --params, or the reference device."""
    from . import NominalDevice, read_params_toml

    return read_params_toml(params_file) if params_file else NominalDevice.reference()


def _studies_dir() -> Path:
    # Studies are scripts in the repository's studies/ folder, next to the package.
    return Path(__file__).resolve().parent.parent / "studies"


@click.group(context_settings={"help_option_names": ["-h", "--help"]}, help=COMMANDS["main"])
@click.version_option(package_name="accel_jax")
@click.pass_context
def main(ctx):
    from ._cache import enable_compilation_cache
    from ._runtime import apply_fast_compile, quiet_xla_logs

    # The XLA:CPU deadlock workaround was applied by `import accel_jax` (see _runtime.py).
    quiet_xla_logs()  # no XLA log lines on the user's terminal (unless they ask)
    if ctx.invoked_subcommand != "report":  # report has its own --compile-cache switch
        # Single records are compile-bound: the persistent cache serves a second record of
        # the same kind, and the faster-compiling emitters (FAST_COMPILE_FLAGS) cut a cold
        # `diagnose` of a step record from 21.7 to 18.6 s in-process on the 2-core CPU; a
        # joint three-record diagnosis ran 48 s instead of 52 s, with the same evidence.
        enable_compilation_cache()
        apply_fast_compile()


@main.command(help=COMMANDS["report"])
@_report(
    "--out",
    "out_dir",
    type=click.Path(file_okay=False, path_type=Path),
    default=Path("out/report"),
    show_default=True,
)
@_report("--quick", is_flag=True)
@_report("--force", is_flag=True)
@_report("--no-progress", is_flag=True)
@_report("--jobs", type=click.IntRange(min=1), default=None)
@_report("--compile-cache/--no-compile-cache", default=True, show_default=True)
@device_option(latency_bound=False)
@_report("--params", "params_file")
def report(out_dir, quick, force, no_progress, jobs, compile_cache, device, params_file):
    from ._cache import enable_compilation_cache
    from ._runtime import apply_fast_compile

    if quick:
        # Before anything starts JAX's backend: the quick report is compile-bound (most of
        # its programs run once or a few times), see FAST_COMPILE_FLAGS.
        apply_fast_compile()
    import jax

    # Studies measure effects below float32 resolution (δK_a at 0.1 %): run them in float64.
    jax.config.update("jax_enable_x64", True)
    from . import read_params_toml

    if compile_cache:
        folder = enable_compilation_cache()
        if folder is not None:
            click.echo(f"compilation cache: {folder}")
    # Latency-bound work on the CPU, sweeps on an accelerator (auto); the studies run side
    # by side, so none of them may claim a GPU's memory up front.
    _place(device, latency_bound=False, shared=True)
    from .report._run import ReportError, StudiesFailed, run_report

    with _refused():
        params = read_params_toml(params_file).params if params_file is not None else None
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


@main.command(help=COMMANDS["info"])
def info():
    import jax

    jax.config.update("jax_enable_x64", True)
    from . import ServoParams
    from .report.text.info import info_lines

    for label, params in (
        ("oscillatory (reference)", ServoParams.reference()),
        ("aperiodic (μ = 1.01e-4)", ServoParams.reference_aperiodic()),
    ):
        click.echo("\n".join(info_lines(label, params)))


@main.command(help=COMMANDS["tolerance"])
@_tolerance("--budget", type=float, required=True)
@_tolerance("--mean-accel", type=float, default=1.0, show_default=True)
@_tolerance(
    "--sine",
    "sine",
    type=(float, float, float),
    default=(0.0, 0.0, 0.0),
    show_default=True,
    metavar="OA PA IA",
)
@_tolerance("--sine-freq", type=float, default=30.0, show_default=True)
@_tolerance("--rms", type=float, default=None)
@_tolerance("--psd", "psd_file")
@_tolerance(
    "--unit", type=click.Choice(["none", "aks05", "al1m"]), default="none", show_default=True
)
@_tolerance("--json", "json_out")
@_tolerance("--force", is_flag=True)
def tolerance(budget, mean_accel, sine, sine_freq, rms, psd_file, unit, json_out, force):
    import jax

    # Limits are ratios of O(1e-4 g) budgets to exact sensitivities: float64 for ppm.
    jax.config.update("jax_enable_x64", True)
    from . import StaticTransferFunction
    from .report.text.tolerance import implausible_option, tolerance_json, tolerance_lines
    from .vibration import (
        ToleranceScenario,
        VibrationEnvironment,
        read_band_spectrum,
        tolerance_table,
    )

    check_outputs(((json_out, "--json"),), force)
    if rms is not None and psd_file is not None:
        raise click.UsageError("give the random vibration by --rms or by --psd, not both.")
    implausible = implausible_option(budget, mean_accel, sine, sine_freq, rms)
    if implausible is not None:
        raise click.BadParameter(implausible[1], param_hint=implausible[0])
    source, sigma = "none given", 0.0
    if psd_file is not None:
        with _refused():
            spectrum = read_band_spectrum(psd_file)
        sigma = float(spectrum.rms(paper=True))
        source = f"{psd_file}: {len(spectrum.psd)} bands, paper's σ formula"
    elif rms is not None:
        sigma, source = rms, "--rms"
    if sigma == 0 and not any(sine):
        raise click.UsageError(
            "no vibration given (every limit would be unbounded): give --sine amplitudes, "
            "--rms or --psd."
        )
    with _refused(ValueError):
        env = VibrationEnvironment(
            sine_amplitude=sine, sine_frequency=sine_freq, random_std=sigma, random_correlation=1.0
        )
        scenario = ToleranceScenario(budget, mean_accel, env, [0.0], [mean_accel])
    passport = {"aks05": StaticTransferFunction.aks05, "al1m": StaticTransferFunction.al1m}
    table = tolerance_table(scenario, passport[unit]() if unit != "none" else None)
    shown = dict(budget=budget, mean_accel=mean_accel, sine=sine, sine_freq=sine_freq)
    shown.update(sigma=sigma, source=source, unit=unit, table=table)
    click.echo("\n".join(tolerance_lines(**shown)))
    write(json_out, tolerance_json(**shown), "json")


@main.command(help=COMMANDS["identify"])
@click.argument("files", nargs=-1, required=True, type=FILE)
@_identify("--params", "params_file")
@_identify(
    "--method",
    type=click.Choice(["auto", "oscillatory", "aperiodic"]),
    default="auto",
    show_default=True,
)
@_identify("--gamma", default="exact", show_default=True)
@outputs("identify")
def identify(files, params_file, method, gamma, json_out, plot_out, out_dir, force, device):
    paths = _start("identify", out_dir, force, device, json_out, plot_out)
    from . import identify_step_record, identify_step_records, read_csv
    from .report import identification_figure, identification_summary, save_figure_atomic
    from .report.text.identify import identify_set_lines, identify_set_records

    try:
        gamma_value = gamma if gamma in ("exact", "paper") else float(gamma)
    except ValueError:
        raise click.BadParameter(
            f"{gamma!r} is not 'exact', 'paper' or a number.", param_hint="--gamma"
        ) from None
    if len(set(files)) != len(files):
        raise click.ClickException("a file is named twice; give each record once.")
    if len(files) > 1:
        with _refused():
            params = _nominal(params_file).params
            datasets = [read_csv(file, kind="step") for file in files]
            results = identify_step_records(datasets, params, method=method, gamma=gamma_value)
        text = "\n".join(identify_set_lines(files, results))
        doc = {"records": identify_set_records(files, results)}
        figure = None
    else:
        with _refused():
            data = read_csv(files[0], kind="step")
            params = _nominal(params_file).params
            result = identify_step_record(data, params, method=method, gamma=gamma_value)
        text = identification_summary(result)
        # The traces (the record and the model, sample by sample) stay out of the JSON.
        doc = {"source": str(files[0]), **result.to_dict()}
        figure = lambda: identification_figure(result, title=str(files[0]))  # noqa: E731
    click.echo(text)
    write(paths["text"], text, "summary")
    write(paths["json_out"], json_writer(lambda: doc), "json")
    if figure is None and paths["plot_out"] is not None:
        click.echo("note: --plot draws one record; with several files it is not drawn")
    elif figure is not None:
        write(paths["plot_out"], lambda path: save_figure_atomic(figure(), path), "plot")


@main.command(help=COMMANDS["diagnose"])
@click.argument("files", nargs=-1, required=True, type=FILE)
@_diagnose("--kind", type=click.Choice(["step", "vibration", "noise"]), default=None)
@_diagnose("--params", "params_file")
@_diagnose("--input-delay", "input_delay", type=float, default=None)
@_diagnose("--discover/--no-discover", "discover", default=True)
@_diagnose("--ceiling", "ceiling", is_flag=True, default=False)
@outputs("diagnose", out="diagnosis")
def diagnose(
    files, kind, params_file, input_delay, discover, ceiling, json_out, plot_out, out_dir,
    force, device,
):
    paths = _start("diagnosis", out_dir, force, device, json_out, plot_out)
    from . import read_csv, with_input_delay
    from .diagnose import SetDiagnosis, diagnose_step_set
    from .diagnose import diagnose as run_diagnosis
    from .report.figures.diagnosis import save_plot, set_figure
    from .report import save_figure_atomic
    from .report.text.diagnose import diagnose_notes

    if ceiling and not discover:
        raise click.ClickException("--ceiling is part of a discovery; drop --no-discover.")
    if len(files) > 1 and kind not in (None, "step"):
        raise click.ClickException(
            f"several files are diagnosed together only as step records of one device; "
            f"--kind {kind} takes one file."
        )
    if len(set(files)) != len(files):
        raise click.ClickException("a file is named twice; give each record once.")
    with _refused():
        if len(files) > 1:
            datasets = [with_input_delay(read_csv(f), input_delay, path=f) for f in files]
            sources = {"sources": [str(f) for f in files]}
            result = diagnose_step_set(datasets, _nominal(params_file), names=sources["sources"])
            kind_read = "step"
        else:
            data = with_input_delay(read_csv(files[0], kind=kind), input_delay, path=files[0])
            result = run_diagnosis(
                data, _nominal(params_file), discover=discover, ceiling=ceiling
            )
            sources, kind_read = {"source": str(files[0])}, data.kind
    click.echo(result.summary())
    write(paths["text"], result.summary(), "summary")
    for line in diagnose_notes(len(files), kind_read, discover, params_file is not None):
        click.echo(line)
    write(paths["json_out"], json_writer(lambda: {**sources, **result.to_dict()}), "json")
    if isinstance(result, SetDiagnosis):  # several files
        write(paths["plot_out"], lambda path: save_figure_atomic(set_figure(result), path), "plot")
    else:
        write(paths["plot_out"], lambda path: save_plot(result, path), "plot")


# The --export formats, and the file each is written to under --out DIR (noise_<file>).
_EXPORTS = {"kalibr": "imu.yaml", "gnss-ins-sim": "gnss_ins_sim.json", "ieee": "ieee.json"}


@main.command(help=COMMANDS["noise"])
@click.argument("file", type=FILE)
@outputs(
    "noise",
    _noise("--export", "export_format", type=click.Choice(list(_EXPORTS)), default=None),
    _noise("--confidence", type=click.FloatRange(0.5, 0.999), default=0.95, show_default=True),
)
def noise(file: Path, json_out, plot_out, export_format, confidence, out_dir, force, device):
    export_out = None
    if out_dir is not None and export_format is not None:
        export_out = out_dir / f"noise_{_EXPORTS[export_format]}"
    paths = _start("noise", out_dir, force, device, json_out, plot_out, (export_out, "--out"))
    from . import read_csv
    from .noise import analyse_static_record, analysis_to_json
    from .report.figures.noise import plot_analysis
    from .report.text.noise import ExportRefused, export_text, noise_lines

    with _refused(ValueError):
        data = read_csv(file, kind="noise")
        result = analyse_static_record(
            data.a_out, data.sample_period, unit="g", confidence=confidence
        )
    printed = noise_lines(data.a_out.size, data.sample_period, result)
    click.echo("\n".join(printed))
    if export_format is not None:
        with _refused(ExportRefused):
            notes, exported = export_text(result, export_format)
        for line in notes if export_out is not None else [*notes, exported]:
            click.echo(line)
            printed.append(line)
        write(export_out, exported, f"{export_format} export")
    write(paths["text"], "\n".join(printed), "summary")
    doc = lambda: {"source": str(file), **analysis_to_json(result)}  # noqa: E731
    write(paths["json_out"], json_writer(doc), "json")
    plot = lambda path: plot_analysis(result, path, title=str(file))  # noqa: E731
    write(paths["plot_out"], plot, "plot")


def run() -> None:
    """The `accel-jax` command (the console script, `python -m accel_jax.cli`): `main`, and
    where it ends while work it started on other threads still runs — an interrupted
    (Ctrl-C) or failed command during a diagnosis, with programs being compiled ahead for
    its later stages — the process exits at once with the command's status instead of
    waiting for that work (XLA cannot cancel a compilation: on the 2-core CPU a lag tie
    interrupted mid-way took 7–11 s to exit). Outputs are written whole or not at all
    before this point (`_io.write_json_atomic`), so nothing is cut short."""
    from ._runtime import background_running

    try:
        main()
    except SystemExit as done:
        if not background_running():
            raise
        code = done.code
        if not isinstance(code, int):
            if code is not None:
                print(code, file=sys.stderr)
            code = 0 if code is None else 1
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)


if __name__ == "__main__":  # pragma: no cover
    run()
