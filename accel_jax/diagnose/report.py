"""Writing a diagnosis: the JSON document of the CLI contract and the --plot figure."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .._io import save_figure_atomic, write_json_atomic
from .base import DiagnosisResult


def write_json(result: DiagnosisResult, path: str | os.PathLike, *, source=None) -> Path:
    """Write `result.to_dict()` (plus the source file name) atomically as JSON."""
    payload = result.to_dict()
    if source is not None:
        payload = {"source": str(source), **payload}
    return write_json_atomic(path, payload)


def figure(result: DiagnosisResult):
    """A 4-panel matplotlib figure: measured vs simulated, the residual before and after the
    chosen effect (held-out part shaded), the residual spectrum against the noise floor, and
    the ranking by evidence."""
    import matplotlib

    if matplotlib.get_backend().lower() not in ("agg", "pdf", "svg", "cairo"):
        matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tr = result.traces
    fig, axes = plt.subplots(2, 2, figsize=(12, 8))
    t_ms = np.asarray(tr["t"]) * 1e3
    split_ms = t_ms[tr["split"]] if tr["split"] < len(t_ms) else t_ms[-1]

    ax = axes[0, 0]
    ax.plot(t_ms, tr["measured"], ".", ms=2, color="0.5", label="measured")
    ax.plot(t_ms, tr["nominal_unrefitted"], ":", color="C3", label="nominal (prior values)")
    ax.plot(t_ms, tr["nominal"], "-", color="C0", label="nominal, refitted")
    if tr["best_name"] != "nominal":
        ax.plot(t_ms, tr["best"], "--", color="C2", label=f"+ {tr['best_name']}")
    ax.axvspan(split_ms, t_ms[-1], color="0.9", zorder=-1, label="held out")
    ax.set_xlabel("time [ms]")
    ax.set_ylabel("U_out [V]")
    ax.set_title("measured vs simulated")
    ax.legend(fontsize=8)

    ax = axes[0, 1]
    ax.plot(t_ms, tr["residual_before"] * 1e3, lw=0.7, color="C0", label="nominal refit")
    label = f"with {tr['best_name']}" if tr["best_name"] != "nominal" else "(no effect chosen)"
    ax.plot(t_ms, tr["residual_after"] * 1e3, lw=0.7, color="C2", label=label)
    ax.axvspan(split_ms, t_ms[-1], color="0.9", zorder=-1, label="held out")
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

    ax = axes[1, 1]
    names = [r["effect"] for r in result.ranking]
    evidence = np.array([r["evidence"] for r in result.ranking], dtype=float)
    shown = np.sign(evidence) * np.log10(1 + np.abs(evidence))
    colors = ["C2" if r["significant"] else "0.6" for r in result.ranking]
    ax.barh(names[::-1], shown[::-1], color=colors[::-1])
    ax.axvline(np.log10(1 + 10.0), color="k", ls=":", label="significance (2 ln B = 10)")
    ax.set_xlabel("sign · log10(1 + |2 ln B|) vs nominal")
    verdict = result.verdict
    if verdict == "cannot_tell":
        verdict += f" ({' / '.join(result.tied)})"
    ax.set_title(f"ranking — verdict: {verdict}")
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def save_plot(result: DiagnosisResult, path: str | os.PathLike) -> Path:
    """Draw `figure(result)` and save it atomically as PNG."""
    import matplotlib.pyplot as plt

    fig = figure(result)
    try:
        return save_figure_atomic(fig, path)
    finally:
        plt.close(fig)
