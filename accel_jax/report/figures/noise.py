"""The `accel-jax noise --plot` figure: the Allan deviation with its ±1σ bands and the
fitted IEEE model over it, and the sensor-noise selection's steps."""

from __future__ import annotations

import numpy as np

from ..._io import save_figure_atomic
from ..._noise.analysis import StaticRecordAnalysis


def plot_analysis(analysis: StaticRecordAnalysis, path, *, title: str = "") -> None:
    """ADEV with its ±1σ bands and the fitted IEEE model over it, and the selection's
    steps; written whole (atomic) to `path` (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    adev, terms, selection = analysis.allan, analysis.terms, analysis.selection
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4.2), constrained_layout=True)
    ax.errorbar(
        adev.taus,
        adev.deviation,
        yerr=[adev.deviation - adev.lower, adev.upper - adev.deviation],
        fmt="o",
        ms=3,
        label="measured ADEV (±1σ, EDF)",
    )
    dense = np.geomspace(adev.taus[0], adev.taus[-1], 200)
    ax.loglog(dense, terms.deviation_at(dense), "-", label="fitted IEEE terms")
    shown = [
        f"{k} = {v['value']:.3g}" if v["supported"] else f"{k} < {v['upper']:.2g}"
        for k, v in terms.terms.items()
    ]
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("τ [s]")
    ax.set_ylabel("Allan deviation [record unit]")
    ax.set_title("Allan deviation; " + ", ".join(shown), fontsize=8)
    ax.legend(fontsize=8)
    steps = selection.steps
    labels = [s["added"] or "white" for s in steps]
    bx.bar(range(len(steps)), [s["explained_fraction"] for s in steps])
    bx.set_xticks(range(len(steps)), labels, rotation=30, ha="right", fontsize=8)
    bx.set_ylim(0, 1.05)
    bx.set_ylabel("explained fraction of the held-out excess")
    bx.set_title(f"effects: {selection.verdict}", fontsize=9)
    if title:
        fig.suptitle(title, fontsize=10)
    save_figure_atomic(fig, path)
    plt.close(fig)
