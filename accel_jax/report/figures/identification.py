"""The `identify --plot` figure: measured against the fitted model with the points the
graph method read, the residual in its noise band, the residual autocorrelation. Takes the
`StepIdentification` of `identify_step_record` (with its `traces`) and returns a matplotlib
`Figure`; nothing here writes a file (the CLI saves it with
`accel_jax.report.save_figure_atomic`).
"""

from __future__ import annotations

import numpy as np

from ..._identify.step_result import (
    FitFailure,
    FitQuality,
    LeastSquaresFit,
    OscillatoryEstimate,
    StepIdentification,
    WhitenessTest,
)
from ..text.identification import _PREFIXES, _p_value, number, quantity


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


def identification_figure(result: StepIdentification, *, title: str | None = None):
    """The `identify --plot` figure, three panels on one page width.

    (a) the measured u_out and the fitted model over the segment, with U_ss and what the
    graph method read: the crossings t1, t2 and the extrema A1, A2 (oscillatory) or the
    inflection and its tangent (aperiodic); (b) the residual measured − model with the ±2σ
    noise band; (c) the residual's autocorrelation with its 95 % band and the Ljung-Box test.

    **Arguments:**

    - `result`: the `StepIdentification` of `identify_step_record`.
    - `title`: a title over the panels, e.g. the record's file name.

    **Returns:** a `matplotlib.figure.Figure`, not attached to pyplot (no backend is chosen
    here; saving it as PNG renders with Agg).
    """
    from matplotlib.figure import Figure

    traces, fit = result.traces, result.fit
    t = np.asarray(traces.t_s, dtype=np.float64)
    u = np.asarray(traces.u_out_V, dtype=np.float64)
    model = traces.model_V
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
    if not isinstance(fit, LeastSquaresFit) or model is None:
        reason = fit.reason if isinstance(fit, FitFailure) else "no fitted model"
        for ax in (ax_b, ax_c):
            ax.set_axis_off()
        ax_b.text(
            0.5,
            0.5,
            f"least-squares fit failed:\n{reason}",
            ha="center",
            va="center",
            wrap=True,
            transform=ax_b.transAxes,
        )
        return fig
    _residual_panel(ax_b, fit.quality, t / scale, u - np.asarray(model))
    _autocorrelation_panel(ax_c, fit.quality.whiteness, float(t[1] - t[0]))
    return fig


def _response_panel(ax, result: StepIdentification, t, u, model, scale) -> None:
    graph, fit = result.graph, result.fit
    ax.plot(t, u, lw=0.6, color="0.55", label="measured u_out")
    if model is not None and isinstance(fit, LeastSquaresFit):
        label = f"fitted model (fit {fit.quality.fit_percent:.2f} %)"
        ax.plot(t, model, lw=1.4, color="C0", label=label)
    steady = graph.steady_state_V
    ax.axhline(steady, color="k", lw=0.7, ls="--", label="U_ss (graph method)")
    step = result.segment.step_time_s / scale
    ax.axvline(step, color="0.3", lw=0.7, ls=":", label="test step applied")
    if isinstance(graph, OscillatoryEstimate):
        for name, crossing in (("t1", graph.crossing_t1_s), ("t2", graph.crossing_t2_s)):
            ax.axvline(crossing / scale, color="C3", lw=0.9, ls="-.")
            ax.annotate(
                name,
                (crossing / scale, 0.0),
                xycoords=("data", "axes fraction"),
                xytext=(3, 4),
                textcoords="offset points",
                color="C3",
            )
        before = u[t < step]
        sign = 1.0 if steady >= (before.mean() if before.size else u[0]) else -1.0
        extrema = (
            ("A1", graph.overshoot_A1_V, graph.overshoot_A1_time_s, 1.0),
            ("A2", graph.undershoot_A2_V, graph.undershoot_A2_time_s, -1.0),
        )
        for name, size, time, side in extrema:
            when = time / scale
            peak = steady + side * sign * size
            ax.annotate(
                "",
                (when, peak),
                xytext=(when, steady),
                arrowprops={"arrowstyle": "<->", "color": "C3", "lw": 1.0},
            )
            ax.annotate(
                f"{name} = {quantity(size, 'V', 3)}",
                (when, peak),
                xytext=(6, 6 * side * sign - 4),
                textcoords="offset points",
                color="C3",
                fontsize=9,
            )
        ax.plot([], [], color="C3", ls="-.", label="graph method: crossings t1, t2; extrema A1, A2")
    else:
        when = graph.inflection_time_s
        level = float(np.interp(when / scale, t, u))
        slope = graph.max_slope_V_per_s * scale  # V per axis unit
        before = u[t < step]
        initial = before.mean() if before.size else u[0]
        ends = np.array([initial, steady])
        tangent = when / scale + (ends - level) / slope
        ax.plot(tangent, ends, color="C3", lw=0.9, ls="-.", label="tangent at the steepest slope")
        ax.plot([when / scale], [level], "o", color="C3", ms=5, label="graph method: inflection")
    method = graph.method.split(" (")[0]
    ax.set_title(f"(a) measured vs fitted model; {method} graph method marked", fontsize=10)
    ax.legend(fontsize=8, loc="best")


def _residual_panel(ax, quality: FitQuality, t, residual) -> None:
    sigma = quality.noise_std_V
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
        f"(b) residual: rms {quantity(quality.residual_rms_V, 'V', 3)}, noise σ "
        f"{quantity(sigma, 'V', 3)}; {outside:.1f} % of samples outside ±2σ",
        fontsize=10,
    )
    ax.legend(fontsize=8, loc="upper right", ncols=2)


def _autocorrelation_panel(ax, test: WhitenessTest, spacing) -> None:
    from matplotlib.ticker import MaxNLocator

    r = np.asarray(test.autocorrelation, dtype=np.float64)
    lags = np.arange(1, r.size + 1)
    band = test.band_95
    ax.axhspan(-band, band, color="C1", alpha=0.2, label="95 % band ±1.96/√n")
    ax.vlines(lags, 0.0, r, color="C0", lw=1.5)
    ax.plot(lags, r, "o", color="C0", ms=4, label="r_k")
    ax.axhline(0.0, color="k", lw=0.5)
    verdict = "white" if test.white else f"not white at {100 * test.level:g} %"
    ax.set_title(
        f"(c) residual autocorrelation: Ljung-Box Q = {number(test.statistic, 3)}, "
        f"{test.lags} lags, {_p_value(test.p_value)}: {verdict}",
        fontsize=10,
    )
    ax.set_xlabel(f"lag [samples of {quantity(spacing, 's', 3)}]")
    ax.set_ylabel("autocorrelation r_k")
    ax.set_xlim(0.3, r.size + 0.7)
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    reach = max(float(np.max(np.abs(r))), band)
    ax.set_ylim(-1.15 * reach, 1.5 * reach)
    ax.legend(fontsize=8, loc="upper right", ncols=2)
