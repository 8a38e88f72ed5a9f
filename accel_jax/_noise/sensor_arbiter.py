"""The time-domain arbiter between a wandering level and a returning bias with a start-up
transient.

A start-up transient in the first minutes of a record and a slow noise process beside it
can be read two ways: a random walk (or flicker) whose wander covers the decay, or a
Gauss–Markov process, which returns to its mean, with the transient on top. The Whittle
likelihood cannot weigh the two: its taper gives the start of the record, where the
transient lies, almost no weight; and the transient's own time-domain test is judged
against one noise model at a time, under a walk that absorbs it. Once the selection's
backward check has dropped a transient, the arbiter weighs the final model's walk or
flicker u against a Gauss–Markov process s in its place with a transient, in one
likelihood: the exact Gaussian likelihood of the differenced block means of the training
part (at most `ARBITER_BLOCKS` of them; the autocovariance and the Durbin–Levinson
recursion of the transient test, the level's drift profiled), each model's parameters of
u or s maximised in it (Nelder–Mead from the Whittle fit; the white noise and any other
effect as selected), the transient's amplitude profiled and its τ the best of the
transient test's grid. 2 ln B of u over the alternative is 2 Δ ln L − (k_u − k_s −
k_transient) ln n, n the block differences (the Bayesian information criterion of this
likelihood); within the selection's bar, or below it, the alternative is reported as a tie.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy import optimize

from . import spectral
from .sensor_model import (
    PARAMETER_COUNT,
    _differenced_autocovariance,
    _differenced_block_means,
    _drift_profiled,
    _evaluate,
    _innovations,
    _Model,
    _transient_grid,
    _transient_templates,
    _transient_test,
)

ARBITER_BLOCKS = 512
"""The most differenced block means the arbiter's likelihood takes (the training part
split into ARBITER_BLOCKS + 1 blocks: 0.85 s blocks on 650 s at 200 Hz)."""

WANDERING = ("random_walk", "flicker")
"""The named effects the arbiter weighs: a level that wanders and does not return."""

REVERTING = ("gauss_markov",)
"""What it weighs them against, with a start-up transient: a bias that returns to its mean
(the reverse, a walk with a transient in place of a named Gauss–Markov process, put a
decay into records that have none: 1 of 4 Gauss–Markov records of 200 s at 200 Hz)."""

ARBITER_EVALUATIONS = 150
"""Nelder–Mead's likelihood evaluations per model at most."""

def _block_differences(r: np.ndarray) -> tuple[np.ndarray, int]:
    """The differenced means of blocks of m samples of r, at most `ARBITER_BLOCKS`; m."""
    m = max(1, -(-r.size // (ARBITER_BLOCKS + 1)))
    return _differenced_block_means(r, m, r.size // m), m


def _two_log_likelihood(y, m, model: _Model, floor: float, templates) -> float:
    """2 ln L (less its constant) of the differenced block means y under `model`'s noise,
    the level's drift profiled; with `templates` (columns), the best transient's 2 ln Λ
    added (its amplitude profiled)."""
    gamma = _differenced_autocovariance(model, floor, y.size, m)
    columns = [y[:, None], np.ones((y.size, 1))]
    if templates is not None:
        columns.append(templates)
    e, d = _innovations(gamma, np.concatenate(columns, axis=1))
    if e.shape[0] < y.size:  # the autocovariance not positive definite: no likelihood
        return -math.inf
    quad, _, _, z2 = _drift_profiled((e / d[:, None]).T @ e)
    two = -(quad + float(np.sum(np.log(d))))
    if templates is not None:
        two += float(np.max(z2))
    return float(two) if math.isfinite(two) else -math.inf


def _maximised(y, m, model: _Model, floor: float, name: str, templates) -> float:
    """The largest 2 ln L over the slots of `name` in `model`'s parameters (Nelder–Mead
    from the model's own)."""
    slots = list(spectral.SLOTS[name])
    z0 = np.asarray(model.z, np.float64)

    def cost(p):
        z = z0.copy()
        z[slots] = p
        value = _two_log_likelihood(y, m, dataclasses.replace(model, z=z), floor, templates)
        return -value if math.isfinite(value) else 1e300

    found = optimize.minimize(
        cost,
        z0[slots],
        method="Nelder-Mead",
        options={"maxfev": ARBITER_EVALUATIONS, "xatol": 1e-2, "fatol": 0.05},
    )
    return -float(found.fun)  # (the start is a vertex of the first simplex: never worse)


def transient_ties(rec, floor, model: _Model, evidence: float, removed: list) -> list:
    """Where the selection's backward check dropped a start-up transient (`removed`, its
    `{"effect", …}` entries) and `model`, the final one, has none: each low-frequency
    effect u of `model` weighed against each other low-frequency effect s with a start-up
    transient, in the arbiter's likelihood (module docstring).

    Returns [{"effect": u, "alternative": "s+startup_transient", "evidence": 2 ln B of u
    over the alternative, "bar": evidence, "judged_by": "time_domain"}] for each
    alternative within `evidence` of u or better (an alternative better by more than the
    bar is listed too: the spectral steps kept u, this likelihood prefers it)."""
    dropped = any(e["effect"] == "startup_transient" for e in removed)
    if model.transient is not None or not dropped:
        return []
    r = rec.residual(model.lines, None)[: rec.split]
    y, m = _block_differences(r)
    taus = _transient_grid(r.size, rec.dt, m)
    templates = _transient_templates(y.size, m, rec.dt, taus)
    log_n = math.log(y.size)
    ties = []
    for name in model.names:
        if name not in WANDERING:
            continue
        named = _maximised(y, m, model, floor, name, None)
        for other in REVERTING:
            if other in model.names:
                continue
            names = tuple(other if n == name else n for n in model.names)
            start = _evaluate(rec, floor, names, model.lines, None, model)
            transient = _transient_test(r, rec.dt, start, floor)["transient"]
            alt = _evaluate(rec, floor, names, model.lines, transient, start)
            value = _maximised(y, m, alt, floor, other, templates)
            k = PARAMETER_COUNT[other] + PARAMETER_COUNT["startup_transient"]
            score = named - value - (PARAMETER_COUNT[name] - k) * log_n
            if math.isfinite(score) and score < evidence:
                ties.append(
                    {
                        "effect": name,
                        "alternative": f"{other}+startup_transient",
                        "evidence": float(score),
                        "bar": float(evidence),
                        "judged_by": "time_domain",
                    }
                )
    return ties
