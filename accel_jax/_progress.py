"""Progress bars for long work, off unless the caller asks (the CLI does).

Library code reports progress through `bar`; nothing is printed unless a caller has
entered `show_progress()`, so tests and user scripts stay quiet, and nothing unless stderr
is a terminal: a redirected stderr (a log file, CI) gets no cursor codes. Bars come from
tqdm (written to stderr, with rate and estimated time left).
"""

from __future__ import annotations

import contextlib
import contextvars
import sys
from collections.abc import Iterator

from tqdm.auto import tqdm

_ENABLED = contextvars.ContextVar("accel_jax_progress", default=False)
_LABEL = contextvars.ContextVar("accel_jax_progress_label", default="")
_POSITION: contextvars.ContextVar[int | None] = contextvars.ContextVar(
    "accel_jax_progress_position", default=None
)


@contextlib.contextmanager
def show_progress(
    enabled: bool = True, label: str = "", position: int | None = None
) -> Iterator[None]:
    """Within this block, sweeps and studies draw progress bars on stderr.

    **Arguments:**

    - `enabled`: draw bars (default) or silence them inside an enabled block.
    - `label`: a prefix for the bars' descriptions (e.g. the study's name).
    - `position`: the terminal line of the bars (tqdm's `position`), for processes that
        draw bars side by side (the report's parallel studies); `None` lets tqdm choose.
    """
    tokens = (_ENABLED.set(enabled), _LABEL.set(label), _POSITION.set(position))
    try:
        yield
    finally:
        _POSITION.reset(tokens[2])
        _LABEL.reset(tokens[1])
        _ENABLED.reset(tokens[0])


def progress_enabled() -> bool:
    """Whether the caller asked for progress bars (see `show_progress`)."""
    return _ENABLED.get()


def on_terminal(stream=None) -> bool:
    """Whether `stream` (default: the current stderr) is a terminal: bars are drawn only
    there (their carriage returns and cursor moves garble a log file)."""
    stream = sys.stderr if stream is None else stream
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # no isatty, or a closed stream
        return False


def bar(total: int, desc: str, unit: str = "it"):
    """A tqdm bar when progress is enabled and stderr is a terminal, else a silent one with
    the same methods."""
    label = _LABEL.get()
    stream = sys.stderr
    return tqdm(
        total=total,
        desc=f"{label}: {desc}" if label else desc,
        unit=unit,
        file=stream,
        disable=not (progress_enabled() and on_terminal(stream)),
        leave=False,
        dynamic_ncols=True,
        position=_POSITION.get(),
    )
