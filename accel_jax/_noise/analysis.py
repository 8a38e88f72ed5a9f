"""One static record analysed as a navigation engineer expects (`accel-jax noise`): the
overlapping Allan deviation with χ² intervals, the IEEE noise-term fit with bootstrap
intervals, the effects the record shows (forward selection), and the identified model in
the forms filters load (`export`).
"""

from __future__ import annotations

import math

import numpy as np

from .allan_intervals import allan_deviation_intervals
from .allan_terms import fit_allan_terms
from .export import AccelNoiseTerms
from .sensor import select_sensor_noise


def analyse_static_record(
    record,
    sample_interval: float,
    *,
    unit: str = "g",
    confidence: float = 0.95,
    n_bootstrap: int = 199,
    seed: int = 0,
) -> dict:
    """ADEV with ±1σ intervals, the IEEE terms (Q, N, B, K, R) at `confidence`, the
    forward-selected effects, and `AccelNoiseTerms` for the exports (the supported terms
    only; N, the white noise density, is always given: the white term is the nominal
    model).

    **Returns:** a dict: `allan` (`AllanDeviation`), `terms` (`AllanTerms`), `selection`
    (`SensorNoiseSelection`), `export_terms` (`AccelNoiseTerms`). Bad input raises
    `ValueError`.
    """
    x = np.asarray(record, np.float64)
    adev = allan_deviation_intervals(x, sample_interval)
    terms = fit_allan_terms(
        x, sample_interval, confidence=confidence, n_bootstrap=n_bootstrap, seed=seed
    )
    selection = select_sensor_noise(x, sample_interval)
    mapping = {}
    for name in ("N", "K", "B", "Q"):
        entry = terms.terms.get(name)
        if entry is not None and entry["supported"]:
            mapping[name] = entry["value"]
    if "N" not in mapping:
        # The white term is the nominal model: its density from the selected model's white
        # variance (σ_w √Δt) when the ADEV fit cannot separate it.
        mapping["N"] = selection.parameters["white_sigma"] * math.sqrt(sample_interval)
    correlation = None
    if "B" in mapping and "gauss_markov" in selection.parameters:
        correlation = selection.parameters["gauss_markov"]["correlation_time_s"]
    export_terms = AccelNoiseTerms.from_mapping(
        mapping, unit, sample_rate=1 / sample_interval, bias_correlation_time=correlation
    )
    return {"allan": adev, "terms": terms, "selection": selection, "export_terms": export_terms}


def analysis_to_json(analysis: dict) -> dict:
    """Plain JSON-ready values of `analyse_static_record`'s result."""
    adev, terms, selection = analysis["allan"], analysis["terms"], analysis["selection"]
    return {
        "allan_deviation": {
            "tau_s": adev.taus.tolist(),
            "adev": adev.deviation.tolist(),
            "lower_1sigma": adev.lower.tolist(),
            "upper_1sigma": adev.upper.tolist(),
            "edf": adev.edf.tolist(),
            "noise_alpha": [None if math.isnan(a) else a for a in adev.alpha.tolist()],
        },
        "ieee_terms": {
            "confidence": terms.confidence,
            "method": terms.method,
            "terms": terms.terms,
            "model_adev": terms.model_deviation.tolist(),
        },
        "effects": {
            "verdict": selection.verdict,
            "effects": list(selection.effects),
            "unexplained": selection.unexplained,
            "steps": selection.steps,
            "parameters": selection.parameters,
            "held_out": selection.held_out,
            "quantization": selection.quantization,
        },
    }


def plot_analysis(analysis: dict, path, *, title: str = "") -> None:
    """ADEV with its ±1σ bands and the fitted IEEE model over it, and the selection's
    steps; written whole (atomic) to `path` (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .._io import save_figure_atomic

    adev, terms, selection = analysis["allan"], analysis["terms"], analysis["selection"]
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
