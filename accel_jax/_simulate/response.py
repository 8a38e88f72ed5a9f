"""`step_response`: the identification record of docs/models.md §1 (a constant test voltage
switched on at t_0 = 0 on a settled device), by either simulator."""

from __future__ import annotations

import math
from typing import Literal, cast

import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, PRNGKeyArray

from .._params import ServoParams
from .linear import simulate_linear
from .loop import _common_dtype
from .nonlinear import simulate_nonlinear
from .state_space import _Samples

# --------------------------------------------------------------------------------------
# Step response
# --------------------------------------------------------------------------------------


def step_response(
    params: ServoParams,
    duration: float,
    sample_rate: float,
    test_voltage: ArrayLike = 1.0,
    *,
    method: Literal["linear", "nonlinear"] = "linear",
    key: PRNGKeyArray | None = None,
    **kwargs,
) -> tuple[_Samples, _Samples]:
    """Response of the output to a constant test voltage switched on at t_0 = 0.

    The device starts settled (the default initial state: equilibrium with zero test
    voltage, under `params.external_moment` and zero acceleration), and U_test is applied
    from t_0 on: the record of docs/models.md §1's identification (step 1).

    **Arguments:**

    - `params`: the device, a `ServoParams`.
    - `duration`: record length [s], a positive Python number.
    - `sample_rate`: [Hz], a positive Python number; n = round(duration·sample_rate) + 1
        samples at ts = arange(n)/sample_rate.
    - `test_voltage`: the constant U_test [V].
    - `method`: `"linear"` (`simulate_linear`) or `"nonlinear"` (`simulate_nonlinear`,
        with the stops).
    - `key`: PRNG key for the output noise, or `None`.
    - `**kwargs`: passed on to the simulator (e.g. `acceleration`, `external_moment`,
        `stops`, `rtol`).

    **Returns:**

    `(ts, u_out)`: sample times [s] and output [V], both shape (n,).
    """
    for name, value in (("duration", duration), ("sample_rate", sample_rate)):
        if (
            isinstance(value, bool)
            or not isinstance(value, (int, float, np.integer, np.floating))
            or not math.isfinite(value)
            or value <= 0
        ):
            raise ValueError(
                f"{name} must be a positive finite Python number, got {value!r}"
                f"{' s' if name == 'duration' else ' Hz'}."
            )
    if method not in ("linear", "nonlinear"):
        raise ValueError(f"method must be 'linear' or 'nonlinear', got {method!r}.")
    n = int(round(duration * sample_rate)) + 1
    if n < 2:
        raise ValueError(
            f"duration·sample_rate = {duration * sample_rate!r} gives fewer than 2 samples; "
            "increase the duration or the sample rate."
        )
    dtype = _common_dtype(params, test_voltage)
    ts = jnp.arange(n, dtype=dtype) / jnp.asarray(sample_rate, dtype=dtype)
    simulate = simulate_linear if method == "linear" else simulate_nonlinear
    # The output alone: `kwargs` are the simulator's inputs and options (not return_states).
    return ts, cast(_Samples, simulate(params, ts, test_voltage, key=key, **kwargs))
