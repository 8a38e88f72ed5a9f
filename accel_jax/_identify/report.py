"""The `identify` result as System Identification Toolbox users read it: text and a figure.

Takes the dict of `identify_step_record` and returns the printed summary (the graph
method's estimate, the fit's parameter table against the nominal device, the fit
percentage and NRMSE as MATLAB's `compare` and `goodnessOfFit` define them, the residual
whiteness test, and why the two methods' ξ may differ) or a matplotlib `Figure` (measured
against the fitted model with the points the graph method read, the residual in its noise
band, the residual autocorrelation). Nothing here writes a file: the CLI saves the figure
(`accel_jax._io.save_figure_atomic`).
"""

from __future__ import annotations

import math

import numpy as np

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


def parameter_table(result: dict) -> list[str]:
    """The fit's parameter table, one line each: parameter · nominal · estimate · ±σ ·
    shift (estimate − nominal)/σ · what it is. Times and voltages in their natural unit.
    Empty when the fit failed."""
    fit = result["fit"]
    if "parameters" not in fit:
        return []
    rows = [
        [
            row["name"],
            quantity(row["nominal"], row["unit"]),
            quantity(row["estimate"], row["unit"]),
            quantity(row["std"], row["unit"], SIGMA_SIGNIFICANT),
            _shift(row["shift_in_std"]),
            row["description"],
        ]
        for row in fit["parameters"]
    ]
    header = ["parameter", "nominal", "estimate", "±σ", "shift", ""]
    return _table(header, rows, "lrrrrl")


def quality_lines(result: dict) -> list[str]:
    """The fit percentage and NRMSE (MATLAB's definitions), the residual's rms against the
    noise σ, and the whiteness line. Empty when the fit failed."""
    quality = result["fit"].get("quality")
    if quality is None:
        return []
    return [
        f"fit {quality['fit_percent']:.2f} % (MATLAB compare: 100 (1 − ‖y − ŷ‖/‖y − ȳ‖)), "
        f"NRMSE {number(quality['nrmse'], 3)}",
        f"residual rms {quantity(quality['residual_rms_V'], 'V', 3)}, noise σ "
        f"{quantity(quality['noise_std_V'], 'V', 3)} (successive differences of the settled "
        "tail)",
        whiteness_line(result),
    ]


def whiteness_line(result: dict) -> str:
    """``residual whiteness: Ljung-Box Q = 21.1 over 20 lags, p = 0.39: white``."""
    test = result["fit"]["quality"]["whiteness"]
    verdict = "white" if test["white"] else f"not white at {100 * test['level']:g} %"
    return (
        f"residual whiteness: Ljung-Box Q = {number(test['statistic'], 3)} over "
        f"{test['lags']} lags, {_p_value(test['p_value'])}: {verdict}"
    )


def _p_value(p: float) -> str:
    """``p = 0.39``, ``p < 1e-16`` (below the χ² tail's resolution in float64)."""
    return "p < 1e-16" if p < 1e-16 else f"p = {number(p, 2)}"


def damping_note(result: dict) -> str | None:
    """One line when the graph method's ξ lies more than 2σ (the fit's σ of ξ) from the
    fit's ξ: why the two can differ, and by how many σ; None otherwise."""
    graph, fit = result["graph"], result["fit"]
    if "damping_ratio_std" not in fit:
        return None
    sigma = fit["damping_ratio_std"]
    difference = graph["damping_ratio"] - fit["damping_ratio"]
    if not (math.isfinite(sigma) and sigma > 0) or abs(difference) <= 2 * sigma:
        return None
    if graph["method"].startswith("oscillatory"):
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
        f"note: graph ξ = {number(graph['damping_ratio'])} and fit ξ = "
        f"{number(fit['damping_ratio'])} ± {number(sigma, SIGMA_SIGNIFICANT)} differ by "
        f"{_shift(difference / sigma)} (the fit's σ): {how}; the fit uses the whole record "
        "with the lags in its model."
    )


def identification_summary(result: dict) -> str:
    """The printed result of `accel-jax identify`: segment, nominal K_a, the graph method's
    estimate and what it read off the record, the fit's parameter table, δK_a, the fit's
    quality and whiteness, and the ξ note when the methods disagree."""
    seg, graph, fit = result["segment"], result["graph"], result["fit"]
    sign = "+" if seg["test_step_V"] > 0 else ""
    lines = [
        f"step of {sign}{number(seg['test_step_V'])} V at t = {quantity(seg['step_time_s'], 's')}, "
        f"{seg['samples']} samples at {number(seg['sample_rate_Hz'])} Hz",
        f"nominal K_a = {quantity(result['nominal']['scale_factor'], 'V/(m/s²)')}",
        f"{graph['method']}:",
        f"  T = {quantity(graph['time_constant_s'], 's')}, ξ = {number(graph['damping_ratio'])}, "
        f"K̂_a = {quantity(graph['scale_factor'], 'V/(m/s²)')}, "
        f"δK_a = {graph['dKa_percent']:+.4f} %",
    ]
    if "crossing_t1_s" in graph:
        lines.append(
            f"  read off: U_ss = {quantity(graph['steady_state_V'], 'V')}, crossings "
            f"t1 = {quantity(graph['crossing_t1_s'], 's')}, "
            f"t2 = {quantity(graph['crossing_t2_s'], 's')}, "
            f"A1 = {quantity(graph['overshoot_A1_V'], 'V')}, "
            f"A2 = {quantity(graph['undershoot_A2_V'], 'V')}"
        )
    elif "inflection_time_s" in graph:
        lines.append(
            f"  read off: U_ss = {quantity(graph['steady_state_V'], 'V')}, inflection at "
            f"{quantity(graph['inflection_time_s'], 's')}, T1..T4 = "
            + ", ".join(quantity(graph[f"T{k}_s"], "s") for k in range(1, 5))
        )
    if "failed" in fit:
        lines.append(f"least-squares fit failed: {fit['failed']}")
        return "\n".join(lines)
    lines.append(f"{fit['method']}:")
    lines += ["  " + line for line in parameter_table(result)]
    lines.append(f"  δK_a = {fit['dKa_percent']:+.4f} ± {fit['dKa_std_percent']:.4f} %")
    lines += ["  " + line for line in quality_lines(result)]
    note = damping_note(result)
    if note is not None:
        lines.append(note)
    return "\n".join(lines)


def _time_scale(duration: float) -> tuple[float, str]:
    """(factor, unit) for a time axis: µs under 2 ms, ms under 2 s, else s."""
    if duration < 2e-3:
        return 1e-6, "µs"
    if duration < 2.0:
        return 1e-3, "ms"
    return 1.0, "s"


def _volt_scale(magnitude: float) -> tuple[float, str]:
    """(factor, unit) for a voltage axis of this size."""
    for prefix, factor in _PREFIXES:
        if magnitude >= factor:
            return factor, f"{prefix}V"
    return 1e-9, "nV"


def identification_figure(result: dict, *, title: str | None = None):
    """The `identify --plot` figure, three panels on one page width.

    (a) the measured u_out and the fitted model over the segment, with U_ss and what the
    graph method read: the crossings t1, t2 and the extrema A1, A2 (oscillatory) or the
    inflection and its tangent (aperiodic); (b) the residual measured − model with the ±2σ
    noise band; (c) the residual's autocorrelation with its 95 % band and the Ljung-Box test.

    **Arguments:**

    - `result`: the dict of `identify_step_record` (with its `traces`).
    - `title`: a title over the panels, e.g. the record's file name.

    **Returns:** a `matplotlib.figure.Figure`, not attached to pyplot (no backend is chosen
    here; saving it as PNG renders with Agg).
    """
    from matplotlib.figure import Figure

    traces, fit = result["traces"], result["fit"]
    t = np.asarray(traces["t_s"], dtype=np.float64)
    u = np.asarray(traces["u_out_V"], dtype=np.float64)
    model = traces.get("model_V")
    scale, unit = _time_scale(float(t[-1] - t[0]))

    fig = Figure(figsize=(8.0, 9.5), layout="constrained")
    grid = fig.add_gridspec(3, 1, height_ratios=(3.2, 2.0, 2.0))
    ax_a = fig.add_subplot(grid[0])
    ax_b = fig.add_subplot(grid[1], sharex=ax_a)
    ax_c = fig.add_subplot(grid[2])
    if title:
        fig.suptitle(title, fontsize=10)

    _response_panel(ax_a, result, t / scale, u, model, scale)
    ax_a.set_ylabel("u_out [V]")
    ax_a.tick_params(labelbottom=False)
    ax_b.set_xlabel(f"time [{unit}]")
    if model is None:
        for ax in (ax_b, ax_c):
            ax.set_axis_off()
        ax_b.text(
            0.5,
            0.5,
            f"least-squares fit failed:\n{fit['failed']}",
            ha="center",
            va="center",
            wrap=True,
            transform=ax_b.transAxes,
        )
        return fig
    _residual_panel(ax_b, fit["quality"], t / scale, u - np.asarray(model))
    _autocorrelation_panel(ax_c, fit["quality"]["whiteness"], float(t[1] - t[0]))
    return fig


def _response_panel(ax, result, t, u, model, scale) -> None:
    graph, fit = result["graph"], result["fit"]
    ax.plot(t, u, lw=0.6, color="0.55", label="measured u_out")
    if model is not None:
        label = f"fitted model (fit {fit['quality']['fit_percent']:.2f} %)"
        ax.plot(t, model, lw=1.4, color="C0", label=label)
    steady = graph["steady_state_V"]
    ax.axhline(steady, color="k", lw=0.7, ls="--", label="U_ss (graph method)")
    step = result["segment"]["step_time_s"] / scale
    ax.axvline(step, color="0.3", lw=0.7, ls=":", label="test step applied")
    if "crossing_t1_s" in graph:
        for name in ("t1", "t2"):
            ax.axvline(graph[f"crossing_{name}_s"] / scale, color="C3", lw=0.9, ls="-.")
            ax.annotate(
                name,
                (graph[f"crossing_{name}_s"] / scale, 0.0),
                xycoords=("data", "axes fraction"),
                xytext=(3, 4),
                textcoords="offset points",
                color="C3",
            )
        before = u[t < step]
        sign = 1.0 if steady >= (before.mean() if before.size else u[0]) else -1.0
        for name, key, side in (("A1", "overshoot_A1", 1.0), ("A2", "undershoot_A2", -1.0)):
            when = graph[f"{key}_time_s"] / scale
            peak = steady + side * sign * graph[f"{key}_V"]
            ax.annotate(
                "",
                (when, peak),
                xytext=(when, steady),
                arrowprops={"arrowstyle": "<->", "color": "C3", "lw": 1.0},
            )
            ax.annotate(
                f"{name} = {quantity(graph[f'{key}_V'], 'V', 3)}",
                (when, peak),
                xytext=(6, 6 * side * sign - 4),
                textcoords="offset points",
                color="C3",
                fontsize=9,
            )
        ax.plot([], [], color="C3", ls="-.", label="graph method: crossings t1, t2; extrema A1, A2")
    elif "inflection_time_s" in graph:
        when = graph["inflection_time_s"]
        level = float(np.interp(when / scale, t, u))
        slope = graph["max_slope_V_per_s"] * scale  # V per axis unit
        before = u[t < step]
        initial = before.mean() if before.size else u[0]
        ends = np.array([initial, steady])
        tangent = when / scale + (ends - level) / slope
        ax.plot(tangent, ends, color="C3", lw=0.9, ls="-.", label="tangent at the steepest slope")
        ax.plot([when / scale], [level], "o", color="C3", ms=5, label="graph method: inflection")
    method = graph["method"].split(" (")[0]
    ax.set_title(f"(a) measured vs fitted model; {method} graph method marked", fontsize=10)
    ax.legend(fontsize=8, loc="best")


def _residual_panel(ax, quality, t, residual) -> None:
    sigma = quality["noise_std_V"]
    factor, unit = _volt_scale(max(float(np.max(np.abs(residual))), 2 * sigma, 1e-12))
    ax.axhspan(-2 * sigma / factor, 2 * sigma / factor, color="C1", alpha=0.2, label="±2σ noise")
    ax.plot(t, residual / factor, lw=0.5, color="C0", label="measured − model")
    ax.axhline(0.0, color="k", lw=0.5)
    # Head room for the legend above the largest excursion.
    reach = max(float(np.max(np.abs(residual))), 2 * sigma) / factor
    ax.set_ylim(-1.15 * reach, 1.5 * reach)
    outside = float(np.mean(np.abs(residual) > 2 * sigma)) * 100
    ax.set_ylabel(f"residual [{unit}]")
    ax.set_title(
        f"(b) residual: rms {quantity(quality['residual_rms_V'], 'V', 3)}, noise σ "
        f"{quantity(sigma, 'V', 3)}; {outside:.1f} % of samples outside ±2σ",
        fontsize=10,
    )
    ax.legend(fontsize=8, loc="upper right", ncols=2)


def _autocorrelation_panel(ax, test, spacing) -> None:
    from matplotlib.ticker import MaxNLocator

    r = np.asarray(test["autocorrelation"], dtype=np.float64)
    lags = np.arange(1, r.size + 1)
    band = test["band_95"]
    ax.axhspan(-band, band, color="C1", alpha=0.2, label="95 % band ±1.96/√n")
    ax.vlines(lags, 0.0, r, color="C0", lw=1.5)
    ax.plot(lags, r, "o", color="C0", ms=4, label="r_k")
    ax.axhline(0.0, color="k", lw=0.5)
    verdict = "white" if test["white"] else f"not white at {100 * test['level']:g} %"
    ax.set_title(
        f"(c) residual autocorrelation: Ljung-Box Q = {number(test['statistic'], 3)}, "
        f"{test['lags']} lags, {_p_value(test['p_value'])}: {verdict}",
        fontsize=10,
    )
    ax.set_xlabel(f"lag [samples of {quantity(spacing, 's', 3)}]")
    ax.set_ylabel("autocorrelation r_k")
    ax.set_xlim(0.3, r.size + 0.7)
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    reach = max(float(np.max(np.abs(r))), band)
    ax.set_ylim(-1.15 * reach, 1.5 * reach)
    ax.legend(fontsize=8, loc="upper right", ncols=2)
