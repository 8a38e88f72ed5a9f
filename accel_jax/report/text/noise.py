"""`accel-jax noise`: the lines printed for a static record (`noise_lines`: the record, the
IEEE terms with their intervals, the effects found and what stays unexplained) and the
identified model in a filter's format (`export_text`)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np

from ..._noise import export
from ..._noise.analysis import StaticRecordAnalysis
from ..._noise.sensor import UNEXPLAINED_Z, SensorNoiseSelection
from ..._noise.sensor_text import (
    level_shift_sentence,
    low_pass_ties_sentence,
    low_pass_words,
    non_gaussian_sentence,
    saturation_sentence,
    spectral_change_sentence,
    white_floor_sentence,
)


class ExportRefused(ValueError):
    """The record cannot give what the export format needs (its message says what to do)."""


def noise_lines(n_samples: int, sample_period: float, analysis: StaticRecordAnalysis) -> list[str]:
    """From "N samples at … Hz" to the output grid: `analysis` is
    `accel_jax.analyse_static_record`'s result."""
    terms, selection = analysis.terms, analysis.selection
    lines = [
        f"{n_samples} samples at {1 / sample_period:.6g} Hz ({n_samples * sample_period:.6g} s)",
        f"IEEE noise terms ({terms.confidence:.0%} intervals; method in --json):",
    ]
    for name, entry in terms.terms.items():
        unit = entry["unit"].replace("u", "g")  # the record's unit
        if entry["supported"]:
            lines.append(
                f"  {name} = {entry['value']:.4g} {unit} "
                f"[{entry['lower']:.3g}, {entry['upper']:.3g}]"
            )
        elif entry["upper"] > 0:
            lines.append(f"  {name}: not supported by the data (< {entry['upper']:.3g} {unit})")
        else:
            lines.append(f"  {name}: not supported by the data (its whole interval is below 0)")
    if "sinusoid" in selection.effects or "bandlimit" in selection.effects:
        lines.append(
            "  (the five terms describe the ADEV alone: the periodic lines and the low-pass "
            "found below also shape it, mostly as B and N)"
        )
    lines.append(f"effects: {selection.verdict}")
    return lines + _selection_lines(selection)


def _selection_lines(selection: SensorNoiseSelection) -> list[str]:
    """The steps of the forward selection, the backward check, exchanges and ties, then
    what stays unexplained and the output grid."""
    lines = []
    for step in selection.steps[1:]:
        was = f" (added as {step['replaced']}, exchanged below)" if "replaced" in step else ""
        lines.append(
            f"  + {step['added']}{was}: 2 ln B = {step['evidence']:.1f}, explained "
            f"{step['explained_fraction']:.1%} of the held-out excess"
        )
    held = selection.held_out
    for entry in held.removed:
        lines.append(
            f"  − {entry['effect']}: added on the way, dropped by the backward check "
            f"(2 ln B = {entry['evidence']:.1f} against the final model)"
        )
    for entry in held.exchanged:
        lines.append(
            f"  ⇄ {entry['by']} in place of {entry['effect']}: "
            f"2 ln B = {entry['evidence']:.1f} in its favour"
        )
    for entry in held.ties:
        pair = f"  ? {entry['effect']} or {entry['alternative']}"
        if entry.get("judged_by") != "time_domain":
            lines.append(
                f"{pair}: the record cannot tell them apart (2 ln B = {entry['evidence']:.1f}"
                f", < {entry['bar']:g})"
            )
        elif entry["evidence"] > -entry["bar"]:
            lines.append(
                f"{pair}: weighed in the time domain, the record cannot tell them apart "
                f"(2 ln B = {entry['evidence']:.1f}, within ±{entry['bar']:g})"
            )
        else:
            lines.append(
                f"{pair}: the time-domain likelihood prefers the second (2 ln B = "
                f"{entry['evidence']:.1f}), the spectral steps took the first: not settled"
            )
    unexplained = [level_shift_sentence(shift) for shift in held.level_shifts]
    if held.more_level_shifts:
        unexplained.append("more steps in the level than were taken out")
    unexplained += [saturation_sentence(rail) for rail in held.saturation]
    if held.non_gaussian.get("significant") and not held.bursts:
        unexplained.append(non_gaussian_sentence(held.non_gaussian))
    if held.spectral_change.get("significant"):
        duration = selection.n_samples * selection.sample_interval
        unexplained.append(spectral_change_sentence(held.spectral_change, duration))
    for burst in held.bursts[:5]:
        unexplained.append(
            f"an impulsive event at {burst['start_s']:.4g} s (peak "
            f"{burst['peak']:.3g} g from the median level)"
        )
    if selection.unexplained and held.z > UNEXPLAINED_Z:
        unexplained.append(
            f"the held-out spectrum stays {held.z:.1f} standard errors above the final model's"
        )
    elif held.drifting and not held.bursts:
        unexplained.append(
            f"the level drifts {held.drift['slope_per_s']:.3g} g/s "
            f"({held.drift['t']:.0f} standard errors), which no named effect makes"
        )
    lines += [f"  unexplained: {sentence}" for sentence in unexplained]
    transient = selection.parameters.get("startup_transient")
    if transient is not None:
        line = (
            f"  start-up transient: {transient['amplitude']:.4g} g, "
            f"τ {transient['time_constant_s']:.4g} s"
        )
        if transient.get("time_constant_at_limit"):
            line += (
                " (the longest τ tried, a quarter of the training part: τ is a lower bound "
                "and the amplitude is fitted with it)"
            )
        lines.append(line)
    band = selection.parameters.get("bandlimit")
    if band is not None:
        lines.append(f"  low-pass: {low_pass_words(band)}, −3 dB at {band['corner_Hz']:.4g} Hz")
    if held.low_pass_ties:
        lines.append(f"  ? {low_pass_ties_sentence(held.low_pass_ties)}")
    after = (band or {}).get("white_after_filter_sigma")
    if after is not None:
        lines.append(f"  white noise after the low-pass (the signal chain's own): σ {after:.4g} g")
    if held.white_floor and held.white_floor["collapsed"]:
        lines.append(f"  ! {white_floor_sentence(held.white_floor)}")
    if selection.quantization is not None:
        lines.append(f"  output grid: step {selection.quantization['step']:.4g} g")
    return lines


def export_text(analysis: StaticRecordAnalysis, export_format: str) -> tuple[list[str], str]:
    """The identified model as `export_format` ("kalibr", "gnss-ins-sim" or "ieee"): the
    notes to print before it, and the text. kalibr needs a random walk > 0: where the data
    do not support K, it gets K's upper bound (said in a note); without one the export is
    refused (`ExportRefused`)."""
    terms, t = analysis.terms, analysis.export_terms
    notes = []
    if export_format == "kalibr":
        if t.random_walk is None:
            # kalibr needs a random walk > 0: the data's upper bound, said so
            bound = terms.terms["K"]["upper"] if "K" in terms.terms else 0.0
            if not bound > 0:
                raise ExportRefused(
                    "kalibr needs accelerometer_random_walk > 0 and the record gives no "
                    "bound on K (choose --export gnss-ins-sim or ieee)."
                )
            t = dataclasses.replace(t, random_walk=bound)
            notes.append(
                f"note: K is not supported by the data; kalibr gets its {terms.confidence:.0%}"
                f" upper bound {bound:.3g} g/√s (conservative)"
            )
        return notes, export.kalibr_yaml(t)
    if export_format == "gnss-ins-sim":
        for name, why in export.gnss_ins_sim_left_out(t).items():
            notes.append(f"note: {name} is not in the gnss-ins-sim export ({why})")
        doc = export.to_gnss_ins_sim(t)
        if not np.all(np.isfinite(doc["accel_b_corr"])):
            notes.append(
                "note: accel_b_corr is Infinity, gnss-ins-sim's 'no correlated bias' "
                "(Python's json reads it as inf; strict JSON parsers refuse it)"
            )
        return notes, json.dumps(doc, indent=1, default=_plain)
    return notes, json.dumps(export.to_ieee(t), indent=1, default=_plain)


def _plain(value):
    return np.asarray(value).tolist()
