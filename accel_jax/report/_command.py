"""What the `accel-jax` commands share on their command line, as `_study` is for the study
scripts: options whose help is `text.help`'s, the output options of a command that reads
records (--json, --plot, --out, --force, --device), where each output goes (`route`), the
refusal to replace a file unasked (`writable`), and each file written atomically and said
(`write`; a JSON document with its provenance block: `json_writer`)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import click

from .._io import _atomic_write_bytes, provenance, write_json_atomic
from .text.help import OPTIONS, device_help, out_help

FILE = click.Path(dir_okay=False, path_type=Path)
"""The click type of an argument or option naming a file (not a folder)."""


def option(command: str, *decls: str, **kwargs):
    """A click option of `command`, its help `text.help.OPTIONS[command][first flag]`; a
    flag and a destination alone (`option(command, "--json", "json_out")`) name a file,
    default none."""
    if len(decls) == 2 and not kwargs:
        kwargs = {"type": FILE, "default": None}
    return click.option(*decls, help=OPTIONS[command][decls[0]], **kwargs)


def device_option(latency_bound: bool):
    """`--device auto|cpu|gpu` (default `$ACCEL_JAX_DEVICE`, else auto)."""
    return click.option(
        "--device",
        type=click.Choice(["auto", "cpu", "gpu"]),
        default="auto",
        envvar="ACCEL_JAX_DEVICE",
        show_default=True,
        help=device_help(latency_bound),
    )


def outputs(command: str, *between, out: str | None = None):
    """The output options of a command that reads records, in this order: --json, --plot,
    the options `between`, --out (DIR/`out`.json, .png and .txt; `out` defaults to
    `command`), --force and --device."""
    options = (
        option(command, "--json", "json_out"),
        option(command, "--plot", "plot_out"),
        *between,
        click.option(
            "--out",
            "out_dir",
            type=click.Path(file_okay=False, dir_okay=True, path_type=Path),
            default=None,
            help=out_help(out or command),
        ),
        option(command, "--force", is_flag=True),
        device_option(latency_bound=True),
    )

    def decorate(function):
        for each in reversed(options):
            function = each(function)
        return function

    return decorate


def route(out_dir: Path | None, command: str, **paths) -> dict:
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


def writable(path: Path | None, force: bool, option: str) -> None:
    """Refuse, before any work, an output path that cannot be written: an existing file
    unless --force (no user file is lost), a folder, or a path below a file."""
    if path is None:
        return
    if path.is_dir():
        raise click.ClickException(f"{option} {path} is a folder; give a file's path.")
    for parent in path.parents:
        if parent.exists():
            if not parent.is_dir():
                raise click.ClickException(
                    f"{option} {path}: {parent} is a file, so nothing can be written below it."
                )
            break
    if path.exists() and not force:
        raise click.ClickException(
            f"{option} {path} already exists; pass --force to replace it, or choose another path."
        )


FIGURE_FORMATS = (".png", ".pdf", ".svg")
"""The figure files --plot writes, by suffix (`save_figure_atomic` saves in that format)."""


def check_outputs(paths, force: bool) -> None:
    """Refuse, before any work, each path `writable` refuses, two outputs of one command
    given the same path (the second would replace the first) and a --plot whose suffix is
    not a figure format (`FIGURE_FORMATS`). `paths`: (path or None, option) pairs."""
    seen: dict = {}
    for path, option in paths:
        if path is None:
            continue
        key = path.resolve()
        if key in seen:
            raise click.ClickException(
                f"{seen[key]} and {option} are the same file, {path}; give each its own path."
            )
        seen[key] = option
        if option == "--plot" and path.suffix.lower() not in FIGURE_FORMATS:
            raise click.ClickException(
                f"--plot {path}: the figure is written as {', '.join(FIGURE_FORMATS)}; end the "
                "path in one of those."
            )
    for path, option in paths:
        writable(path, force, option)


def write(path: Path | None, content, what: str) -> None:
    """Write `content` to `path` atomically and say so ("<what> written: <path>"); nothing
    when `path` is None. `content`: text (a str, ending in one newline), a JSON document (a
    dict) or a function that writes the file (`content(path)`, e.g. a figure's)."""
    if path is None:
        return
    if isinstance(content, str):
        path.parent.mkdir(parents=True, exist_ok=True)
        _atomic_write_bytes(path, (content.rstrip("\n") + "\n").encode())
    elif isinstance(content, dict):
        write_json_atomic(path, content)
    else:
        content(path)
    click.echo(f"{what} written: {path}")


def json_writer(doc: Callable[[], dict]) -> Callable[[Path], object]:
    """For `write`: the JSON document `doc()` (made only when it is written) with the
    provenance block (versions, where the work ran, XLA options in effect and skipped,
    date), as each study's result carries it."""
    return lambda path: write_json_atomic(
        path, {**doc(), "provenance": provenance(precision="float64")}
    )
