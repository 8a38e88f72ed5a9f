"""The verdict of several step records of one device fitted together (`joint`).

**Verdict.** Fitted on every block of every record (the models have ≤ 1 parameter beyond the
shared device; held-out testing is the single-record diagnosis's, `diagnose_step`): the
evidence 2 ln B of each lag against the nominal (Schwarz, profiled noise per record), and
each record's excess RMS over its floor. `none` when the nominal leaves every record at its
floor and no lag is significant; a lag's name when it is significant, leaves every record at
its floor, and beats the other lag by `INDISTINCT`; `cannot_tell` when both do within it;
`unexplained` when no candidate brings every record to its floor.

With `cannot_tell` between the lags, the experiment that would break the tie is designed
by `design.next_experiments`.

Float64 throughout (x64 must be enabled).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from ..._data import DataError, Dataset, NominalDevice, StepData
from ..base import INDISTINCT, SIGNIFICANCE, require_float64, verdict_line
from .design import next_experiments
from .model import REFIT_FIELDS
from .joint import (
    CANDIDATES,
    PreparedSet,
    _score,
    fit_set,
    prepare_set,
    release_lag_states,
    shared_values,
)
from .segments import time_text
from .state import JointScore, SetRankingEntry


@dataclasses.dataclass
class SetDiagnosis:
    """The diagnosis of several step records of one device.

    **Fields:** `verdict` (`none`, `torquer_lag`, `output_filter`, `cannot_tell`,
    `unexplained`); `tied` (with `cannot_tell`); `reason`; `ranking` (per candidate: evidence
    2 ln B against the nominal, records at their floor, shared values; each a
    `SetRankingEntry`'s `to_dict`); `records` (per record: name, whether simulated with the
    stops, whether it has `a_in`, then its misfit under the chosen model, a `RecordScore`'s
    `to_dict`); `shared` (the chosen model's shared device values); `next_experiment` (with
    `cannot_tell`: the best experiments of `experiment_menu`, each with its expected
    2 ln B); `notes`.
    """

    verdict: str
    tied: list
    reason: str
    ranking: list
    records: list
    shared: dict
    next_experiment: list = dataclasses.field(default_factory=list)
    notes: list = dataclasses.field(default_factory=list)
    kind: str = "step_set"
    traces: dict = dataclasses.field(default_factory=dict, repr=False)

    def to_dict(self) -> dict:
        return {
            "kind": self.kind,
            "verdict": self.verdict,
            "tied": list(self.tied),
            "reason": self.reason,
            "ranking": self.ranking,
            "records": self.records,
            "shared": self.shared,
            "next_experiment": self.next_experiment,
            "notes": list(self.notes),
        }

    def summary(self) -> str:
        lines = [f"kind: step (joint diagnosis of {len(self.records)} records of one device)"]
        lines.append(verdict_line(self.verdict, self.tied))
        lines.append(f"why: {self.reason}")
        for r in self.records:
            stops = ", simulated with the stops" if r["on_stops"] else ""
            lines.append(
                f"record {r['name']}{stops}: residual {r['excess_over_floor']:.2f} floors above "
                f"its {r['noise_floor_V']:.3g} V noise floor"
            )
        lines.append("ranking (evidence = 2 ln B against the nominal model, all records together):")
        for r in self.ranking:
            at = "every record at its floor" if r["all_at_floor"] else "misfit remains"
            lines.append(f"  {r['effect']:<14} evidence {r['evidence']:>9.1f}  {at}")
        values = self.shared
        lag = [
            f"T_dm {time_text(values['torquer_time_constant'])}",
            f"T_f {time_text(values['filter_time_constant'])}",
        ]
        lines.append("shared: " + ", ".join(lag) + _shared_extra(values))
        for e in self.next_experiment[:3]:
            lines.append(
                f"next experiment: {e['description']} (expected 2 ln B ≈ {e['expected_2lnB']:.0f})"
            )
        lines.extend(f"note: {n}" for n in self.notes)
        return "\n".join(lines)


def _shared_extra(values) -> str:
    parts = []
    for field in REFIT_FIELDS:
        if field in values:
            parts.append(f"{field} {values[field]['shift_sigma']:+.1f}σ")
    if "stop_voltage_V" in values:
        parts.append(
            f"stop voltage k_dp·k_y·h_max {values['stop_voltage_V']:.4g} V (nominal "
            f"{values['stop_voltage_nominal_V']:.4g} V)"
        )
    return ("; " + ", ".join(parts)) if parts else ""


def diagnose_step_set(
    datasets: Sequence[Dataset],
    nominal: NominalDevice | None = None,
    *,
    names: list[str] | None = None,
    recommend: bool = True,
) -> SetDiagnosis:
    """Diagnose several step records of one device together (see the module docstring).

    **Arguments:** `datasets` validated `StepData` records of one device (small steps,
    stop-level steps, acceleration steps in any mix); `nominal` its nominal device (default
    the reference); `names` the records' names for the report; `recommend` whether a
    `cannot_tell` computes the next experiment (`next_experiments`). A record of another
    kind is refused (`DataError`, naming each record's kind).

    **Returns:** a `SetDiagnosis`. Float64 (x64 must be enabled; `ValueError` otherwise).
    """
    require_float64("the evidence compares log-likelihoods of ~1e4 to within ~1")
    nominal = NominalDevice.reference() if nominal is None else nominal
    names = names or [f"#{i + 1}" for i in range(len(datasets))]
    if not all(isinstance(d, StepData) for d in datasets):
        listed = ", ".join(
            f"{name} ({getattr(d, 'kind', type(d).__name__)})"
            for name, d in zip(names, datasets, strict=True)
        )
        raise DataError(
            "several records are diagnosed together only when every one is a step "
            f"record (t, u_test, u_out[, a_in]) of one device; got {listed}."
        )
    steps = [d for d in datasets if isinstance(d, StepData)]  # all of them, checked above
    given = [name for name, d in zip(names, steps, strict=True) if d.input_delay is not None]
    if given:
        raise DataError(
            f"record {given[0]} gives an input delay: the joint fit of a set takes each "
            "record's change times as its columns show them; diagnose that record alone to "
            "use its known delay."
        )
    prepared = prepare_set(steps, nominal)
    fits = fit_set(prepared, nominal)
    scores, ranking = _rank(fits, prepared, nominal)
    notes = [
        f"{name}: {note}"
        for name, p in zip(names, prepared.preps, strict=True)
        for note in p.notes
    ]
    if not any(r.all_at_floor for r in ranking):
        first = min(r.worst_excess_over_floor for r in ranking)
        prepared, fits = release_lag_states(prepared, nominal, fits)
        scores, ranking = _rank(fits, prepared, nominal)
        notes.append(
            "with every record's initial lag states on their first-order rule no candidate "
            f"brought every record to its floor (best worst record {first:.2f} floors); "
            "refitted with them free (second stage, `release_lag_states`)"
        )
    return _diagnose_prepared(prepared, nominal, fits, scores, ranking, names, notes, recommend)


def _rank(
    fits, prepared: PreparedSet, nominal: NominalDevice
) -> tuple[dict[str, JointScore], list[SetRankingEntry]]:
    """Each candidate's score (`_score`) and ranking entry (`SetRankingEntry`): evidence
    against the nominal (Schwarz: ln n per lag parameter), records at their floor, shared
    values."""
    scores = {c: _score(fits[c], prepared, nominal) for c in CANDIDATES}
    n_total = scores["nominal"].n
    ranking = []
    for c in CANDIDATES:
        evidence = 2 * (scores[c].log_likelihood - scores["nominal"].log_likelihood)
        if c != "nominal":
            evidence -= math.log(n_total)
        ranking.append(
            SetRankingEntry(
                effect=c,
                evidence=float(evidence) if c != "nominal" else 0.0,
                all_at_floor=all(r.at_floor for r in scores[c].records),
                worst_excess_over_floor=max(r.excess_over_floor for r in scores[c].records),
                converged=fits[c].converged,
                shared=shared_values(fits[c], prepared, nominal, c),
            )
        )
    return scores, ranking


def _verdict(ranking: list[SetRankingEntry]) -> tuple[str, list[str], str]:
    by = {r.effect: r for r in ranking}
    lags = sorted((r for r in ranking if r.effect != "nominal"), key=lambda r: -r.evidence)
    good = [r for r in lags if r.evidence >= SIGNIFICANCE and r.all_at_floor]
    tied: list[str] = []
    if by["nominal"].all_at_floor and not any(r.evidence >= SIGNIFICANCE for r in lags):
        verdict = "none"
        reason = (
            "the nominal device, refitted within its prior, leaves every record at its noise "
            "floor and neither lag is significant"
        )
    elif good and (len(good) == 1 or good[0].evidence - good[1].evidence >= INDISTINCT):
        verdict = good[0].effect
        other = lags[1]
        reason = (
            f"{verdict} brings every record to its floor (evidence {good[0].evidence:.1f} "
            f"against the nominal, {good[0].evidence - other.evidence:.1f} against "
            f"{other.effect})"
        )
    elif len(good) == 2:
        verdict = "cannot_tell"
        tied = [good[0].effect, good[1].effect]
        reason = (
            f"both lags bring every record to its floor; their evidence differs by "
            f"{good[0].evidence - good[1].evidence:.1f} (< {INDISTINCT:g}): these "
            "records cannot separate a lag inside the loop from one on the output"
        )
    else:
        verdict = "unexplained"
        worst = min(ranking, key=lambda r: r.worst_excess_over_floor)
        reason = (
            "no candidate brings every record to its floor; the best "
            f"({worst.effect}) leaves {worst.worst_excess_over_floor:.2f} floors of "
            "excess in its worst record (an effect outside the joint model: run the "
            "single-record diagnosis of each record)"
        )
    return verdict, tied, reason


def _diagnose_prepared(prepared, nominal, fits, scores, ranking, names, notes, recommend):
    verdict, tied, reason = _verdict(ranking)
    by = {r.effect: r for r in ranking}
    chosen = verdict if verdict in CANDIDATES else (tied[0] if tied else "nominal")
    # What the result reports: dicts (`to_dict`), each record's name and kind first.
    records = [
        {"name": name, "on_stops": p.on_stops, "has_accel": p.has_accel, **score.to_dict()}
        for name, p, score in zip(names, prepared.preps, scores[chosen].records, strict=True)
    ]
    traces = {
        "records": [
            {
                "name": name,
                "t": np.asarray(p.view.t),
                "u_out": prepared.data[r, : p.n],
                "sigma": p.sigma,
                "predictions": {c: fits[c].prediction[r, : p.n] for c in CANDIDATES},
            }
            for r, (name, p) in enumerate(zip(names, prepared.preps, strict=True))
        ],
        "chosen": chosen,
    }
    result = SetDiagnosis(
        verdict=verdict,
        tied=tied,
        reason=reason,
        ranking=[r.to_dict() for r in ranking],
        records=records,
        shared=by[chosen].shared,
        notes=notes,
        traces=traces,
    )
    if verdict == "cannot_tell" and recommend:
        result.next_experiment = next_experiments(prepared, nominal, fits, tied)
        if result.next_experiment:
            best = result.next_experiment[0]
            result.reason += (
                f"; to separate {tied[0]} from {tied[1]}, {best['description']} (expected "
                f"2 ln B ≈ {best['expected_2lnB']:.0f})"
            )
    return result
