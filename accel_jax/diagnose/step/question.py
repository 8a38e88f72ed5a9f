"""A step noise verdict (`verdict.noise_verdict`) weighed against the
discovery's best term (`weigh_discovery`), and the gap blocks of a verdict it overturns
(`_gap_of_the_nominal`)."""

from __future__ import annotations

from .. import openworld
from ..base import DiagnosisResult
from ..discovery_result import VibrationDiscovery
from .verdict import noise_verdict


def weigh_discovery(result: DiagnosisResult) -> None:
    """A noise verdict (`noise_verdict`, in question or not) against the discovery's best
    subset of terms (`result.discovery`), in place, on the held-out part: where the subset
    is credible and brings the held-out free-run gap to the floor
    (`held_out_at_floor`), and the noise leaves its own free-run gap above the floor
    (`openworld.FLOOR_FACTOR`), the verdict becomes `unexplained` — a deterministic term
    outside the library predicts the held-out part and the noise does not — with the
    noise's explained fraction 0 (a noise that absorbed a predictable misfit explains none
    of it, as `ranking_entry` counts one); otherwise the noise is kept and a note says
    what the discovery found. Both gaps are the held-out RMS in excess of the same noise
    floor, the record's (`_free_run_gap`): not the noise's gap over its own fitted variance
    (the ranking's `gap_after_V`), which a noise fitted large enough to absorb the misfit
    always brings to 0. The two evidences are not compared: the discovery's is a BIC at
    the floor's σ with the change times' priors, the noise's a likelihood ratio with the
    variance fitted, and far above the floor the first grows as n(σ̂²/σ² − 1), the second as
    n ln(σ̂²/σ²). Seen on a blind record of a 382 Hz disturbance on a loop of f₀ = 549 Hz
    (docs/findings.md): `moment_noise` leaves 0.00416 V (9.6× the floor), the discovered
    `forcing_sinusoid` 8.4e-5 V, at the floor."""
    entry = noise_verdict(result)
    discovery = result.discovery
    if entry is None or discovery is None or isinstance(discovery, VibrationDiscovery):
        return
    noise = entry["effect"]
    best = discovery.best
    if best is None or discovery.rating != "credible" or not best.held_out_at_floor:
        found = (
            "nothing" if best is None else f"{' + '.join(best.terms)} ({discovery.rating})"
        )
        result.notes.append(
            f"the discovery weighed against {noise} found {found}, no credible term that "
            f"brings the held-out gap to the floor: {noise} is kept"
        )
        return
    terms = " + ".join(best.terms)
    floor = float(result.remaining_gap.get("noise_floor_V", 0.0))
    left = _free_run_gap(entry, floor)
    if not left > openworld.FLOOR_FACTOR * floor:
        result.notes.append(
            f"the discovered {terms} brings the held-out gap to the floor, and so does "
            f"{noise} ({left:.3g} V against the {floor:.3g} V floor): {noise} is kept"
        )
        return
    result.reason = (
        f"a term outside the library describes the record where {noise} does not: the "
        f"discovered {terms} brings the held-out free-run gap from "
        f"{best.held_out_gap_before_V:.3g} V to {best.held_out_gap_after_V:.3g} V above "
        f"the floor (at the floor), {noise} leaves {left:.3g} V "
        f"({left / floor:.1f}× the {floor:.3g} V floor); the library has no effect for "
        f"the term (its evidence {best.evidence:.1f}, a BIC at the floor; {noise}'s "
        f"{entry['evidence']:.1f}, a likelihood ratio: not on one scale). Before the "
        f"discovery, {noise} was named: {result.reason}"
    )
    result.verdict = "unexplained"
    result.tied = []
    result.explained_fraction = 0.0
    _gap_of_the_nominal(result)
    # (the note that put the noise in question is now the reason's)
    asked = f"{noise} is named, but a predictor"
    result.notes = [note for note in result.notes if not note.startswith(asked)]


def _free_run_gap(entry: dict, floor: float) -> float:
    """A noise's held-out free-run error (its model without the noise's own predictions)
    in excess of the record's noise floor `floor` [V]: what the noise leaves unpredicted,
    on the scale of the discovery's held-out gap. Its ranking's `gap_after_V` is the excess
    over the noise's own fitted variance instead (white + correlated, `assess.assess_fit`),
    and on three blind records of a 261–786 Hz disturbance (measured-input harness records
    809, 815 and 877) `moment_noise` was fitted large enough to make that 0 V while its free
    run missed the held-out part by 1.2–24 mV: the rule kept the noise though the
    discovered sinusoid reached the floor."""
    return openworld.excess(float(entry["held_out_mean_square"]), floor**2)


def _gap_of_the_nominal(result: DiagnosisResult) -> None:
    """The gap blocks of an overturned noise verdict (`weigh_discovery`), in place: no
    library model is kept, so the held-out gap after is the nominal's, as the explained
    fraction 0 says. Before, they still showed the noise's shrink (e.g. 0.79) beside an
    explained fraction of 0 and the verdict `unexplained`; the discovered term's own gaps
    are the discovery's (`result.discovery.best`), a hypothesis, not the diagnosis's."""
    gap = result.gap
    if "before" in gap:
        gap.update(
            after=gap["before"], shrink=0.0, shrink_std=0.0, shrink_p16=0.0, shrink_p84=0.0,
            model_after="nominal",
        )
        for before, after in (("rms_before", "rms_after"),
                              ("one_step_before_rms_V", "one_step_after_rms_V")):
            if before in gap:
                gap[after] = gap[before]
    remaining = result.remaining_gap
    if "before" in gap and remaining:
        floor = float(remaining.get("noise_floor_V", 0.0))
        remaining.update(
            V=gap["before"], model="nominal",
            over_floor=gap["before"] / floor if floor > 0 else float("inf"),
        )
        # (its `where` was read off the noise's free-run error, which is the deterministic
        # part's: the noise predicts nothing in a free run)
    if result.refit.get("parameter_error"):
        result.refit["parameter_error"] = False
