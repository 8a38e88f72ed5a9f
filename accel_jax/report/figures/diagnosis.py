"""The diagnosis's figures (`accel-jax diagnose --plot`): for one record, measured against
simulated, the residual before and after the chosen effect (held-out part shaded), where
the residual lies and the ranking by evidence (with the Allan deviation and the selection's
steps for a noise record); for a set of step records, each record's block means with the
chosen model and every candidate's residual in units of its noise floor."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..._format import number
from ..._io import save_figure_atomic
from ...diagnose import DiagnosisResult, SetDiagnosis


def figure(result: DiagnosisResult):
    """A 4-panel matplotlib figure: measured vs simulated, the residual before and after the
    chosen effect (held-out part shaded, or cross-validated rows for a vibration table),
    where the residual lies (its spectrum against the noise floor; for a vibration table,
    across vibration levels), and the ranking by evidence."""
    import matplotlib

    if matplotlib.get_backend().lower() not in ("agg", "pdf", "svg", "cairo"):
        matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if result.kind == "noise":  # two more panels: the Allan deviation and the effects' steps
        fig, axes = plt.subplots(2, 3, figsize=(17, 8))
    else:
        fig, axes = plt.subplots(2, 2, figsize=(12, 8))
    drawers = {"step": _step_panels, "vibration": _vibration_panels, "noise": _noise_panels}
    drawers[result.kind](result, axes)
    _ranking_panel(result, axes[1, 1])
    fig.tight_layout()
    return fig


def _step_panels(result: DiagnosisResult, axes) -> None:
    tr = result.traces
    t_ms = np.asarray(tr["t"]) * 1e3
    held = np.asarray(tr["held_out"], dtype=bool)

    ax = axes[0, 0]
    ax.plot(t_ms, tr["measured"], ".", ms=2, color="0.5", label="measured")
    ax.plot(t_ms, tr["nominal_unrefitted"], ":", color="C3", label="nominal (prior values)")
    ax.plot(t_ms, tr["nominal"], "-", color="C0", label="nominal, refitted")
    if tr["best_name"] != "nominal":
        ax.plot(t_ms, tr["best"], "--", color="C2", label=f"+ {tr['best_name']}")
    _shade(ax, t_ms, held)
    ax.set_xlabel("time [ms]")
    ax.set_ylabel("U_out [V]")
    ax.set_title("measured vs simulated")
    ax.legend(fontsize=8)

    ax = axes[0, 1]
    ax.plot(t_ms, tr["residual_before"] * 1e3, lw=0.7, color="C0", label="nominal refit")
    label = f"with {tr['best_name']}" if tr["best_name"] != "nominal" else "(no effect chosen)"
    ax.plot(t_ms, tr["residual_after"] * 1e3, lw=0.7, color="C2", label=label)
    _shade(ax, t_ms, held)
    ax.set_xlabel("time [ms]")
    ax.set_ylabel("residual [mV]")
    ax.set_title(
        f"held-out gap {result.gap['before'] * 1e3:.3g} → {result.gap['after'] * 1e3:.3g} mV "
        f"(shrink {result.gap['shrink']:.2f})"
    )
    ax.legend(fontsize=8)

    ax = axes[1, 0]
    spectrum = result.where.get("frequency", {})
    if spectrum.get("frequency_Hz"):
        f = np.asarray(spectrum["frequency_Hz"])[1:]
        psd = np.asarray(spectrum["psd_V2_per_Hz"])[1:]
        ax.loglog(f, psd, color="C0", label="nominal-refit residual")
        ax.axhline(spectrum["noise_floor_V2_per_Hz"], color="k", ls="--", label="white floor 2σ²dt")
        ax.legend(fontsize=8)
    ax.set_xlabel("frequency [Hz]")
    ax.set_ylabel("PSD [V²/Hz]")
    ax.set_title("residual spectrum")


def _shade(ax, t, held):
    """Grey spans over the held-out samples (one legend entry)."""
    padded = np.concatenate([[False], held, [False]]).astype(int)
    edges = np.flatnonzero(np.diff(padded))
    for k, (a, b) in enumerate(zip(edges[::2], edges[1::2], strict=True)):
        stop = t[b] if b < len(t) else t[-1]
        ax.axvspan(t[a], stop, color="0.9", zorder=-1, label="held out" if k == 0 else None)


def _vibration_panels(result: DiagnosisResult, axes) -> None:
    tr = result.traces
    rows = tr["row"]
    ax = axes[0, 0]
    ppm = 1e6
    ax.plot(rows, (tr["measured"] - tr["a_in"]) * ppm, "o", ms=4, color="0.4", label="measured")
    ax.plot(rows, (tr["nominal"] - tr["a_in"]) * ppm, "_", ms=10, color="C0", label="nominal refit")
    if tr["best_name"] != "nominal":
        label = f"+ {tr['best_name']}"
        ax.plot(rows, (tr["best"] - tr["a_in"]) * ppm, "x", color="C2", label=label)
    ax.set_xlabel("table row")
    ax.set_ylabel("a_out − a_in [µg]")
    ax.set_title("measured vs model, per test condition")
    ax.legend(fontsize=8)

    ax = axes[0, 1]
    ax.plot(rows, tr["held_out_before"] * ppm, "o", ms=4, color="C0", label="nominal (held out)")
    label = f"with {tr['best_name']}" if tr["best_name"] != "nominal" else "(no effect chosen)"
    ax.plot(rows, tr["held_out_after"] * ppm, "s", ms=4, color="C2", label=label)
    ax.axhline(0, color="k", lw=0.5)
    ax.set_xlabel("table row")
    ax.set_ylabel("cross-validated residual [µg]")
    ax.set_title(
        f"held-out gap {result.gap['before'] * ppm:.3g} → {result.gap['after'] * ppm:.3g} µg "
        f"(shrink {result.gap['shrink']:.2f})"
    )
    ax.legend(fontsize=8)

    ax = axes[1, 0]
    scatter = ax.scatter(
        tr["vibration_mean_square"], tr["residual_before"] * ppm, c=tr["a_in"], cmap="coolwarm"
    )
    ax.axhline(0, color="k", lw=0.5)
    sigma = result.where.get("noise_sigma_g", 0.0) * ppm
    ax.axhspan(-2 * sigma, 2 * sigma, color="0.9", zorder=-1, label="±2σ noise")
    ax.set_xlabel("input-axis vibration mean square b²/2 + σ² [g²]")
    ax.set_ylabel("nominal residual [µg]")
    ax.set_title("where: residual across vibration levels (colour: a_in [g])")
    ax.figure.colorbar(scatter, ax=ax, fraction=0.046)
    ax.legend(fontsize=8)


def _noise_panels(result: DiagnosisResult, axes) -> None:
    tr = result.traces
    t = np.asarray(tr["t"])
    split_t = t[tr["split"]] if tr["split"] < len(t) else t[-1]
    ax = axes[0, 0]
    centred = np.asarray(tr["measured"]) - tr["level"]
    unit, scale = _g_unit(float(np.std(centred)))
    ax.plot(t, centred * scale, lw=0.5, color="0.4")
    ax.axvspan(split_t, t[-1], color="0.9", zorder=-1, label="held out")
    ax.set_xlabel("time [s]")
    ax.set_ylabel(f"a_out − level [{unit}]")
    ax.set_title("static record about its level")
    ax.legend(fontsize=8)

    ax = axes[0, 1]
    if "innovations_before" in tr:
        ax.plot(t, tr["innovations_before"] * scale, lw=0.5, color="C0", label="white (nominal)")
        label = f"with {tr['best_name']}" if tr["best_name"] != "nominal" else "(no effect chosen)"
        ax.plot(t, tr["innovations_after"] * scale, lw=0.5, color="C2", label=label)
        ax.axvspan(split_t, t[-1], color="0.9", zorder=-1)
        ax.set_xlabel("time [s]")
        ax.set_ylabel(f"one-step prediction error [{unit}]")
        ax.set_title(
            f"held-out gap {number(result.gap['before'] * scale, 3)} → "
            f"{number(result.gap['after'] * scale, 3)} {unit} "
            f"(shrink {result.gap['shrink']:.2f})"
        )
        ax.legend(fontsize=8)
    else:  # a long record, diagnosed by the Whittle selection alone: no one-step errors
        ax.axis("off")
        ax.text(0, 0.5, "\n".join(_wrap(result.reason, 60)), fontsize=8, va="center")
        ax.set_title("why (forward selection)")

    _allan_panel(result, axes[0, 2])
    _steps_panel(result, axes[1, 2])

    ax = axes[1, 0]
    spectrum = result.where["frequency"]
    f = np.asarray(spectrum["frequency_Hz"])[1:]
    psd = np.asarray(spectrum["psd_g2_per_Hz"])[1:]
    ax.loglog(f, psd, color="C0", label="record about its level")
    model = result.refit.get("model_parameters")
    dt = float(np.median(np.diff(t))) if t.size > 1 else 1.0
    fitted = _model_psd(model, f, dt) if model else None
    if model and fitted is not None:
        white = model["parameters"]["white_sigma_g"]["value"]
        ax.axhline(
            2 * white**2 * dt,
            color="k",
            ls="--",
            label=f"fitted white floor 2σ_w²Δ ({model['model']})",
        )
        if model["model"] != "white":
            ax.loglog(f, fitted, color="C3", lw=1.2, label=f"fitted model {model['model']}")
    else:
        ax.axhline(spectrum["noise_floor_g2_per_Hz"], color="k", ls="--", label="white floor 2σ²Δ")
    ax.set_xlabel("frequency [Hz]")
    ax.set_ylabel("PSD [g²/Hz]")
    ax.set_title("spectrum vs the fitted model")
    ax.legend(fontsize=8)


def _model_psd(model: dict, f: np.ndarray, dt: float) -> np.ndarray | None:
    """One-sided PSD [g²/Hz] of the fitted sampled model (the scale of `_welch`: 2Δσ² for
    white noise): white + Gauss–Markov (AR(1), ρ = e^{−Δ/τ_c}), exponential-cosine
    (ρ = e^{−αΔ}, θ = βΔ) or random walk (increments qΔ)."""
    p = {k: v["value"] for k, v in model["parameters"].items()}
    if "white_sigma_g" not in p:
        return None
    omega = 2 * np.pi * f * dt
    out = np.full_like(f, 2 * dt * p["white_sigma_g"] ** 2)

    def poisson(x, rho):
        return (1 - rho**2) / (1 - 2 * rho * np.cos(x) + rho**2)

    if "correlation_time_s" in p and "sigma_g" in p:
        out = out + 2 * dt * p["sigma_g"] ** 2 * poisson(
            omega, np.exp(-dt / p["correlation_time_s"])
        )
    elif "decay_rate_per_s" in p and "sigma_g" in p:
        rho, theta = np.exp(-p["decay_rate_per_s"] * dt), p["angular_frequency_rad_per_s"] * dt
        out = out + dt * p["sigma_g"] ** 2 * (
            poisson(omega - theta, rho) + poisson(omega + theta, rho)
        )
    elif "intensity_g2_per_s" in p:
        out = out + 2 * dt * p["intensity_g2_per_s"] * dt / (2 - 2 * np.cos(omega))
    return out


def _wrap(text: str, width: int) -> list:
    import textwrap

    return textwrap.wrap(text, width)


def _g_unit(typical: float) -> tuple[str, float]:
    """g, mg or µg, whichever puts a typical value between 0.1 and 1000."""
    for unit, scale in (("g", 1.0), ("mg", 1e3), ("µg", 1e6)):
        if typical * scale >= 0.1:
            return unit, scale
    return "µg", 1e6


def _allan_panel(result: DiagnosisResult, ax) -> None:
    allan = result.where.get("allan")
    if not allan:
        ax.axis("off")
        return
    tau, adev = np.asarray(allan["tau_s"]), np.asarray(allan["adev_g"])
    lo, hi = np.asarray(allan["lower_1sigma_g"]), np.asarray(allan["upper_1sigma_g"])
    unit, scale = _g_unit(float(np.median(adev)))
    ax.errorbar(tau, adev * scale, yerr=[(adev - lo) * scale, (hi - adev) * scale], fmt="o", ms=3)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("τ [s]")
    ax.set_ylabel(f"Allan deviation [{unit}]")
    ax.set_title("overlapping ADEV, ±1σ (EDF) intervals")


def _steps_panel(result: DiagnosisResult, ax) -> None:
    sensor = result.where.get("sensor_effects")
    if not sensor:
        ax.axis("off")
        ax.set_title("forward selection: not needed (the exact verdict is clear)", fontsize=9)
        return
    steps = sensor["steps"]
    ax.bar(range(len(steps)), [st["explained_fraction"] for st in steps], color="C2")
    ax.set_xticks(
        range(len(steps)), [st["added"] or "white" for st in steps], rotation=30, ha="right"
    )
    ax.set_ylim(0, 1.05)
    ax.set_ylabel("explained fraction (held-out deviance)")
    ax.set_title("\n".join(_wrap(f"effects added: {sensor['verdict']}", 50)), fontsize=9)


def _ranking_panel(result: DiagnosisResult, ax) -> None:
    names = [r["effect"] for r in result.ranking]
    evidence = np.array([r["evidence"] for r in result.ranking], dtype=float)
    shown = np.sign(evidence) * np.log10(1 + np.abs(evidence))
    colors = ["C2" if r["significant"] else "0.6" for r in result.ranking]
    ax.barh(names[::-1], shown[::-1], color=colors[::-1])
    # The evidence itself beside each bar: bars on a log scale hide orders of magnitude.
    for y, (value, length) in enumerate(zip(evidence[::-1], shown[::-1], strict=True)):
        text = number(value, 3) if np.isfinite(value) else "—"
        ax.text(
            length, y, f" {text}", va="center", ha="left" if length >= 0 else "right", fontsize=8
        )
    ax.margins(x=0.15)
    ax.axvline(np.log10(1 + 10.0), color="k", ls=":", label="significance (2 ln B = 10)")
    ax.set_xlabel("sign · log10(1 + |2 ln B|) vs nominal")
    verdict = result.verdict
    if verdict == "cannot_tell":
        verdict += f" ({' / '.join(result.tied)})"
    ax.set_title("\n".join(_wrap(f"ranking — verdict: {verdict}", 50)), fontsize=9)
    ax.legend(fontsize=8)


def save_plot(result: DiagnosisResult, path: str | os.PathLike) -> Path:
    """Draw `figure(result)` and save it atomically as PNG."""
    import matplotlib.pyplot as plt

    fig = figure(result)
    try:
        return save_figure_atomic(fig, path)
    finally:
        plt.close(fig)


def set_figure(result: SetDiagnosis):
    """One row per record: the measured block means with the chosen model (left), and each
    candidate's residual in units of the record's noise floor (right)."""
    import matplotlib

    if matplotlib.get_backend().lower() not in ("agg", "pdf", "svg", "cairo"):
        matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = result.traces["records"]
    fig, axes = plt.subplots(len(rows), 2, figsize=(13, 2.6 * len(rows) + 0.8), squeeze=False)
    chosen = result.traces["chosen"]
    for (left, right), row in zip(axes, rows, strict=True):
        t = 1e3 * (row["t"] - row["t"][0])
        left.plot(t, row["u_out"], lw=0.8, color="0.3", label="measured (block means)")
        left.plot(t, row["predictions"][chosen], lw=0.8, color="C3", ls="--", label=chosen)
        left.set_ylabel("U_out [V]")
        left.set_title(str(row["name"]), fontsize=9, loc="left")
        left.legend(fontsize=7, loc="best")
        for k, (name, prediction) in enumerate(row["predictions"].items()):
            residual = (row["u_out"] - prediction) / row["sigma"]
            right.plot(t, residual, lw=0.6, color=f"C{k}", label=name)
        right.axhspan(-1, 1, color="0.85", zorder=0)
        right.set_ylabel("residual / floor")
        right.set_yscale("symlog", linthresh=3)
        right.legend(fontsize=7, loc="best")
    for ax in axes[-1]:
        ax.set_xlabel("time [ms]")
    title = f"joint step diagnosis: {result.verdict}"
    if result.tied:
        title += f" ({result.tied[0]} or {result.tied[1]})"
    fig.suptitle(title + "; residual band ±1 noise floor", fontsize=10)
    fig.tight_layout()
    return fig
