"""In-flight compensation of the basic and vibration errors, eqs. (17)-(20): from the
indicated acceleration and the estimated vibration, the successive estimates â(1)..â(4)
(`compensate_in_flight`, returning `CompensationSteps`), subtracting the paper's closed
forms or the exact expectation.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike

from .._static import StaticTransferFunction, basic_error
from .environment import VibrationEnvironment
from .expectation import vibration_error
from .paper import paper_deterministic_error, paper_random_error


class CompensationSteps(eqx.Module):
    """The estimates of the compensation algorithm (17)-(20) [g].

    **Fields:**

    - `first`: â(1) = (Û/K1 − a0)/(1 + δ), eq. (17).
    - `after_basic`: â(2) = â(1) − δ_OP(â(1)) without a0, eq. (18).
    - `after_deterministic`: â(3) = â(2) − δ_V,D(â(1)), eq. (19).
    - `after_random`: â(4) = â(3) − δ_V,R(â(1)), eq. (20).
    """

    first: Array
    after_basic: Array
    after_deterministic: Array
    after_random: Array


def compensate_in_flight(
    passport: StaticTransferFunction,
    indicated: ArrayLike,
    env_estimate: VibrationEnvironment,
    a1: ArrayLike = 0.0,
    a2: ArrayLike = 0.0,
    *,
    method: str = "paper",
    k5_quartic: float = 1.875,
    n_phase: int = 512,
) -> CompensationSteps:
    """In-flight compensation of the basic and vibration errors, eqs. (17)-(20).

    **Arguments:**

    - `passport`: the unit's passport coefficients (Table 4).
    - `indicated`: the mean indicated acceleration Û/K1 [g] along the input axis.
    - `env_estimate`: the vibration as estimated by the extra piezo sensors (amplitudes
      b̂_i, RMS σ̂_i).
    - `a1`, `a2`: the cross-axis accelerations [g] (from the other two accelerometers).
    - `method`: "paper" subtracts the closed forms (19), (20); "exact" subtracts the exact
      expectation (sine part, then the rest), both evaluated at â(1) as the paper does.
    - `k5_quartic`: see `paper_deterministic_error`.

    **Returns:** `CompensationSteps` [g]. float64 advised (ppm-level corrections).
    """
    if method not in ("paper", "exact"):
        raise ValueError(f"method must be 'paper' or 'exact', got {method!r}.")
    first = (jnp.asarray(indicated) - passport.bias) / (1 + passport.scale_factor_error)
    after_basic = first - basic_error(passport, first, a1, a2, include_bias=False)
    if method == "paper":
        det = paper_deterministic_error(passport, env_estimate, first, k5_quartic=k5_quartic)
        rnd = paper_random_error(passport, env_estimate, first)
    else:
        sine_only = eqx.tree_at(lambda e: e.random_std, env_estimate, jnp.zeros(3))
        det = vibration_error(passport, sine_only, first, a1, a2, n_phase=n_phase)
        rnd = vibration_error(passport, env_estimate, first, a1, a2, n_phase=n_phase) - det
    after_det = after_basic - det
    return CompensationSteps(first, after_basic, after_det, after_det - rnd)
