"""The sensor-noise selection's refinements of a selected model.

`_backward`: each effect of the final model judged again against the model without it,
the weakest below the evidence bar removed until every one stands (an effect added early
can lose its evidence once a later one is in). `_exchanges`: each named low-frequency or
exponential-cosine process tried against the other `LOW_FREQUENCY` ones in its place; a
better one by the bar replaces it, one within the bar either way is a tie. Both judge by
`sensor_model`'s evidence and held-out check.
"""

from __future__ import annotations

import dataclasses

from .sensor_model import (
    HELD_OUT_Z,
    PARAMETER_COUNT,
    _evaluate,
    _evaluate_many,
    _evidence,
    _held_out_z,
    _Model,
    _transient_test,
)


def _backward(rec, floor, model: _Model, log_j: float, evidence: float):
    """The backward check of the forward selection: each effect of the final model is
    judged again against the final model without it (a stochastic effect by its Whittle
    2 ln B on the whole record, `_evidence`, the start-up transient by its time-domain test against
    the reduced noise model); the weakest that falls below `evidence` is removed and the
    check repeats. An effect added early can lose its evidence once a later one is in: a
    random walk taken for the low-frequency power of a start-up transient, or a transient
    seen in the start of a record whose wandering level was not yet modelled.

    Returns (model, removed: [{"effect", "evidence"}])."""
    removed = []
    while True:
        weakest = None
        specs = []
        for name in model.names:
            names = tuple(n for n in model.names if n != name)
            parent = dataclasses.replace(model, names=names)
            specs.append((names, model.lines, model.transient, parent))
        for name, reduced in zip(model.names, _evaluate_many(rec, floor, specs), strict=True):
            score = _evidence(model, reduced, PARAMETER_COUNT[name], log_j)
            if weakest is None or score < weakest[0]:
                weakest = (score, name, reduced)
        if model.transient is not None:
            r = rec.residual(model.lines, None)
            found = _transient_test(r[: rec.split], rec.dt, model, floor)
            score = found["evidence"] - PARAMETER_COUNT["startup_transient"] * log_j
            if weakest is None or score < weakest[0]:
                reduced = _evaluate(rec, floor, model.names, model.lines, None, model)
                weakest = (score, "startup_transient", reduced)
        if weakest is None or weakest[0] >= evidence:
            return model, removed
        removed.append({"effect": weakest[1], "evidence": float(weakest[0])})
        model = weakest[2]


LOW_FREQUENCY = ("gauss_markov", "random_walk", "flicker")
"""The effects that put their power at the lowest frequencies: on a record a few of their
time scales long, one can stand in for another."""


EXCHANGED = (*LOW_FREQUENCY, "exp_cosine")
"""The named effects the exchange tries the `LOW_FREQUENCY` ones in place of: an
exponential-cosine process too can stand in for a low-frequency one (its oscillation
frequency fitted near 0 it is a Gauss–Markov process; harness record 166663425, flicker
with a line, took it first, before the line was in and while the line's power favoured a
peaked spectrum, and kept it)."""


def _exchanges(rec, floor, model: _Model, log_j: float, evidence: float):
    """Each named effect of `EXCHANGED` against each unnamed `LOW_FREQUENCY` one in its
    place (the rest of the model kept, the substitute's fit started from the model's
    optimum): 2 ln B of the named effect over the substitute, 2 Δ ln L − (k − k') ln J on
    the whole record as in the forward selection. A substitute that beats the named effect by `evidence` or
    more replaces it (the forward path added the first that stood, not the best: a random
    walk with a start-up transient can look like flicker until the transient is in), and
    the exchange repeats; one within `evidence` either way is reported as a tie: the
    record cannot tell the two apart.

    Returns (model, exchanged: [{"effect", "by", "evidence"}], ties: [{"effect",
    "alternative", "evidence"}])."""
    exchanged, ties = [], []  # (ties: rebound by every pass)
    for _ in range(len(EXCHANGED) + 1):
        ties, best = [], None
        pairs, specs = [], []
        for name in model.names:
            if name not in EXCHANGED:
                continue
            rest = tuple(n for n in model.names if n != name)
            for other in LOW_FREQUENCY:
                if other in model.names:
                    continue
                names = tuple(other if n == name else n for n in model.names)
                parent = dataclasses.replace(model, names=rest)
                pairs.append((name, other, parent))
                specs.append((names, model.lines, model.transient, parent))
        for (name, other, parent), alt in zip(
            pairs, _evaluate_many(rec, floor, specs), strict=True
        ):
            score = (
                2 * ((model.train + model.held) - (alt.train + alt.held))
                - (PARAMETER_COUNT[name] - PARAMETER_COUNT[other]) * log_j
            )
            if score <= -evidence and _held_out_z(alt, parent) >= -HELD_OUT_Z:
                if best is None or score < best[0]:
                    best = (score, alt, name, other)
            elif score < evidence:
                ties.append(
                    {
                        "effect": name,
                        "alternative": other,
                        "evidence": float(score),
                        "bar": float(evidence),
                    }
                )
        if best is None:
            return model, exchanged, ties
        score, model, name, other = best
        exchanged.append({"effect": name, "by": other, "evidence": float(-score)})
    ties = [t for t in ties if t["effect"] in model.names and t["alternative"] not in model.names]
    return model, exchanged, ties
