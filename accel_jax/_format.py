"""Numbers as people read them: significant figures, natural time units, intervals.

Every printed number of the command line and the report goes through these, so that a user
reads ``1.3`` and not ``1.2999999999999998``, ``25 µs`` and not ``2.5e-05 s``, and never
``None`` or ``nan`` in a table cell.
"""

from __future__ import annotations

import math

SIGNIFICANT = 4
"""Significant figures of a printed value unless the caller asks for others."""

MISSING = "—"
"""What a table cell shows for a value that does not exist (None, NaN)."""

_TIME_UNITS = (("s", 1.0), ("ms", 1e-3), ("µs", 1e-6), ("ns", 1e-9))


def number(value, significant: int = SIGNIFICANT) -> str:
    """`value` to `significant` figures: fixed notation from 1e-3 to 1e6, else scientific
    (``3.02e-4``); no trailing zeros, no ``e+00``; ``—`` for None or NaN, ``∞`` for inf.

    >>> number(1.2999999999999998), number(0.0302), number(0.000302), number(None)
    ('1.3', '0.0302', '3.02e-4', '—')
    """
    if value is None:
        return MISSING
    value = float(value)
    if math.isnan(value):
        return MISSING
    if math.isinf(value):
        return "∞" if value > 0 else "−∞"
    if value == 0:
        return "0"
    magnitude = abs(value)
    if 1e-3 <= magnitude < 1e6:
        decimals = max(significant - 1 - math.floor(math.log10(magnitude)), 0)
        text = f"{value:.{decimals}f}"
        # Rounding can carry into a new digit (9.9996 → 10.000): re-round to the figures.
        if "." in text:
            text = text.rstrip("0").rstrip(".")
        return text
    mantissa, exponent = f"{value:.{significant - 1}e}".split("e")
    if "." in mantissa:
        mantissa = mantissa.rstrip("0").rstrip(".")
    return f"{mantissa}e{int(exponent)}"


def precise(value) -> str:
    """A value to 10 significant figures, for messages that quote a number back to its
    writer (a time stamp, a cell of their file): ``1.3``, not ``1.2999999999999998``, while
    two nearby time stamps stay distinct."""
    value = float(value)
    if not math.isfinite(value):
        return repr(value)  # nan, inf, -inf: as the file wrote it
    return number(value, 10)


def seconds(value, significant: int = 3) -> str:
    """A time in the natural unit: ``25 µs``, ``1.2 ms``, ``3.4 s`` (``—`` for None/NaN).

    >>> seconds(2.5e-5), seconds(0.0012), seconds(0.0)
    ('25 µs', '1.2 ms', '0 s')
    """
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return MISSING
    value = float(value)
    if value == 0 or math.isinf(value):
        return f"{number(value)} s"
    for unit, factor in _TIME_UNITS:
        if abs(value) >= factor * 0.9995:
            return f"{number(value / factor, significant)} {unit}"
    return f"{number(value / 1e-9, significant)} ns"


def percent(value, significant: int = 3, *, signed: bool = True) -> str:
    """A fraction as a percentage: ``+1.31 %`` (``—`` for None/NaN)."""
    if value is None or math.isnan(float(value)):
        return MISSING
    text = number(100 * float(value), significant)
    if signed and not text.startswith("-") and float(value) != 0:
        text = "+" + text
    return f"{text} %"


def interval(value, low, high, unit: str = "", significant: int = 3) -> str:
    """``1.02e-3 g [0.98e-3, 1.06e-3]``: a value and its interval (omitted when absent)."""
    suffix = f" {unit}" if unit else ""
    text = number(value, significant)
    if low is None or high is None or not (math.isfinite(low) and math.isfinite(high)):
        return text + suffix
    values = [v for v in (value, low, high) if v != 0]
    if any(not 1e-3 <= abs(v) < 1e6 for v in values) and value != 0:
        # One exponent for all three: 1.02e-3 [0.98e-3, 1.06e-3].
        exponent = math.floor(math.log10(abs(value)))
        scale = 10.0**exponent
        text = f"{number(value / scale, significant)}e{exponent}"
        bounds = [f"{number(b / scale, significant)}e{exponent}" for b in (low, high)]
    else:
        bounds = [number(b, significant) for b in (low, high)]
    return f"{text}{suffix} [{bounds[0]}, {bounds[1]}]"


def table(columns: list[str], rows: list[list], align: str | None = None) -> str:
    """A plain-text table with aligned columns: text cells left, numbers right (`align`, one
    character per column, 'l' or 'r', overrides). Numbers are formatted by `number`."""
    cells = [[c if isinstance(c, str) else number(c) for c in row] for row in rows]
    widths = [max([len(columns[j])] + [len(r[j]) for r in cells]) for j in range(len(columns))]
    if align is None:
        align = "".join(
            "r" if rows and not isinstance(rows[0][j], str) else "l" for j in range(len(columns))
        )

    def line(values):
        parts = [
            v.rjust(w) if a == "r" else v.ljust(w)
            for v, w, a in zip(values, widths, align, strict=True)
        ]
        return "  ".join(parts).rstrip()

    return "\n".join([line(columns), line(["-" * w for w in widths])] + [line(r) for r in cells])
