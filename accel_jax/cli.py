"""The `accel-jax` command: a thin layer that parses, calls the library and prints."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import click

STUDIES = ("scale_factor_identification",)


def _studies_dir() -> Path:
    # Studies are scripts in the repository's studies/ folder, next to the package.
    return Path(__file__).resolve().parent.parent / "studies"


def _load_study(name: str, folder: Path):
    path = folder / f"{name}.py"
    if not path.exists():
        raise click.ClickException(f"study script not found: {path}")
    spec = importlib.util.spec_from_file_location(f"accel_jax_study_{name}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


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
def report(out_dir: Path, quick: bool):
    """Run every study and write a self-contained HTML report (OUT/index.html)."""
    import jax

    # Studies measure effects below float32 resolution (δK_a at 0.1 %): run them in float64.
    jax.config.update("jax_enable_x64", True)
    from .report._html import build_report

    root = out_dir.parent
    study_dirs = []
    for name in STUDIES:
        module = _load_study(name, _studies_dir())
        study_out = root / name
        click.echo(f"[{name}] running{' (quick)' if quick else ''} ...")
        try:
            module.run(study_out, quick=quick)
        except ValueError as error:
            raise click.ClickException(f"{name}: {error}") from error
        study_dirs.append(study_out)
    index = build_report(study_dirs, out_dir / "index.html", title="accel_jax design-study report")
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


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
