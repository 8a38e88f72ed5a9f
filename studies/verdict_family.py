"""Verdicts that name one family of effects, for the blind studies' scoring (one definition:
`sim_to_real_validation`, `measured_input_harness` and `contact_harness` read it).

The inelastic stop (`stop_saturation`: the velocity lost at contact) is the stiff, damped
limit of the compliant stops (`stop_contact`): a clamp truth named `stop_contact` is
named, and two twins that name one and the other agree."""

from __future__ import annotations

MEMBER_OF = {"stop_contact": "stop_saturation"}
"""Each verdict that belongs to another's family, mapped to that family's name."""


def family(verdict):
    """The family a verdict names (itself when it has none; None stays None)."""
    return MEMBER_OF.get(verdict, verdict)
