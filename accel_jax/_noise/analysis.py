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
