"""The network reference of what a state-dependent term could achieve (issue 45, item 3):
a small equinox network f(v, w, m, g·U) of the loop's scaled states (`terms`: v the
deflection as the amplifier voltage, w = T v̇, the torquer moment m, the test drive g·U),
added as a residual moment on the pendulum and a residual at the output, fitted under the
record's nuisances as a discovered term is (`discover`), and its held-out gap measured the
same way.

Its fit is non-convex (`STARTS` starts, the best kept), so the shrink it reaches is an
estimate of what a term of the states could remove, not a bound; it is never a verdict.
What it cannot stand for: a term of time (a forcing) or a new state (an extra pole), which
a function of the present states reaches only in part, so a discovered term can exceed it.

At its start the network's last layer is zero, so the nominal model is nested exactly. Its
weights have a standard normal prior (inputs and outputs in units of the training output's
half range h), which is what keeps a fit of `size()` parameters from following the
training part's noise. Float64 (the structure is built at call time, in the precision
then in force).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from .. import openworld
from ..discovery_result import NetworkReference
from .minpack import solve
from .state import StepRecord
from .terms import N_COEFFICIENTS

WIDTH = 16
"""Hidden units (one tanh layer). On a pickoff-nonlinearity record whose held-out levels
lie inside the training part's, widths 8, 16 and 32 removed 58, 78 and 82 % of the
held-out excess in 74, 67 and 117 s of fitting: 16 is where the gain flattens."""

STARTS = 2
"""Random starts of the hidden layer (fixed keys); the fit with the lowest cost is kept."""

PRIOR = 1.0
"""Standard deviation of each weight's normal prior."""

INPUTS = 4
OUTPUTS = 2  # a moment [V of M/k_dm] and an output [V], both in units of h


def _network(key) -> eqx.nn.MLP:
    mlp = eqx.nn.MLP(
        INPUTS, OUTPUTS, WIDTH, 1, activation=jnp.tanh, dtype=jnp.zeros(()).dtype, key=key
    )
    last = mlp.layers[-1]
    return eqx.tree_at(
        lambda m: (m.layers[-1].weight, m.layers[-1].bias),
        mlp,
        (jnp.zeros_like(last.weight), jnp.zeros(OUTPUTS, last.weight.dtype)),
    )


def starts() -> list[jax.Array]:
    """The flat parameter vectors the fit starts from: each network's output zero."""
    out = []
    for seed in range(STARTS):
        params, _ = eqx.partition(_network(jax.random.PRNGKey(seed)), eqx.is_array)
        out.append(ravel_pytree(params)[0])
    return out


def size() -> int:
    """The number of the network's parameters."""
    return int(starts()[0].size)


def residual(flat: jax.Array, half):
    """The residual (moment, output) [V] of the states (v, w, m, g·U) [V] for the network
    with flat parameters `flat`, its inputs and outputs in units of `half`."""
    params, static = eqx.partition(_network(jax.random.PRNGKey(0)), eqx.is_array)
    mlp = eqx.combine(ravel_pytree(params)[1](flat), static)

    def f(v, w, torque, drive):
        out = mlp(jnp.stack([v, w, torque, drive]) / half)
        return half * out[0], half * out[1]

    return f


REFERENCE_MAX_EVALUATIONS = 400
"""The network fit's evaluations at most, per start (it has ~60 more parameters than a
term's refit)."""


def outside_training(rec: StepRecord, unpacked, theta) -> bool:
    """Whether the held-out part holds test levels (g·U, block by block) outside the
    range of the training part's by more than 5 % of that range: a function of the states
    fitted on the training part is extrapolated there."""
    model = unpacked(theta)
    levels = float(rec.ctx.first_level) + np.concatenate([[0.0], np.cumsum(model.step)])
    first_samples = np.arange(len(rec.u_out)) * int(rec.block)
    index = np.searchsorted(np.asarray(rec.ctx.change_index), first_samples, side="right")
    drive = float(model.gain) * levels[index]
    n = len(rec.u_out)
    train = np.asarray(rec.ctx.train)[:n] > 0
    test = np.asarray(rec.ctx.test)[:n] > 0
    if not (train.any() and test.any()):
        return False
    low, high = drive[train].min(), drive[train].max()
    margin = 0.05 * max(high - low, 1e-12)
    return bool(drive[test].min() < low - margin or drive[test].max() > high + margin)


def fit_reference(
    residuals, jacobian, held_out_error, theta0, scales, record, sigma, *, extrapolates: bool
) -> NetworkReference:
    """The discovery's `ceiling`: the network fitted on the training part with the device
    and the record's nuisances from `theta0` (the nominal fit), then its held-out gap with
    the held-out part's nuisances refitted (`held_out_error`), as for a term.
    `residuals(params)` and `jacobian(params)`: the training residuals (whitened, then the
    priors', the network's weights' last) at params = [θ, the network's flat weights] and
    their Jacobian — `term_model.network_at` and `network_jacobian_at` on the record's
    model, compiled once per record layout; `record`: (the held-out rows, the gap before,
    the nominal cost); `sigma` [V] the floor; `extrapolates`: whether the held-out part
    leaves the training part's levels (`outside_training`)."""
    test_rows, gap_before, cost0 = record
    n_free = theta0.size
    zero = jnp.zeros(N_COEFFICIENTS)
    solution = min(
        (
            solve(
                lambda p, _: residuals(p), lambda p, _: jacobian(p), np.r_[theta0, flat],
                None, REFERENCE_MAX_EVALUATIONS,
            )
            for flat in starts()
        ),
        key=lambda sol: sol.cost,
    )
    theta, flat = jnp.asarray(solution.x[:n_free]), jnp.asarray(solution.x[n_free:])
    fitted = np.asarray(residuals(jnp.asarray(solution.x)))[: -flat.size]  # the prior's apart
    error = np.asarray(held_out_error(theta, zero, scales, network=flat))
    gap_after = openworld.excess(float(np.mean(error[test_rows] ** 2)), sigma**2)
    return NetworkReference(
        method=(
            f"a network of the states (v, w, m, g·U) → (moment, output), one tanh layer of "
            f"{WIDTH}, {flat.size} weights under a standard normal prior, fitted with "
            f"the device and the record's nuisances (best of {STARTS} starts): an "
            "estimate of what a term of the states could remove, not a bound, never a verdict"
        ),
        parameters=int(flat.size),
        delta_chi2_train=float(cost0 - np.sum(fitted**2)),
        held_out_gap_before_V=gap_before,
        held_out_gap_after_V=gap_after,
        explained_fraction=openworld.explained_fraction(gap_before, gap_after),
        converged=bool(solution.status > 0),
        extrapolates=extrapolates,
    )
