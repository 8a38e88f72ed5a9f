"""What a discovered term means for a designer (`discover`'s `consequence`): the static
transfer function's coefficients it implies (docs/models.md §3, eq. (1)), their vibration
error in the paper's Example 1 flight (Cyclone-4: mean a3 = 2 g, 0.5 g sine and σ = 1.4 g
random along IA) and the paper's limit on each; for a term with no static part, what it
does instead.

The static maps are those of the loop with the term at rest (`term_record` settled at a
constant input; the tests check each against it), with y the output [V], h the record's
half span [V] and K1 [V/g] the nominal device's static output per g of input
acceleration (m l g₀ over k_dm, times the loop's static gain):

- `torquer_asymmetry` c: y = K1 a + c|y|, the scale factor 1 + c sign a: A1 = 2c;
- `spring_square`, `output_square` c: Δy = c y²/h: k2 = c K1/h [1/g];
- `spring_cube` c: Δy = c y³/h²: k3 = c K1²/h² [1/g²];
- `torquer_square` c: Δy = −c y|y|/h, an a|a| term (not one of eq. (1)'s);
- `torquer_dead_zone` c: Δy = −c h sign y, a step of 2ch at a = 0 (not one of eq. (1)'s);
- the pickoff terms: the loop's gain takes the pickoff's error at rest (what is left acts
  through the pendulum's own spring, ~c/C of it: 2e-5 V for c = 0.01 at y = 1 V);
- damping, dry friction (smooth), the poles and the forcing: none at rest.

The coefficients are in the record's output frame: with an output that reads negative for
a positive input acceleration, the even terms' (A1, k2) signs reverse in a3's frame.

Float64 (the vibration errors are ppm-level; the diagnosis runs in float64).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from ..._data import NominalDevice
from ..._simulate.sequence import accel_moment, equilibrium
from ..._static import PPM_UNITS, StaticTransferFunction
from ..._tolerance import cyclone4, paper_limits
from ..._vibration import vibration_error
from ..discovery_result import DiscoveredColumn

SCENARIO = "Cyclone-4 (the paper's Example 1: δ* = 5e-4 g, mean a3 = 2 g)"

_STATIC = {
    "torquer_asymmetry": ("asymmetry", lambda c, h, k1: 2 * c),
    "spring_square": ("k2", lambda c, h, k1: c * k1 / h),
    "output_square": ("k2", lambda c, h, k1: c * k1 / h),
    "spring_cube": ("k3", lambda c, h, k1: c * k1**2 / h**2),
}
"""Terms with a coefficient of eq. (1): (its name, c ↦ its value in g-units)."""

_DYNAMIC = {
    "pickoff": "no static term: at rest the loop's gain takes the pickoff's error (only "
    "~c/C of it, C the loop's stiffness, acts through the pendulum's spring); it changes "
    "the loop's dynamics (the step responses, δ(ω))",
    "damping_quadratic": "no static term: it acts only while the pendulum moves",
    "dry_friction": "no static term in this smooth form (a sticking pivot would leave a "
    "dead band of about ±c·h of input-referred moment)",
    "torquer_pole": "no static term: the feedback path lags by c·T, a dynamic scale-factor "
    "error δ(ω)",
    "output_pole": "no static term: the output lags by c·T, a dynamic scale-factor error δ(ω)",
    "forcing_ramp": "no static term: an input-referred bias drifting by c·h over the record",
    "forcing_sinusoid": "no static term: an input-axis disturbance at the fitted frequency "
    "(the stand's, or the sensor's own)",
}


def static_gain(nominal: NominalDevice) -> float:
    """K1 [V/g]: the output at rest per g of input acceleration (`accel_moment` times the
    loop's static gain k_dp k_y l k_dm / C)."""
    p = nominal.params
    return float(equilibrium(p, accel_moment(p), 0.0)[0])  # the deflection voltage v = output


def consequence(
    columns: Sequence[DiscoveredColumn], half: float, nominal: NominalDevice
) -> list[dict]:
    """Per column of a discovered subset (a `DiscoveryCandidate`'s `columns`), a
    JSON-ready dict: `term`; `static` (the coefficient of eq. (1) it implies:
    `coefficient`, `value` [g-units], `ppm` (×1e6, in `ppm_unit`), `vibration_error_ug` in
    the scenario, `paper_limit_ppm` and `within_limit`) or None; `text`, one line for the
    summary."""
    k1 = static_gain(nominal)
    scenario = cyclone4()
    limits = paper_limits(scenario)
    out = []
    for column in columns:
        name, c = column.term, float(column.coefficient)
        base = name.split(" ")[0]
        entry = {"term": name, "static": None, "K1_V_per_g": k1}
        if base in _STATIC:
            coefficient, value_of = _STATIC[base]
            value = float(value_of(c, half, k1))
            tf = StaticTransferFunction(**{coefficient: value})
            error = float(vibration_error(tf, scenario.environment, scenario.mean_acceleration))
            limit = float(limits[coefficient])
            entry["static"] = {
                "coefficient": coefficient,
                "value": value,
                "ppm": value * 1e6,
                "ppm_unit": PPM_UNITS[coefficient],
                "scenario": SCENARIO,
                "vibration_error_ug": error * 1e6,
                "paper_limit_ppm": limit * 1e6,
                "within_limit": bool(abs(value) <= limit),
            }
            verdict = "within" if abs(value) <= limit else "beyond"
            entry["text"] = (
                f"{name}: {coefficient} = {value * 1e6:.3g} {PPM_UNITS[coefficient]} in eq. (1) "
                f"(K1 = {k1:.3g} V/g); vibration error {error * 1e6:.3g} µg in {SCENARIO}, "
                f"{verdict} the paper's limit {limit * 1e6:.3g} {PPM_UNITS[coefficient]}"
            )
        elif base == "torquer_square":
            value = -c * k1 / half
            entry["text"] = (
                f"{name}: a static a|a| term, {value * 1e6:.3g} ppm/g × a|a| (not a "
                "coefficient of eq. (1))"
            )
        elif base == "torquer_dead_zone":
            step = 2 * abs(c) * half / k1
            entry["text"] = (
                f"{name}: a static step of {step * 1e6:.3g} µg at a = 0 (a sign(a) bias, not "
                "a coefficient of eq. (1))"
            )
        else:
            key = "pickoff" if base.startswith("pickoff") else base
            entry["text"] = f"{name}: " + _DYNAMIC.get(key, "no static term")
        if not math.isfinite(k1):
            entry["text"] += " (K1 not finite: the nominal device's values)"
        out.append(entry)
    return out
