"""MINPACK's Levenberg–Marquardt through SciPy on a compiled JAX residual and Jacobian,
the solver of the discovery's refits (`discover`) and of the network reference
(`ceiling`). Float64."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from scipy.optimize import least_squares

MAX_EVALUATIONS = 200
FTOL = 1e-10
"""MINPACK's relative tolerance on the sum of squares, unless a caller asks otherwise."""


def solve(fun, jac, x0, args, max_evaluations: int = MAX_EVALUATIONS, ftol: float = FTOL):
    """MINPACK's Levenberg–Marquardt (SciPy) on a compiled residual and Jacobian: its
    scaling by the Jacobian's column norms converges in tens of evaluations where the
    terms' coefficients and the nominal parameters differ in scale by 10⁴ (optimistix's
    unscaled Levenberg–Marquardt needed hundreds of steps here)."""
    return least_squares(
        lambda p: np.asarray(fun(jnp.asarray(p), args)),
        np.asarray(x0, dtype=np.float64),
        jac=lambda p: np.asarray(jac(jnp.asarray(p), args)),  # pyright: ignore[reportArgumentType]  # SciPy's stubs take a callable too
        method="lm",
        xtol=1e-10,
        ftol=ftol,
        max_nfev=max_evaluations,
    )
