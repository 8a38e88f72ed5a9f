"""The `accel-jax` command: a thin layer that parses, calls the library and prints."""

from __future__ import annotations

import sys
from pathlib import Path

import click

STUDIES = ("scale_factor_identification",)


def _studies_dir() -> Path:
    # Studies are scripts in the repository's studies/ folder, next to the package.
    return Path(__file__).resolve().parent.parent / "studies"


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="accel_jax")
def main():
    """accel-jax: servo (pendulum compensating) accelerometer design studies.

    Run `accel-jax report` for the full design-study report, or `accel-jax info` for the
    closed-form characteristics of the reference device.
    """


@main.command()
@click.option(
    "--out",
    "out_dir",
    type=click.Path(file_okay=False, path_type=Path),
    default=Path("out/report"),
    show_default=True,
    help="Folder for index.html; each study writes its own folder beside it.",
)
@click.option("--quick", is_flag=True, help="Smaller sweeps (a smoke run, minutes not tens).")
@click.option(
    "--force",
    is_flag=True,
    help="Replace earlier results in the output folders (by default finished studies are "
    "reused and folders from a different run are left alone).",
)
@click.option("--no-progress", is_flag=True, help="No progress bars (e.g. in logs).")
def report(out_dir: Path, quick: bool, force: bool, no_progress: bool):
    """Run every study and write a self-contained HTML report (OUT/index.html).

    Interrupted runs resume: a study that finished with the same options and code is not
    redone. Nothing is deleted unless --force.
    """
    import jax

    # Studies measure effects below float32 resolution (δK_a at 0.1 %): run them in float64.
    jax.config.update("jax_enable_x64", True)
    from .report._run import ReportError, run_report

    try:
        index = run_report(
            out_dir,
            studies=STUDIES,
            studies_dir=_studies_dir(),
            quick=quick,
            force=force,
            progress=not no_progress,
            echo=click.echo,
        )
    except ReportError as error:
        raise click.ClickException(str(error)) from error
    except ValueError as error:
        raise click.ClickException(f"a study rejected its input: {error}") from error
    except KeyboardInterrupt:
        click.echo(
            "\ninterrupted: finished studies are kept; run the same command again to resume.",
            err=True,
        )
        sys.exit(130)
    click.echo(f"report written: {index}")


@main.command()
def info():
    """Print the closed-form characteristics of the SPEC.md reference device."""
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


@main.command()
@click.argument("file", type=click.Path(dir_okay=False, path_type=Path))
@click.option(
    "--kind",
    type=click.Choice(["step", "vibration", "noise"]),
    default=None,
    help="Force the kind of record (default: inferred from the CSV columns).",
)
@click.option(
    "--params",
    "params_file",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Nominal device (TOML: ServoParams fields, value or {value, uncertainty}); "
    "default the SPEC.md reference device with J, μ, c, k_dm known to ±5 %.",
)
@click.option(
    "--json",
    "json_out",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Write the diagnosis as JSON here.",
)
@click.option(
    "--plot",
    "plot_out",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Draw measured vs simulated, residuals, spectrum and ranking (PNG) here.",
)
def diagnose(file: Path, kind, params_file, json_out, plot_out):
    """Diagnose the sim-to-real gap of one experiment (CSV, SI units, header row)."""
    import jax

    # Evidence compares log-likelihoods of ~1e4 to within ~1: float64.
    jax.config.update("jax_enable_x64", True)
    from ._data import DataError, NominalDevice, read_csv, read_params_toml
    from .diagnose import diagnose as run_diagnosis
    from .diagnose.report import save_plot, write_json

    try:
        data = read_csv(file, kind=kind)
        nominal = read_params_toml(params_file) if params_file else NominalDevice.reference()
        result = run_diagnosis(data, nominal)
    except DataError as error:
        raise click.ClickException(str(error)) from None
    click.echo(result.summary())
    if json_out is not None:
        write_json(result, json_out, source=file)
        click.echo(f"json written: {json_out}")
    if plot_out is not None:
        save_plot(result, plot_out)
        click.echo(f"plot written: {plot_out}")


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
