"""The record that would excite a barely measured term (`discover`'s `excite`).

A term of a discovered subset, or one that a refitted candidate adds to it, whose
coefficient the record measures to less than `WEAK_Z` standard errors (a pickoff square at
small deflections beside its cube) is barely excited. The same record is then taken with
its test steps scaled by s, so that the largest settled deflection voltage reaches
`REACH` of the stops' (k_dp k_y h_max of the nominal device), and the coefficient's
standard error there is computed from the linearised Fisher information: the Jacobian of
the block means with respect to the device's free parameters, the record's nuisances,
the output offset and the subset's coefficients, at the fitted values (the sinusoid's
frequency held), whitened by the record's floor, plus the priors'. The fit's own σ
(the candidates list's) is scaled by the ratio of that standard error at s to the same
computation at s = 1, so that both numbers reported come from one method; the repeats of
the scaled record that would bring the term to `WANTED_Z` follow from the information
growing with the number of records. A first-order statement (the fitted values taken as
the truth), not a simulation of the refit.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..discovery_result import DiscoveryCandidate

WEAK_Z = 3.0
"""|c|/σ below which a term counts as barely excited."""

HINT_Z = 2.0
"""|c|/σ from which a barely excited term is reported: a term measured at less than this
is as likely absent as present (several candidates add one each), and its excitation
would only be noise in the summary."""

MAX_ENTRIES = 2
"""At most this many terms reported, the best measured first."""

REACH = 0.8
"""The scaled record's largest settled deflection voltage, over the stops'."""

WANTED_Z = 5.0
"""|c|/σ the suggested repeats of the scaled record would reach."""


def weak_terms(
    best: DiscoveryCandidate,
    tie: DiscoveryCandidate | None,
    candidates: Sequence[DiscoveryCandidate],
) -> list[tuple[DiscoveryCandidate, int]]:
    """(candidate, column index) of the barely excited columns (HINT_Z ≤ |c|/σ < WEAK_Z,
    at most `MAX_ENTRIES`, the best measured first): in the best subset, its tie, or a
    refitted candidate that adds one term to the best subset."""
    named = set(best.terms)
    pool = [best] + ([tie] if tie is not None else [])
    pool += [
        c for c in candidates
        if named < set(c.terms) and len(c.terms) == len(named) + 1 and c not in pool
    ]
    out = []
    for candidate in pool:
        for i, column in enumerate(candidate.columns):
            sigma = column.sigma
            if sigma > 0 and HINT_Z * sigma <= abs(column.coefficient) < WEAK_Z * sigma:
                out.append((candidate, i))

    def z(item):
        column = item[0].columns[item[1]]
        return abs(column.coefficient) / column.sigma

    return sorted(out, key=z, reverse=True)[:MAX_ENTRIES]


@eqx.filter_jit
def _jacobians(model, p, pick, scales, sigma, amplitude):
    """The Jacobians of the whitened block means (test steps × `amplitude`) and of the
    priors with respect to p = [θ, the used coefficients]."""
    n_free = p.shape[0] - pick.shape[0]

    def blocks(q):
        return model.prediction(q[:n_free], q[n_free:] @ pick, scales, amplitude) / sigma

    return jax.jacfwd(blocks)(p), jax.jacfwd(lambda q: model.penalties(q[:n_free]))(p)


def standard_errors(model, theta, coefficients, pick, scales, sigma, amplitudes):
    """σ of the coefficients (the used rows of `pick`) from the linearised Fisher
    information of the whole record with its test steps × each of `amplitudes`: shape
    (len(amplitudes), k). `model`: the record's model with terms (`term_model.RecordModel`,
    or any equinox module with `prediction(θ, coefficients, scales, amplitude)` [V] and
    `penalties(θ)`), an argument of the one compiled Jacobian, so that records of one
    layout share it."""
    n_free = theta.shape[0]
    p0 = jnp.concatenate([theta, coefficients])
    sigma = jnp.asarray(sigma, p0.dtype)
    out = []
    for amplitude in amplitudes:
        j, jp = (
            np.asarray(v)
            for v in _jacobians(model, p0, pick, scales, sigma, jnp.asarray(amplitude, p0.dtype))
        )
        information = j.T @ j + jp.T @ jp
        try:
            cov = np.linalg.inv(information)
        except np.linalg.LinAlgError:
            out.append(np.full(coefficients.shape, np.inf))
            continue
        out.append(np.sqrt(np.maximum(np.diag(cov)[n_free:], 0.0)))
    return np.stack(out)


class StepScale(NamedTuple):
    """How far the record's steps are scaled to excite a term: `factor` the scale of the
    steps, `deflection_V` [V] the largest deflection it reaches (k_dp k_y h), `stop_V` [V]
    the stops' (`REACH` of it is the aim)."""

    factor: float
    deflection_V: float
    stop_V: float


def entry(
    term: str,
    candidate: DiscoveryCandidate,
    coefficient: float,
    here: float,
    there: float,
    scale: StepScale,
) -> dict:
    """One `excite` entry (JSON-ready) and its summary text."""
    z_here, z_there = abs(coefficient) / here, abs(coefficient) / there
    repeats = max(1, math.ceil((WANTED_Z / z_there) ** 2)) if z_there > 0 else math.inf
    others = [t for t in candidate.terms if t != term.split(" ")[0]]
    beside = f" (beside {', '.join(others)})" if others else ""
    text = (
        f"{term}{beside} barely excited: c = {coefficient:.3g} ± {here:.2g} (z = {z_here:.1f}); "
        f"the same steps ×{scale.factor:.2g} (deflection to {scale.deflection_V:.3g} V, "
        f"{REACH:.0%} of the stops') would measure it to ±{there:.2g} (z ≈ {z_there:.1f})"
    )
    if z_there < WANTED_Z:
        text += f"; {repeats} such records for z ≈ {WANTED_Z:.0f}"
    return {
        "term": term,
        "candidate": list(candidate.terms),
        "coefficient": coefficient,
        "sigma_here": float(here),
        "z_here": float(z_here),
        "step_factor": scale.factor,
        "deflection_V": scale.deflection_V,
        "stop_voltage_V": scale.stop_V,
        "sigma_excited": float(there),
        "z_excited": float(z_there),
        "records_for_z5": repeats,
        "text": text,
    }
