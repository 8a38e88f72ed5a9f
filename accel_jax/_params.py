"""Device parameters of the closed-loop pendulum (servo) accelerometer (docs/models.md §1)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

_POSITIVE = (
    "pendulum_mass",
    "pendulum_length",
    "moment_of_inertia",
    "stop_displacement",
    "pickoff_gain",
    "amplifier_gain",
    "torquer_gain",
)
_NON_NEGATIVE = (
    "damping",
    "stiffness",
    "torquer_time_constant",
    "filter_time_constant",
    "noise_std",
)
_FINITE = ("external_moment",)

_UNITS = {
    "pendulum_mass": "kg",
    "pendulum_length": "m",
    "moment_of_inertia": "kg·m²",
    "damping": "N·m·s",
    "stiffness": "N·m",
    "stop_displacement": "m",
    "pickoff_gain": "V/m",
    "amplifier_gain": "1",
    "torquer_gain": "N·m/V",
    "torquer_time_constant": "s",
    "filter_time_constant": "s",
    "external_moment": "N·m",
    "noise_std": "V",
}


def _concrete(value) -> np.ndarray | None:
    """The value as a NumPy array, or None while it is being traced."""
    if isinstance(value, jax.core.Tracer):
        return None
    try:
        return np.asarray(value)
    except Exception:  # abstract values under eqx.filter_* transforms
        return None


_SHOWN_AT_MOST = 8  # values a message lists; a larger array is named by its shape


def _shown(value: np.ndarray) -> str:
    """A concrete value as a message shows it: `-1.0`, or `[1.0, -2.0]`, not `array(-1.)`;
    an array of more than `_SHOWN_AT_MOST` values by its shape and first values (a record
    passed where a number belongs must not put a million numbers in the message)."""
    value = np.asarray(value)
    if value.ndim == 0:
        return repr(value.item())
    if value.size <= _SHOWN_AT_MOST:
        return repr(value.tolist())
    first = ", ".join(repr(v) for v in value.ravel()[:3].tolist())
    return f"an array of shape {value.shape} ([{first}, ...])"


def _as_float(value: ArrayLike) -> Array:
    # Keep the caller's floating dtype; promote ints/Python floats to JAX's default float
    # (float32 unless the caller enabled x64: the library never flips that switch itself).
    if isinstance(value, jax.core.Tracer):
        return value
    array = jnp.asarray(value)
    if not jnp.issubdtype(array.dtype, jnp.floating):
        array = array.astype(jnp.result_type(float))
    return array


class ServoParams(eqx.Module):
    """Parameters of a pendulum compensating accelerometer with magnetoelectric feedback.

    The sensing element is a pendulum of pendulosity m·l, length l and moment of inertia J,
    with viscous damping μ and elastic stiffness c, free between mechanical stops at linear
    displacement h = l·θ = ±h_max. A capacitive pickoff (gain k_dp) and an amplifier (gain
    k_y) produce U_amp = k_dp·k_y·l·θ; a magnetoelectric torquer (gain k_dm, electrical time
    constant T_dm) turns it into the feedback moment. The output U_out is U_amp passed
    through an output filter of time constant T_f (outside the loop) plus white noise of
    standard deviation ε. The governing equations (SI units, see `accel_jax.simulate_linear`):

        J θ'' + μ θ' + c θ = m l a + M_v + M_dm
        T_dm M_dm' = k_dm (U_test − U_amp) − M_dm,       U_amp = k_dp k_y l θ
        T_f U_f' = U_amp − U_f,                           U_out = U_f + ε w

    giving the closed-loop transfer function of docs/models.md eq. (1).

    Every field is an array leaf (so `jax.grad`, `jax.vmap` and optimistix fits act on
    them); positivity is checked on construction when the values are concrete.

    **Fields:**

    - `pendulum_mass`: m [kg].
    - `pendulum_length`: l [m].
    - `moment_of_inertia`: J [kg·m²].
    - `damping`: μ [N·m·s].
    - `stiffness`: c [N·m] (per radian).
    - `stop_displacement`: h_max [m], symmetric mechanical stops at ±h_max.
    - `pickoff_gain`: k_dp [V/m].
    - `amplifier_gain`: k_y [dimensionless].
    - `torquer_gain`: k_dm [N·m/V].
    - `torquer_time_constant`: T_dm [s], inside the loop (0 for an ideal torquer).
    - `filter_time_constant`: T_f [s], on the output only (0 for no filter).
    - `external_moment`: M_v [N·m], the unmodelled constant external moment.
    - `noise_std`: ε [V], standard deviation of the white output noise.
    """

    pendulum_mass: Float[Array, ""] = eqx.field(converter=_as_float)
    pendulum_length: Float[Array, ""] = eqx.field(converter=_as_float)
    moment_of_inertia: Float[Array, ""] = eqx.field(converter=_as_float)
    damping: Float[Array, ""] = eqx.field(converter=_as_float)
    stiffness: Float[Array, ""] = eqx.field(converter=_as_float)
    stop_displacement: Float[Array, ""] = eqx.field(converter=_as_float)
    pickoff_gain: Float[Array, ""] = eqx.field(converter=_as_float)
    amplifier_gain: Float[Array, ""] = eqx.field(converter=_as_float)
    torquer_gain: Float[Array, ""] = eqx.field(converter=_as_float)
    torquer_time_constant: Float[Array, ""] = eqx.field(converter=_as_float)
    filter_time_constant: Float[Array, ""] = eqx.field(converter=_as_float)
    external_moment: Float[Array, ""] = eqx.field(converter=_as_float)
    noise_std: Float[Array, ""] = eqx.field(converter=_as_float)

    def __check_init__(self):
        for name in _POSITIVE + _NON_NEGATIVE + _FINITE:
            value = _concrete(getattr(self, name))
            if value is None:
                continue
            unit = _UNITS[name]
            if not np.all(np.isfinite(value)):
                raise ValueError(f"ServoParams.{name} must be finite, got {_shown(value)} {unit}.")
            if name in _POSITIVE and not np.all(value > 0):
                raise ValueError(
                    f"ServoParams.{name} must be positive, got {_shown(value)} {unit}; "
                    "check the sign and the units (SI)."
                )
            if name in _NON_NEGATIVE and not np.all(value >= 0):
                raise ValueError(
                    f"ServoParams.{name} must be non-negative, got {_shown(value)} {unit}; "
                    "use 0 to switch the effect off."
                )

    @classmethod
    def reference(cls, **overrides) -> ServoParams:
        """The reference device of docs/models.md §1 (Raspopov's values, used by Mironov et al.).

        Oscillatory case: T ≈ 2.90e-4 s, ξ ≈ 0.52. Any field can be overridden by keyword,
        e.g. `ServoParams.reference(torquer_time_constant=0.0)`.
        """
        values = dict(REFERENCE_VALUES)
        unknown = set(overrides) - set(values)
        if unknown:
            raise ValueError(
                f"Unknown ServoParams field(s) {sorted(unknown)}; valid fields are "
                f"{sorted(values)}."
            )
        values.update(overrides)
        return cls(**values)

    @classmethod
    def reference_aperiodic(cls, **overrides) -> ServoParams:
        """The paper's aperiodic case: the reference device with μ = 1.01e-4 N·m·s (ξ ≈ 2.07)."""
        return cls.reference(**{"damping": APERIODIC_DAMPING, **overrides})

    def as_dict(self) -> dict[str, float]:
        """Plain floats keyed by field name (for JSON provenance); scalar fields only."""
        return {name: float(getattr(self, name)) for name in REFERENCE_VALUES}


REFERENCE_VALUES: dict[str, float] = {
    "pendulum_mass": 2.9e-4,
    "pendulum_length": 4.28e-3,
    "moment_of_inertia": 7.09e-9,
    "damping": 2.54e-5,
    "stiffness": 3.02e-4,
    "stop_displacement": 1.9e-6,
    "pickoff_gain": 2.5e5,
    "amplifier_gain": 8.5,
    "torquer_gain": 9.23e-6,
    "torquer_time_constant": 1e-5,
    "filter_time_constant": 1e-5,
    "external_moment": 1e-6,
    "noise_std": 1e-5,
}
"""docs/models.md §1 reference parameters (SI units)."""

APERIODIC_DAMPING = 1.01e-4
"""Damping μ [N·m·s] of the paper's aperiodic example (ξ ≈ 2.07)."""

PAPER_GAMMA = 0.75
"""The paper's rounded pendulum shape factor γ = 3/4 in K_a ≈ γ T² k_dp k_y (eq. 7)."""
