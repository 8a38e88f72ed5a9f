"""The shaker-test estimator of the vibration error, eq. (16): the mean output during
vibration against the mean of the outputs before and after it, with the paper's
axis-stability check (`shaker_vibration_error`, returning a `ShakerEstimate`).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike

from .._params import _concrete


class ShakerEstimate(eqx.Module):
    """Result of the shaker-test estimator (16).

    **Fields:**

    - `vibration_error`: δ̂_V = (U2 − ½(U1 + U3))/K1 [g].
    - `axis_shift`: |U1 − U3|/K1 [g at 1 g, i.e. rad for a small tilt about the
      horizontal], the paper's axis-stability statistic.
    - `valid`: axis_shift ≤ the tolerance (the paper's 1e-4 rad).
    """

    vibration_error: Array
    axis_shift: Array
    valid: Array


def shaker_vibration_error(
    u_before: ArrayLike,
    u_during: ArrayLike,
    u_after: ArrayLike,
    scale_factor: ArrayLike,
    *,
    axis_tolerance: float = 1e-4,
) -> ShakerEstimate:
    """The shaker estimator (16) with its axis-stability check.

    **Arguments:**

    - `u_before`, `u_during`, `u_after`: output records [V] (any length; their means U1, U2,
      U3 are used) before, during and after vibration, input axis along gravity.
    - `scale_factor`: K1 [V/g] > 0.
    - `axis_tolerance`: the admissible |U1 − U3|/K1 [rad] (paper: 1e-4).

    **Returns:** a `ShakerEstimate`. The mean of U1 and U3 cancels a bias drift linear in
    time exactly; the check bounds what a non-linear drift or a tilt can leave.
    """
    k1 = _concrete(scale_factor)
    if k1 is not None and not np.all(k1 > 0):
        raise ValueError(
            f"shaker_vibration_error: scale_factor K1 must be positive, got {k1!r} V/g."
        )
    u1, u2, u3 = (jnp.mean(jnp.asarray(u), axis=-1) for u in (u_before, u_during, u_after))
    shift = jnp.abs(u1 - u3) / scale_factor
    return ShakerEstimate(
        vibration_error=(u2 - 0.5 * (u1 + u3)) / scale_factor,
        axis_shift=shift,
        valid=shift <= axis_tolerance,
    )
