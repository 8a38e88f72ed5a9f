"""The `identify` result as System Identification Toolbox users read it: the text.

Takes the `StepIdentification` of `identify_step_record` and returns the printed summary:
the graph method's estimate, the fit's parameter table against the nominal device, the fit
percentage and NRMSE as MATLAB's `compare` and `goodnessOfFit` define them, the residual
whiteness test, and why the two methods' ξ may differ. Its figure is
`accel_jax.report.figures.identification`.
"""

from __future__ import annotations

import math

from ..._identify.step_result import AperiodicEstimate, LeastSquaresFit, StepIdentification

SIGNIFICANT = 4
"""Significant figures of a printed value; a standard deviation gets `SIGMA_SIGNIFICANT`."""

SIGMA_SIGNIFICANT = 2

MISSING = "—"
"""A table cell for a value that does not exist (no nominal value, no σ)."""

# SI prefixes a printed time or voltage may take, largest first.
_PREFIXES = (("", 1.0), ("m", 1e-3), ("µ", 1e-6), ("n", 1e-9))
_SCALED_UNITS = ("s", "V")


def number(value, significant: int = SIGNIFICANT) -> str:
    """`value` to `significant` figures: fixed notation from 1e-4 to 1e6 (``207.8`` → ``210``
    to two figures), scientific elsewhere without padding (``1.2e-5``, not ``1.2e-05``);
    trailing zeros dropped; ``—`` for None or NaN.

    >>> number(0.5196352600751051), number(207.8, 2), number(1.2e-05, 2), number(None)
    ('0.5196', '210', '1.2e-5', '—')
    """
    if value is None or math.isnan(float(value)):
        return MISSING
    value = float(value)
    if math.isinf(value):
        return "∞" if value > 0 else "-∞"
    if value == 0:
        return "0"
    exponent = math.floor(math.log10(abs(value)))
    if -4 <= exponent < 6:
        decimals = significant - 1 - exponent
        text = f"{round(value, decimals):.{max(decimals, 0)}f}"
        return text.rstrip("0").rstrip(".") if "." in text else text
    mantissa, power = f"{value:.{significant - 1}e}".split("e")
    if "." in mantissa:
        mantissa = mantissa.rstrip("0").rstrip(".")
    return f"{mantissa}e{int(power)}"


def quantity(value, unit: str, significant: int = SIGNIFICANT) -> str:
    """`value` [unit] with an SI prefix for times and voltages so the number reads between
    1 and 1000 (``290.1 µs``, ``3.5 ns``, ``162.3 mV``); ``—`` for None or NaN; a
    dimensionless value (unit ``"1"``) bare.

    >>> quantity(2.9009559e-4, "s"), quantity(0.1623, "V"), quantity(0.134, "V/(m/s²)")
    ('290.1 µs', '162.3 mV', '0.134 V/(m/s²)')
    """
    if value is None or math.isnan(float(value)):
        return MISSING
    value = float(value)
    if unit == "1":
        return number(value, significant)
    if unit in _SCALED_UNITS and value != 0 and math.isfinite(value):
        for prefix, factor in _PREFIXES:
            if abs(value) >= factor * (1 - 0.5 * 10.0 ** (1 - significant)):
                return f"{number(value / factor, significant)} {prefix}{unit}"
        return f"{number(value / 1e-9, significant)} n{unit}"
    return f"{number(value, significant)} {unit}"


def _shift(value) -> str:
    """A shift in standard deviations: ``+0.28σ``, ``-1250σ``; ``—`` where there is none."""
    if value is None or not math.isfinite(value):
        return MISSING
    magnitude = abs(value)
    if magnitude < 10:
        text = number(magnitude, 2)
    elif magnitude < 1e6:
        text = f"{magnitude:.0f}"
    else:  # the digits are meaningless there, the order of magnitude is not
        text = number(magnitude, 1)
    return f"{'-' if value < 0 else '+'}{text}σ"


def _table(header: list[str], rows: list[list[str]], align: str) -> list[str]:
    """Lines of a plain-text table, columns two spaces apart ('l'/'r' per column)."""
    widths = [max(len(row[j]) for row in [header, *rows]) for j in range(len(header))]

    def line(cells):
        parts = [
            cell.rjust(width) if side == "r" else cell.ljust(width)
            for cell, width, side in zip(cells, widths, align, strict=True)
        ]
        return "  ".join(parts).rstrip()

    return [line(header)] + [line(row) for row in rows]


def parameter_table(result: StepIdentification) -> list[str]:
    """The fit's parameter table, one line each: parameter · nominal · estimate · ±σ ·
    shift (estimate − nominal)/σ · what it is. Times and voltages in their natural unit.
    Empty when the fit failed."""
    fit = result.fit
    if not isinstance(fit, LeastSquaresFit):
        return []
    rows = [
        [
            row.name,
            quantity(row.nominal, row.unit),
            quantity(row.estimate, row.unit),
            quantity(row.std, row.unit, SIGMA_SIGNIFICANT),
            _shift(row.shift_in_std),
            row.description,
        ]
        for row in fit.parameters
    ]
    header = ["parameter", "nominal", "estimate", "±σ", "shift", ""]
    return _table(header, rows, "lrrrrl")


def quality_lines(result: StepIdentification) -> list[str]:
    """The fit percentage and NRMSE (MATLAB's definitions), the residual's rms against the
    noise σ, and the whiteness line. Empty when the fit failed."""
    if not isinstance(result.fit, LeastSquaresFit):
        return []
    quality = result.fit.quality
    return [
        f"fit {quality.fit_percent:.2f} % (MATLAB compare: 100 (1 − ‖y − ŷ‖/‖y − ȳ‖)), "
        f"NRMSE {number(quality.nrmse, 3)}",
        f"residual rms {quantity(quality.residual_rms_V, 'V', 3)}, noise σ "
        f"{quantity(quality.noise_std_V, 'V', 3)} (successive differences of the settled "
        "tail)",
        whiteness_line(result),
    ]


def whiteness_line(result: StepIdentification) -> str:
    """``residual whiteness: Ljung-Box Q = 21.1 over 20 lags, p = 0.39: white``; empty when
    the fit failed."""
    if not isinstance(result.fit, LeastSquaresFit):
        return ""
    test = result.fit.quality.whiteness
    verdict = "white" if test.white else f"not white at {100 * test.level:g} %"
    return (
        f"residual whiteness: Ljung-Box Q = {number(test.statistic, 3)} over "
        f"{test.lags} lags, {_p_value(test.p_value)}: {verdict}"
    )


def _p_value(p: float) -> str:
    """``p = 0.39``, ``p < 1e-16`` (below the χ² tail's resolution in float64)."""
    return "p < 1e-16" if p < 1e-16 else f"p = {number(p, 2)}"


def damping_note(result: StepIdentification) -> str | None:
    """One line when the graph method's ξ lies more than 2σ (the fit's σ of ξ) from the
    fit's ξ: why the two can differ, and by how many σ; None otherwise."""
    graph, fit = result.graph, result.fit
    if not isinstance(fit, LeastSquaresFit):
        return None
    sigma = fit.damping_ratio_std
    difference = graph.damping_ratio - fit.damping_ratio
    if not (math.isfinite(sigma) and sigma > 0) or abs(difference) <= 2 * sigma:
        return None
    if graph.method.startswith("oscillatory"):
        how = (
            "the graph method reads ξ from the first two extrema A1, A2 of an idealised "
            "second-order response (Mironov, Fominov & Maletin, eq. (9)), so the torquer "
            "and filter lags, the "
            "noise at the extrema and the sampling bias it"
        )
    else:
        how = (
            "the graph method reads ξ = T1/(2 T2) from the tangent at the steepest slope of "
            "an idealised second-order response (Mironov, Fominov & Maletin, eqs. "
            "(13)-(15)), with the lags "
            "only shifted out of the inflection time by eq. (16), so the lags and the noise in "
            "the slope bias it"
        )
    return (
        f"note: graph ξ = {number(graph.damping_ratio)} and fit ξ = "
        f"{number(fit.damping_ratio)} ± {number(sigma, SIGMA_SIGNIFICANT)} differ by "
        f"{_shift(difference / sigma)} (the fit's σ): {how}; the fit uses the whole record "
        "with the lags in its model."
    )


TIME_SCALE_FACTOR = 3.0
"""An identified T this factor or more from the nominal device's is noted (the diagnosis's
domain check uses the same factor on the rise time)."""


def time_scale_note(identified_s: float, nominal_s: float) -> str | None:
    """A note where the graph method's T lies `TIME_SCALE_FACTOR` or more from the nominal
    device's: K̂_a and δK_a then describe another device, or a record whose time is not in
    seconds (in ms: T × 1000). None otherwise."""
    if not (identified_s > 0 and nominal_s > 0):
        return None
    ratio = identified_s / nominal_s
    if 1 / TIME_SCALE_FACTOR < ratio < TIME_SCALE_FACTOR:
        return None
    return (
        f"note: T = {quantity(identified_s, 's')} is {ratio:.3g}× the nominal device's "
        f"{quantity(nominal_s, 's')}: δK_a compares two different devices. Give the device's "
        "values with --params, and check that the time column is in seconds."
    )


def identification_summary(result: StepIdentification) -> str:
    """The printed result of `accel-jax identify`: segment, nominal K_a, the graph method's
    estimate and what it read off the record, the fit's parameter table, δK_a, the fit's
    quality and whiteness, and the ξ note when the methods disagree."""
    seg, graph, fit = result.segment, result.graph, result.fit
    sign = "+" if seg.test_step_V > 0 else ""
    lines = [
        f"step of {sign}{number(seg.test_step_V)} V at t = {quantity(seg.step_time_s, 's')}, "
        f"{seg.samples} samples at {number(seg.sample_rate_Hz)} Hz",
        f"nominal K_a = {quantity(result.nominal.scale_factor, 'V/(m/s²)')}",
        f"{graph.method}:",
        f"  T = {quantity(graph.time_constant_s, 's')}, ξ = {number(graph.damping_ratio)}, "
        f"K̂_a = {quantity(graph.scale_factor, 'V/(m/s²)')}, "
        f"δK_a = {graph.dKa_percent:+.4f} %",
    ]
    if isinstance(graph, AperiodicEstimate):
        times = (graph.T1_s, graph.T2_s, graph.T3_s, graph.T4_s)
        lines.append(
            f"  read off: U_ss = {quantity(graph.steady_state_V, 'V')}, inflection at "
            f"{quantity(graph.inflection_time_s, 's')}, T1..T4 = "
            + ", ".join(quantity(value, "s") for value in times)
        )
    else:
        lines.append(
            f"  read off: U_ss = {quantity(graph.steady_state_V, 'V')}, crossings "
            f"t1 = {quantity(graph.crossing_t1_s, 's')}, "
            f"t2 = {quantity(graph.crossing_t2_s, 's')}, "
            f"A1 = {quantity(graph.overshoot_A1_V, 'V')}, "
            f"A2 = {quantity(graph.undershoot_A2_V, 'V')}"
        )
    scale = time_scale_note(graph.time_constant_s, result.nominal.time_constant_s)
    if scale is not None:
        lines.append(scale)
    if not isinstance(fit, LeastSquaresFit):
        lines.append(f"least-squares fit failed: {fit.reason}")
        return "\n".join(lines)
    lines.append(f"{fit.method}:")
    lines += ["  " + line for line in parameter_table(result)]
    lines.append(f"  δK_a = {fit.dKa_percent:+.4f} ± {fit.dKa_std_percent:.4f} %")
    lines += ["  " + line for line in quality_lines(result)]
    note = damping_note(result)
    if note is not None:
        lines.append(note)
    return "\n".join(lines)
