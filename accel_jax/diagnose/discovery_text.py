"""The summary's "discovered (hypothesis)" block of a step record's discovery
(`step.discover`; the network reference's line, `step.ceiling`): presentation only, from
the typed `Discovery` (`discovery_result`)."""

from __future__ import annotations

from .discovery_result import Discovery, DiscoveryCandidate


def discovery_lines(discovery: Discovery | None) -> list[str]:
    """The summary's "discovered (hypothesis)" block (`step.discover`); none without one."""
    if discovery is None:
        return []
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
        parts = [
            f"{col.term} at the {col.place} ({col.formula}), "
            f"c = {col.coefficient:.3g} ± {col.sigma:.2g}"
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
