"""The vibration diagnosis's fit: every candidate on all rows and on every cross-validation
fold, by optimistix least squares on the linear model a_out − a_in = J θ (`fit_table`),
vmapped over the tables of one size (`fit_tables`)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import optimistix as optx

FIT_TOLERANCE = 1e-10
"""rtol = atol of the least-squares fits (ppm-scaled coefficients and residuals)."""


def fit_table(design, target, masks, weights):
    """Least squares of every candidate (rows of `masks`: 1 where a coefficient is free)
    on every row subset (rows of `weights`: 1 where a row is fitted), vmapped. Coefficients
    that are not free are pinned at 0 by extra residuals; a_out − a_in = J θ (ppm)."""

    def fit_one(mask, weight):
        def residuals(theta, _):
            data = weight * (design @ (mask * theta) - target)
            return jnp.concatenate([data, (1 - mask) * theta])

        # Gauss–Newton with an SVD solve: the problem is linear, so the first step lands on
        # the least-squares solution and the second confirms it; the SVD keeps a fold whose
        # training rows cannot determine a coefficient finite (minimum-norm solution).
        solver = optx.GaussNewton(rtol=FIT_TOLERANCE, atol=FIT_TOLERANCE, linear_solver=lx.SVD())
        solution = optx.least_squares(
            residuals, solver, jnp.zeros(design.shape[1]), max_steps=16, throw=False
        )
        theta = mask * solution.value
        return theta, solution.result == optx.RESULTS.successful

    per_fold = jax.vmap(fit_one, in_axes=(None, 0))
    return jax.vmap(per_fold, in_axes=(0, None))(masks, weights)


fit_tables = eqx.filter_jit(jax.vmap(fit_table))
"""`fit_table` of a batch of tables of one size and one set of candidates (one compilation)."""
