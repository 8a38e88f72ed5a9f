"""Profile-likelihood intervals of a discovered term's coefficients (`discover`).

The linearised standard error of a coefficient (the inverse of JᵀJ at the optimum) can be
wrong by an order of magnitude when the model is strongly nonlinear along the direction in
which the coefficient trades off against the device's parameters and the record's
nuisances. On the unit tests' pickoff record the pair pickoff square + cube has a
linearised σ of 0.085 for the square (c = 0.056) while the misfit, refitted with the square
held 0.1 σ off its optimum, already rises by Δχ² ≈ 2 (the Gauss–Newton prediction: 0.01);
the Jacobian there agrees with central differences to 2e-5, so the linearisation itself,
not its arithmetic, fails. The profile is the honest measure: the coefficient held at v,
everything else refitted, Δχ²(v) = χ²(v) − χ²(ĉ).

`interval` finds, on each side of ĉ, the v where Δχ²(v) reaches `level` (1 scaled by
max(1, χ²/dof): a 68 % interval under Wilks's theorem, widened by a misfit of the model's
form as the linearised σ is). Near the optimum √Δχ² grows linearly in |v − ĉ|, so the root
is found by the secant method on √Δχ² − √level, started from a probe at a small fraction
of the linearised σ (which may be far too wide or too narrow), in a handful of refits per
side.

Each refit starts from the converged refit of the nearest value held so far on its side
(continuation), not from the optimum. From the optimum, MINPACK can stop in a false minimum
far above the profile. On the independent simulator's pickoff record of the discovery
benchmark (seed 2045), one coefficient of a two-term subset, held 0.318 σ_lin below its
estimate: from the optimum the refit ended (converged by MINPACK's test) at Δχ² = 8.8e5
after 43 evaluations; continued from the refit at 0.2 σ_lin it reached Δχ² = 0.12 in 6
evaluations. The secant then met those false minima as a cliff and crawled towards the near
probe (about 1/400 of the way a refit), so the side ended 0.1 σ_lin from ĉ, many times
narrower than the profile. Such a cliff may also be real (a term held where the loop runs
away): a far probe whose √Δχ² exceeds `CLIFF` times the straight line's prediction through
the optimum and the near probe makes the next probe bisect the bracket, not take the
secant. A refit stops after `MAX_EVALUATIONS` (one from the optimum had run MINPACK's 200,
31 s of the record's 179 s discovery, to Δχ² = 8e6); a capped refit's Δχ² is an upper
bound. Only converged refits whose Δχ² is below `CLIFF`² times the level are continued
from: a false minimum is MINPACK-converged too, and one continued from led the next
refits astray; a refit just beyond the level (Δχ² = 1.38 at −0.97 σ_lin) is a good start
for the secant's next probe (0.97 at −0.83 σ_lin, where from the near probe's refit a
false minimum at 5e6 was reached).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import jax.numpy as jnp
import numpy as np

from ..._runtime import thread_map

PROBE = 0.1
"""The first probe's distance from ĉ, in linearised σ."""

MAX_REFITS = 4
"""Refits per side at most (the probe included)."""

TOLERANCE = 0.1
"""A side is found when Δχ² is within this fraction of the level."""

CLIFF = 3.0
"""A far probe whose √Δχ² is above this many times the straight line's (through the
optimum and the near probe) is a cliff: the bracket is bisected, not cut by the secant."""

MAX_EVALUATIONS = 60
"""MINPACK's residual evaluations per profile refit at most (the discovery's refits keep
`minpack.MAX_EVALUATIONS`)."""

FTOL = 1e-6
"""The profile refits' relative tolerance on the sum of squares (MINPACK's `ftol`; the
discovery's other refits keep `minpack.FTOL`). A refit stops once the predicted and actual
relative reductions of χ² are below it, so its χ² is within about FTOL·χ² of its minimum:
on a record of 10⁴ blocks 0.01, ten times below what the secant needs (`TOLERANCE` × the
level ≥ 0.1). Measured on the unit tests' 1300 Hz forcing record (`discover="all"`,
eleven intervals): the same ends to 2e-6 of their σ, 145 Jacobians instead of 209
and the discovery 21 s faster warm (138.4 → 117.4 s with the diagnosis)."""


@dataclasses.dataclass(frozen=True)
class ProfileInterval:
    """The profile interval of one coefficient: `lower`, `upper` (Δχ² = `level` on each
    side, as found), `sigma` (their mean half-width), `refits` (the profile refits it
    took), `found` (both sides within `TOLERANCE` of the level)."""

    lower: float
    upper: float
    sigma: float
    refits: int
    found: bool


def interval(
    delta_chi2: Callable[[float], float],
    estimate: float,
    sigma_linearised: float,
    level: float = 1.0,
) -> ProfileInterval:
    """The profile interval of a coefficient whose estimate is `estimate`.

    **Arguments:** `delta_chi2(v)`: the refitted χ² with the coefficient held at v, minus
    the optimum's (≥ 0 up to the solver's tolerance); `sigma_linearised`: the linearised
    standard error (the first probe's scale); `level`: Δχ² that bounds the interval.

    **Returns:** a `ProfileInterval`. A side not found within `MAX_REFITS` refits takes
    the last secant (or extrapolated) estimate, and `found` is False; so does a side whose
    refit gives a non-finite Δχ² (its end: the bracket beyond the level, else the farthest
    probe below it or the first probe; never NaN).
    """
    return _joined([
        _side(delta_chi2, estimate, sigma_linearised, level, side) for side in (-1.0, 1.0)
    ])


def _side(delta_chi2, estimate, sigma_linearised, level, side) -> tuple[float, int, bool]:
    """One side (`side` −1 or +1) of `interval`: its end, its refits, whether found."""
    if not (sigma_linearised > 0 and math.isfinite(sigma_linearised)):
        raise ValueError(f"the linearised σ must be positive and finite, not {sigma_linearised}")
    target = math.sqrt(level)
    # (distance, √Δχ²) pairs: the optimum itself is (0, 0).
    near, far = (0.0, 0.0), None
    x = PROBE * sigma_linearised
    value = 0.0
    refits, found = 0, True
    for _ in range(MAX_REFITS):
        delta = delta_chi2(estimate + side * x)
        refits += 1
        if not math.isfinite(delta):  # a failed refit: this side is not found
            x = far[0] if far is not None else max(near[0], PROBE * sigma_linearised)
            found = False
            break
        value = math.sqrt(max(delta, 0.0))
        if abs(value**2 / level - 1.0) <= TOLERANCE:
            break
        if value < target:
            near = (x, value)
        else:
            far = (x, value)
        if far is None:
            # Not bracketed yet: extrapolate the line through the optimum and the
            # nearest probe (at most ×10 per step, so a flat start cannot jump away).
            slope = (near[1] - 0.0) / near[0] if near[0] > 0 else 0.0
            x = min(target / slope, 10 * x) if slope > 0 else 10 * x
        else:
            (x0, y0), (x1, y1) = near, far
            line = y0 / x0 * x1 if x0 > 0 else 0.0  # the far probe's √Δχ² on a line
            if line > 0 and y1 > CLIFF * line:
                x = 0.5 * (x0 + x1)
            else:
                x = x0 + (target - y0) * (x1 - x0) / (y1 - y0)
    else:
        found = False
    return estimate + side * x, refits, found


def _joined(sides) -> ProfileInterval:
    """The `ProfileInterval` of a lower and an upper `_side`."""
    (lower, low_refits, low_found), (upper, up_refits, up_found) = sides
    return ProfileInterval(
        lower=lower, upper=upper, sigma=0.5 * (upper - lower),
        refits=low_refits + up_refits, found=low_found and up_found,
    )


def column_intervals(
    solve, residuals_at, jacobian_at, params, args, n_free, n_cols, sigmas, level, ftol=FTOL
):
    """`interval` of each of a refitted subset's `n_cols` coefficients.

    **Arguments:** `solve(fun, jac, x0, args, ftol=, max_evaluations=)` (`minpack.solve`);
    `residuals_at(params, (pick, used, tone, fixed))` and its Jacobian: the discovery's
    whitened training residuals, priors and pins, with the coefficients entering as
    `c @ pick + fixed`;
    `params` the subset's optimum (`n_free` device and nuisance entries, then the
    coefficients); `args` its `(pick, used, tone)`; `sigmas` the linearised σ; `level`
    the Δχ² bound; `ftol` the refits' tolerance (`FTOL`).

    A coefficient is held at v by taking its row out of `pick` (its entry pinned at 0,
    where the pin costs nothing) and adding v times that row to `fixed`; every other
    parameter is refitted, from the converged refit of the nearest value held so far on
    the same side of the estimate whose Δχ² is below `CLIFF`² times `level` (the optimum
    itself first): continuation along the profile, without which a refit can stop in a
    false minimum far above it (module docstring). The two sides of every coefficient are
    independent searches, run side by side on the process's cores (`thread_map`; the same
    intervals as one after the other).
    """
    pick, used, tone = (np.asarray(a, dtype=np.float64) for a in args)
    params = np.asarray(params, dtype=np.float64)
    fixed0 = np.zeros(pick.shape[1])
    optimum = np.asarray(residuals_at(jnp.asarray(params), _args(pick, used, tone, fixed0)))
    cost = float(optimum @ optimum)

    def side_of(task):
        i, side = task
        held_pick, held_used = pick.copy(), used.copy()
        held_pick[i], held_used[i] = 0.0, 0.0
        estimate = float(params[n_free + i])
        start = params.copy()
        start[n_free + i] = 0.0
        solved = [(estimate, start)]  # (value held, its converged refit), the optimum first

        def delta(v):
            x0 = min(solved, key=lambda item: abs(item[0] - v))[1]
            held = _args(held_pick, held_used, tone, v * pick[i])
            refit = solve(
                residuals_at, jacobian_at, x0, held, ftol=ftol, max_evaluations=MAX_EVALUATIONS
            )
            value = 2.0 * float(refit.cost) - cost
            if refit.status > 0 and value < CLIFF**2 * level:  # no false minimum
                solved.append((v, np.asarray(refit.x, dtype=np.float64)))
            return value

        return _side(delta, estimate, float(sigmas[i]), level, side)

    # Each side of each coefficient continues only from its own refits: the sides are
    # independent, and run side by side on the process's cores.
    sides = thread_map(side_of, [(i, side) for i in range(n_cols) for side in (-1.0, 1.0)])
    return [_joined(sides[2 * i : 2 * i + 2]) for i in range(n_cols)]


def _args(pick, used, tone, fixed):
    return tuple(jnp.asarray(a) for a in (pick, used, tone, fixed))
