"""What every study script shares: its command line, float64 for the run, the quick run's
compile options, a run cached and guarded exactly as `accel-jax report` does it, and
figures saved whole with their captions.

A study is a script `studies/<name>.py` with

    @study_run(compile_bound_when_quick=True)   # or False
    def run(out_dir, *, quick=False, ...) -> dict: ...

    if __name__ == "__main__":
        study_main(run, __file__, __doc__)

`study_run` makes `run` compute in float64 and restore the caller's setting afterwards
(the report's process and a user's notebook keep theirs). `study_main` is the command line
a user runs (`python studies/<name>.py [--quick] [--out DIR] [--force]`): it writes the
same folder, marker and cache key as `accel-jax report`, so a report run afterwards reuses
the result, and an existing folder of another run is never replaced unasked.
"""

from __future__ import annotations

import argparse
import functools
import os
import sys
from collections.abc import Callable
from pathlib import Path


def study_run(*, compile_bound_when_quick: bool = False):
    """Decorate a study's `run(out_dir, *, quick=False, **options)`: it computes in float64
    (`jax.enable_x64`, the caller's setting restored on return) and, when
    `compile_bound_when_quick` and `quick`, compiles inside `_runtime.fast_compile`
    (for studies whose quick run is compile-bound throughout; results equal to round-off)."""

    def decorate(run):
        @functools.wraps(run)
        def wrapper(out_dir, *, quick: bool = False, **options):
            import jax

            from .._runtime import fast_compile

            with jax.enable_x64(True), fast_compile(compile_bound_when_quick and quick):
                return run(out_dir, quick=quick, **options)

        return wrapper

    return decorate


class Figures:
    """A study's figures, in the order the report shows them: each saved whole as a PNG
    beside `result.json` (tight layout unless the figure has its own layout engine, closed
    after) with its caption.

        figures = Figures(out_dir)
        figures.save(fig, "sweep.png", "δK_a versus ξ (…)")
        result["figures"] = figures.entries
    """

    def __init__(self, out_dir):
        self.out_dir = Path(out_dir)
        self.entries: list[dict] = []

    def save(self, figure, file: str, caption: str) -> dict:
        import matplotlib.pyplot as plt

        from .._io import save_figure_atomic

        if figure.get_layout_engine() is None:
            # A figure made with its own layout (constrained: the identification figure)
            # keeps it; tight_layout would replace it, with a warning on the terminal.
            figure.tight_layout()
        save_figure_atomic(figure, self.out_dir / file)
        plt.close(figure)
        entry = {"file": file, "caption": caption}
        self.entries.append(entry)
        return entry


def _default_summary(result: dict) -> None:
    for row in result.get("summary", []):
        if not isinstance(row, dict) or "quantity" not in row:
            continue
        ours = row.get("ours")
        if isinstance(ours, float):
            ours = f"{ours:.6g}"
        paper = row.get("paper", row.get("note"))
        print(f"{row['quantity']}: {ours}" + (f" (paper {paper})" if paper is not None else ""))


def study_main(
    run: Callable[..., dict],
    study_file: str | os.PathLike,
    doc: str | None,
    *,
    argv=None,
    add_arguments: Callable[[argparse.ArgumentParser], None] | None = None,
    options: Callable[[argparse.Namespace], tuple[dict, dict]] | None = None,
    summary: Callable[[dict], None] | None = None,
) -> int:
    """The command line of the study script `study_file` (its `__file__`).

    Options: `--out DIR` (default `out/<study>`), `--quick`, `--force` (replace a folder
    holding another run), plus the study's own (`add_arguments`). `options(args)` returns
    `(run_kwargs, key_options)`: keyword arguments for `run` and the values that make a run
    different from the report's default one (they enter the cache key; empty for the
    report's own settings); it raises `ValueError` for a bad value. Prints the summary
    (`summary(result)` or each summary row); a bad option or folder is one line on stderr
    and exit status 2; a study that raises is one line on stderr (its traceback in
    `OUT/error.log`) and exit status 1.
    """
    from .._placement import DEVICE_CHOICES, DeviceError, apply_device
    from .._cache import enable_compilation_cache
    from .._runtime import apply_fast_compile, quiet_xla_logs
    from ._run import ERROR_LOG, ReportError, _record_failure, cache_key, one_line, run_study

    script = Path(study_file).resolve()
    name = script.stem
    parser = argparse.ArgumentParser(
        prog=f"python {script.parent.name}/{script.name}",
        description=(doc or name).strip().splitlines()[0],
    )
    parser.add_argument("--out", type=Path, default=Path("out") / name, help="output folder")
    parser.add_argument("--quick", action="store_true", help="small sizes (as report --quick)")
    parser.add_argument(
        "--force", action="store_true", help="replace a folder that holds another run"
    )
    parser.add_argument(
        "--device",
        choices=DEVICE_CHOICES,
        default=None,
        help="where the work runs (default $ACCEL_JAX_DEVICE, else auto: latency-bound "
        "work on the CPU, Monte Carlo sweeps on a GPU where one is present)",
    )
    if add_arguments is not None:
        add_arguments(parser)
    args = parser.parse_args(argv)
    quiet_xla_logs()
    if args.quick:
        apply_fast_compile()  # as `accel-jax report --quick` (before JAX starts)
    enable_compilation_cache()  # $ACCEL_JAX_CACHE_DIR decides, as for the report
    try:
        apply_device(args.device, latency_bound=False)  # as the report places a study
    except DeviceError as error:
        print(f"{parser.prog}: {error}", file=sys.stderr)
        return 2
    import jax

    # As `accel-jax report`: the process runs in float64 (the key records it), so a study
    # run here and one run by the report are the same run.
    jax.config.update("jax_enable_x64", True)
    try:
        run_kwargs, key_options = options(args) if options is not None else ({}, {})
    except ValueError as error:  # a bad option value: one line, as argparse's own errors
        print(f"{parser.prog}: error: {error}", file=sys.stderr)
        return 2
    key = cache_key(name, script, {"quick": bool(args.quick), **key_options})
    try:
        result, cached = run_study(
            name, run, Path(args.out), key, quick=args.quick, force=args.force, **run_kwargs
        )
    except ReportError as error:
        print(f"{parser.prog}: {error}", file=sys.stderr)
        return 2
    except Exception as error:  # the study raised: one line, its traceback in a log file
        import traceback

        reason, where = one_line(error), ""
        try:  # marked failed as the report marks it, with the traceback beside it
            _record_failure(Path(args.out), key, reason, traceback.format_exc())
            where = f" (log: {Path(args.out) / ERROR_LOG})"
        except OSError:
            pass
        print(f"{parser.prog}: the study failed: {reason}{where}", file=sys.stderr)
        return 1
    if cached:
        print(f"{args.out} is up to date (same options and code; --force recomputes)")
    (summary or _default_summary)(result)
    print(f"written: {Path(args.out) / 'result.json'}")
    return 0
