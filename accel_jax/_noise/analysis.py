"""One static record analysed as a navigation engineer expects (`accel-jax noise`): the
overlapping Allan deviation with χ² intervals, the IEEE noise-term fit with bootstrap
intervals, the effects the record shows (forward selection), and the identified model in
the forms filters load (`export`).
"""

from __future__ import annotations

import dataclasses
import math
import threading

import numpy as np

from .._deprecated import LegacyItems
from .._runtime import beside
from .allan_intervals import AllanDeviation, allan_deviation_intervals
from .allan_terms import TERM_NAMES, AllanTerms, Stopped, _fit_allan_terms, minimum_samples
from .export import AccelNoiseTerms
from .sensor import SensorNoiseSelection, select_sensor_noise


@dataclasses.dataclass(frozen=True, eq=False)
class StaticRecordAnalysis(LegacyItems):
    """What `analyse_static_record` found in one static record.

    **Fields:**

    - `allan`: the overlapping Allan deviation with its ±1σ χ² intervals
        (`AllanDeviation`).
    - `terms`: the IEEE noise terms Q, N, B, K, R with their bootstrap intervals
        (`AllanTerms`).
    - `selection`: the effects the record shows, by forward selection
        (`SensorNoiseSelection`).
    - `export_terms`: the identified model in the form the exports take
        (`AccelNoiseTerms`).

    `to_dict()` is the JSON of `accel-jax noise` (without its `source` and `provenance`);
    `result["allan"]` and the other keys of the dict this replaced still work for one
    release, with a `DeprecationWarning`.
    """

    allan: AllanDeviation
    terms: AllanTerms
    selection: SensorNoiseSelection
    export_terms: AccelNoiseTerms

    def to_dict(self) -> dict:
        """Plain JSON-ready values: `allan_deviation` (τ in [s], ADEV, its ±1σ bounds, the
        equivalent degrees of freedom and the noise type α), `ieee_terms` and `effects`
        (the selection, its held-out check by `HeldOutCheck.to_dict`)."""
        adev, terms, selection = self.allan, self.terms, self.selection
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
                "held_out": selection.held_out.to_dict(),
                "quantization": selection.quantization,
            },
        }

    def _legacy(self) -> dict:
        return {
            "allan": self.allan,
            "terms": self.terms,
            "selection": self.selection,
            "export_terms": self.export_terms,
        }


def analyse_static_record(
    record,
    sample_interval: float,
    *,
    unit: str = "g",
    confidence: float = 0.95,
    n_bootstrap: int = 199,
    seed: int = 0,
) -> StaticRecordAnalysis:
    """ADEV with ±1σ intervals, the IEEE terms (Q, N, B, K, R) at `confidence`, the
    forward-selected effects, and `AccelNoiseTerms` for the exports (the supported terms
    only; N, the white noise density, is always given: the white term is the nominal
    model).

    **Returns:** a `StaticRecordAnalysis`: `allan` (`AllanDeviation`), `terms`
    (`AllanTerms`), `selection` (`SensorNoiseSelection`), `export_terms`
    (`AccelNoiseTerms`). Bad input raises `ValueError`.
    """
    x = np.asarray(record, np.float64)
    least = minimum_samples()
    if x.ndim == 1 and x.size < least:  # said in the analysis's terms, before any work
        raise ValueError(
            f"a record of {x.size} samples is too short for the noise analysis: the Allan "
            f"deviation's five IEEE terms need at least {least} samples."
        )
    adev, terms, selection = _three_parts(x, sample_interval, confidence, n_bootstrap, seed)
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
    return StaticRecordAnalysis(
        allan=adev, terms=terms, selection=selection, export_terms=export_terms
    )


def _three_parts(x, sample_interval, confidence, n_bootstrap, seed):
    """The ADEV with its intervals, the IEEE terms and the selection of `x`: three
    independent computations. Where the process has two CPUs or more, the first two
    (NumPy and short XLA calls: the terms' bootstrap simulates 199 records and takes their
    ADEVs) run on a background thread while the selection runs here (`_runtime.beside`):
    the selection's compilations and its single-threaded stretches leave a CPU idle. The
    same calls, so the same results; an error is raised as in sequence (the ADEV's, then
    the terms', then the selection's). Where the selection fails or is interrupted
    (Ctrl-C), the bootstrap is stopped before its next batch, so the process does not wait
    for it. With the transient tests beside the fits (`_noise/sensor`), `accel-jax noise`
    of the benchmark's 1.3e5-sample record on the 2-core CPU, medians of 3: cold 26.4 →
    23.7 s (docs/performance.md)."""
    stop = threading.Event()

    def adev():
        return allan_deviation_intervals(x, sample_interval)

    def terms():
        return _fit_allan_terms(
            x, sample_interval, confidence, n_bootstrap, seed, TERM_NAMES, stop
        )

    futures = beside(adev, terms)  # (on one CPU, run here: an error is raised here)
    try:
        selection = select_sensor_noise(x, sample_interval)
    except Exception:
        stop.set()
        for future in futures:
            try:
                future.result()  # the earlier steps' error first, as in sequence
            except Stopped:
                pass
        raise
    except BaseException:  # an interrupt: the bootstrap ends before its next batch
        stop.set()
        raise
    return futures[0].result(), futures[1].result(), selection


def analysis_to_json(analysis: StaticRecordAnalysis | dict) -> dict:
    """Plain JSON-ready values of `analyse_static_record`'s result: its `to_dict()`. A dict
    with the four keys of the result (`allan`, `terms`, `selection`, `export_terms`) is
    taken too."""
    if isinstance(analysis, dict):
        analysis = StaticRecordAnalysis(**analysis)
    return analysis.to_dict()
