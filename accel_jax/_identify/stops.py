"""k_dp k_y from the outputs on the mechanical stops, SPEC.md eq. (11)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from .._params import _concrete
from .record import Values, ValuesLike

# ---------------------------------------------------------------------------------------
# k_dp k_y from the stops, eq. (11)


def pickoff_gain_from_stops(
    u_plus: ValuesLike,
    u_minus: ValuesLike,
    h_plus: ValuesLike,
    h_minus: ValuesLike,
) -> Values:
    """k_dp k_y = ½ (U⁺/h⁺ − U⁻/h⁻) [V/m], SPEC.md eq. (11).

    With ±U_test large enough to hold the pendulum on its stops, the output is
    U± = ±k_dp k_y h± + U_offset. Averaging the two slopes cancels the offset exactly when
    h⁺ = h⁻ (in general it leaves ½ U_offset (1/h⁺ − 1/h⁻)).

    **Arguments:**

    - `u_plus`: output on the positive stop [V] (positive).
    - `u_minus`: output on the negative stop [V] (negative).
    - `h_plus`, `h_minus`: the stop displacements as positive magnitudes [m].

    **Returns:**

    k_dp k_y [V/m]. Concrete inputs are checked (`ValueError`); traced ones are not.
    """
    for name, value in (("h_plus", h_plus), ("h_minus", h_minus)):
        concrete = _concrete(value)
        if concrete is not None and not np.all(np.isfinite(concrete) & (concrete > 0)):
            raise ValueError(
                f"pickoff_gain_from_stops: {name} must be a positive magnitude in metres, "
                f"got {concrete!r}."
            )
    plus, minus = _concrete(u_plus), _concrete(u_minus)
    if plus is not None and not np.all(np.isfinite(plus) & (plus > 0)):
        raise ValueError(
            f"pickoff_gain_from_stops: u_plus (output on the + stop) must be positive, got "
            f"{plus!r} V; check the sign convention or swap the arguments."
        )
    if minus is not None and not np.all(np.isfinite(minus) & (minus < 0)):
        raise ValueError(
            f"pickoff_gain_from_stops: u_minus (output on the − stop) must be negative, got "
            f"{minus!r} V; check the sign convention or swap the arguments."
        )
    return 0.5 * (jnp.asarray(u_plus) / h_plus - jnp.asarray(u_minus) / h_minus)
