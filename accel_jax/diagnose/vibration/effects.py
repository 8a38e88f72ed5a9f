"""The vibration kind's effect library: `AbstractVibrationEffect` (an effect frees
coefficients of the static transfer function in the design matrix) and its final effects
`k2`..`k5` (one factory), `asymmetry`, `cross_coupling`, each the nominal model at z = 0."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from ..._data import VibrationData
from ..base import (
    AbstractEffect,
    effect_library,
    register_effect,
)

NOMINAL_COEFFICIENTS = ("bias", "scale_factor_error")
"""The nominal model's coefficients (a0 [g], δ [1])."""

COEFFICIENTS = (
    "bias",
    "scale_factor_error",
    "asymmetry",
    "k2",
    "k3",
    "k4",
    "k5",
    "m31",
    "m32",
)
"""Every coefficient a candidate may free, in the column order of the design matrix."""


class AbstractVibrationEffect(AbstractEffect):
    """An effect on a vibration table: it frees the transfer-function coefficients
    `coefficients` (fields of `StaticTransferFunction`), whose scaled parameters z are
    those coefficients in ppm units (z = 0: the nominal model, exactly). Override
    `unavailable` when the effect needs columns a table may lack."""

    kind = "vibration"
    coefficients: ClassVar[tuple[str, ...]]

    def unavailable(self, data: VibrationData) -> str | None:
        """Why this table cannot show the effect at all (None: it can)."""
        return None

    def initial_guess(self, context) -> np.ndarray:
        return np.zeros(self.n_params)

    def physical(self, z, context) -> dict[str, float]:
        se = context.get("standard_errors", {}).get(self.name, np.full(self.n_params, np.nan))
        out = {}
        for name, value, error in zip(self.parameter_names, z, se, strict=True):
            out[name] = float(value)
            out[name + "_se"] = float(error)
        return out


_POLYNOMIAL_TERMS = {
    2: ("quadratic", "²", "k2 (b²/2 + σ²)"),
    3: ("cubic", "³", "k3 (1.5 a b² + 3 a σ²)"),
    4: ("quartic", "⁴", "k4 (3 a² b² + 0.375 b⁴ + …)"),
    5: ("quintic", "⁵", "k5 (5 a³ b² + 1.875 a b⁴ + …)"),
}
"""Order → (word, superscript, its rectification under a sine a + b sin ωt plus random σ)."""


def _polynomial_effect(order: int) -> type:
    """The effect of the nonlinearity k_n a3ⁿ (n = `order`): one final class per order,
    registered as `kn`, its parameter in ppm/gⁿ⁻¹."""
    word, power, rectified = _POLYNOMIAL_TERMS[order]
    name = f"k{order}"
    unit = "ppm_per_g" + ("" if order == 2 else str(order - 1))
    return register_effect(
        type(
            f"K{order}",
            (AbstractVibrationEffect,),
            {
                "__doc__": f"{word.capitalize()} nonlinearity {name} a3{power}: rectifies as "
                f"{rectified}.",
                "__module__": __name__,
                "name": name,
                "coefficients": (name,),
                "parameter_names": (f"{name}_{unit}",),
                "description": f"{word} nonlinearity {name} a3{power}",
            },
        )
    )


K2, K3, K4, K5 = (_polynomial_effect(order) for order in (2, 3, 4, 5))


@register_effect
class Asymmetry(AbstractVibrationEffect):
    """Scale-factor asymmetry ½ A1 |a3|: rectifies when the vibration crosses zero."""

    name = "asymmetry"
    coefficients = ("asymmetry",)
    parameter_names = ("A1_ppm",)
    description = "scale-factor asymmetry ½ A1 |a3|"


@register_effect
class CrossCoupling(AbstractVibrationEffect):
    """Cross-coupling m31 a3 a1 + m32 a3 a2: rectifies as ½ m3i b3 bi (in-phase sinusoids).
    Needs the cross-axis vibration columns."""

    name = "cross_coupling"
    coefficients = ("m31", "m32")
    parameter_names = ("m31_ppm_per_g", "m32_ppm_per_g")
    description = "cross-coupling m31 a3 a1 + m32 a3 a2"

    def unavailable(self, data):
        columns = [c for c in ("vib_amp_oa", "vib_amp_pa") if getattr(data, c) is not None]
        if not columns:
            return (
                "cross_coupling left out: the table has no cross-axis vibration columns "
                "(vib_amp_oa, vib_amp_pa); m31, m32 act only through the products a3·a1, "
                "a3·a2 and cannot be seen without vibration on a cross axis."
            )
        if not any(np.any(np.asarray(getattr(data, c)) > 0) for c in columns):
            return (
                "cross_coupling left out: the cross-axis vibration columns are zero in every "
                "row, so m31, m32 cannot be seen."
            )
        return None


def vibration_effects() -> list[AbstractVibrationEffect]:
    """The registered vibration effects, in registration order."""
    return [cls() for cls in effect_library("vibration").values()]
