"""k_dp k_y from the outputs on the mechanical stops, docs/models.md eq. (11)."""

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
    """k_dp k_y = ½ (U⁺/h⁺ − U⁻/h⁻) [V/m], docs/models.md eq. (11).

    With ±U_test large enough to hold the pendulum on its stops, the output is
    U± = ±k_dp k_y h± + U_offset. Averaging the two slopes cancels the offset exactly when
    h⁺ = h⁻ (in general it leaves ½ U_offset (1/h⁺ − 1/h⁻)).

    A reinterpretation of the paper: eq. (11) as printed (docs/models.md §1) divides the
    *test signals* U_test± by h_max±. Read literally that is not k_dp k_y — the test voltage
    sets the torque, not the pick-off output, so the value would change with U_test — and on
    the reference device with the study's U_test = 5 V it is 24 % off (5 V / 1.9 µm =
    2.63e6 against k_dp k_y = 2.125e6 V/m).
    Here U± are the *outputs* on the stops, which is what the formula must mean for its
    result to be the pick-off and amplifier gain. An error in h± enters k_dp k_y, and so
    K̂_a (eq. (7)), one for one.

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


PLATEAU_FRACTION = 0.03
"""A stop shows in a record as a plateau: at least this fraction of the samples within
`PLATEAU_WIDTH` noise floors of the record's extreme level."""

PLATEAU_WIDTH = 6.0


def stop_record_gain(data, params) -> dict:
    """k_dp k_y by eq. (11) from a record whose test steps drive the pendulum onto both
    stops (host side, NumPy float64).

    U⁺ and U⁻ are the medians of the output on its upper and lower plateaus (the samples
    within `PLATEAU_WIDTH` noise floors of the record's 0.1 % and 99.9 % quantiles, at
    least `PLATEAU_FRACTION` of the record each; the noise floor from second differences,
    `diagnose.openworld.noise_floor`), taken as ±k_dp k_y h_max + offset whatever the
    recorder's polarity; h⁺ = h⁻ = the device's `stop_displacement`. Raises `DataError`
    when the record shows no plateau on one side (it does not reach that stop).

    Returns a dict: `u_plus_V`, `u_minus_V`, `offset_V` (½(U⁺ + U⁻)),
    `pickoff_amplifier_gain_V_per_m` (k_dp k_y), its nominal and relative shift, the
    plateau sample counts and `h_max_m` used.
    """
    from .._data import DataError

    y = np.asarray(data.u_out, dtype=np.float64)
    second = np.diff(y, 2)  # σ√6 for white noise; steps and transients are outliers
    mad = float(np.median(np.abs(second - np.median(second))))
    spacing = np.diff(np.unique(y))
    quantum = float(np.min(spacing)) if spacing.size else 0.0  # an ADC step, if any
    sigma = max(mad / 0.6745 / np.sqrt(6.0), quantum, 1e-12 * float(np.max(np.abs(y))))
    sides = {}
    for name, level in (("plus", np.quantile(y, 0.999)), ("minus", np.quantile(y, 0.001))):
        near = np.abs(y - level) <= PLATEAU_WIDTH * sigma
        if np.mean(near) < PLATEAU_FRACTION:
            raise DataError(
                f"the output shows no plateau at its {'highest' if name == 'plus' else 'lowest'} "
                f"level ({np.mean(near):.1%} of the samples within {PLATEAU_WIDTH:g} noise floors "
                f"of it, {PLATEAU_FRACTION:.0%} needed): the record does not reach that stop."
            )
        sides[name] = (float(np.median(y[near])), int(np.sum(near)))
    h = float(params.stop_displacement)
    u_plus, u_minus = sides["plus"][0], sides["minus"][0]
    gain = float(pickoff_gain_from_stops(u_plus, u_minus, h, h))
    nominal = float(params.pickoff_gain * params.amplifier_gain)
    return {
        "u_plus_V": u_plus,
        "u_minus_V": u_minus,
        "offset_V": 0.5 * (u_plus + u_minus),
        "pickoff_amplifier_gain_V_per_m": gain,
        "nominal_V_per_m": nominal,
        "shift_relative": gain / nominal - 1,
        "plateau_samples": [sides["plus"][1], sides["minus"][1]],
        "h_max_m": h,
        "noise_floor_V": sigma,
        "method": "eq. (11): k_dp k_y = ½(U⁺/h⁺ − U⁻/h⁻), U± the medians of the output's "
        "plateaus, h± the device's stop_displacement",
    }
