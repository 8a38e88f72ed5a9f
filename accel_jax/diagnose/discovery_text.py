"""The summary's "discovered (hypothesis)" block of a step record's discovery
(`step.discover`; the network reference's line, `step.ceiling`) or a vibration table's
(`vibration.discover`): presentation only, from the typed `Discovery` or
`VibrationDiscovery` (`discovery_result`)."""

from __future__ import annotations

from .discovery_result import (
    Discovery,
    DiscoveryCandidate,
    VibrationCandidate,
    VibrationDiscovery,
)


def discovery_lines(discovery: Discovery | VibrationDiscovery | None) -> list[str]:
    """The summary's "discovered (hypothesis)" block (`step.discover`,
    `vibration.discover`); none without one."""
    if discovery is None:
        return []
    if isinstance(discovery, VibrationDiscovery):
        return _vibration_lines(discovery)
    best = discovery.best
    reference = discovery.ceiling
    reached = []
    if reference is not None:
        reached = [
            f"   a network of the loop's states ({reference.parameters} weights, an "
            f"estimate, not a bound) removes {reference.explained_fraction:.0%} of the "
            "held-out gap"
            + (
                f"; the term reaches {best.ceiling_fraction:.0%} of that"
                if best is not None and best.ceiling_fraction is not None
                else ""
            )
            + (
                " (the held-out part holds test levels outside the training part's: the "
                "network is extrapolated there, a term of fixed form need not be)"
                if reference.extrapolates
                else ""
            )
        ]
    if best is None:
        return ["discovered (hypothesis): nothing found in the term library"] + reached

    def term_text(d: DiscoveryCandidate) -> str:
        # A σ whose profile interval was not found on both sides (`profile`: a refit
        # failed, or the sides' refits ran out) is not the interval's: said beside it.
        parts = [
            f"{col.term} at the {col.place} ({col.formula}), "
            f"c = {col.coefficient:.3g} ± {col.sigma:.2g}"
            + (" (profile interval not found: σ uncertain)" if col.profile_found is False else "")
            for col in d.columns
        ]
        return " + ".join(parts)

    lines = [
        f"discovered (hypothesis, {discovery.rating}): {term_text(best)}",
        f"   held-out gap {best.held_out_gap_before_V:.3g} → "
        f"{best.held_out_gap_after_V:.3g} V above the floor "
        f"({best.explained_fraction:.0%} explained), evidence {best.evidence:.1f}, "
        f"stable in {best.stability:.0%} of resamples",
    ]
    lines += reached
    lines += [f"   for a designer: {c['text']}" for c in best.consequence or ()]
    lines += [f"   to excite it: {e['text']}" for e in discovery.excite or ()]
    tie = discovery.tie
    if tie is not None:
        lines.append(
            f"   cannot tell it from: {term_text(tie)} (evidence {tie.evidence:.1f})"
        )
    return lines


def _vibration_terms(d: VibrationCandidate) -> str:
    return " + ".join(
        f"{c.formula} ({c.term} = {c.coefficient:.3g} ± {c.sigma:.2g} {c.unit}"
        + ("" if c.library is None else ", a library coefficient")
        + f"; at {c.condition}: {c.rectified_ug:.3g} µg)"
        for c in d.columns
    )


def _vibration_lines(discovery: VibrationDiscovery) -> list[str]:
    best = discovery.best
    if best is None:
        return [
            "discovered (hypothesis): nothing found in the term library "
            f"({len(discovery.searched)} terms the table can show)"
        ]
    if best.at_floor is None:
        floor = "the table repeats no condition: whether it reaches the noise floor is untested"
    else:
        floor = (
            f"{'at' if best.at_floor else 'not at'} the floor of the repeated conditions "
            f"(lack of fit p = {best.lack_of_fit_p:.2g})"
        )
    lines = [
        f"discovered (hypothesis, {discovery.rating}): {_vibration_terms(best)}",
        f"   cross-validated gap {best.cv_gap_before_g:.3g} → {best.cv_gap_after_g:.3g} g "
        f"above the floor ({best.explained_fraction:.0%} explained), evidence "
        f"{best.evidence:.1f}, stable in {best.stability:.0%} of resamples; {floor}",
    ]
    if discovery.tie is not None:
        lines.append(
            f"   cannot tell it from: {_vibration_terms(discovery.tie)} (evidence "
            f"{discovery.tie.evidence:.1f})"
        )
        if discovery.separate:
            lines.append(f"   to separate them: {discovery.separate}")
    if discovery.overturned:
        lines.append(f"   before the discovery the verdict was {discovery.overturned}")
    return lines
