"""`accel-jax tolerance`: why an option's value is refused (`implausible_option`), the
limits table with its legend and the passport check, and the JSON the command writes
(`tolerance_lines`, `tolerance_json`; both take the command's inputs and
`accel_jax._tolerance.tolerance_table`'s result, `table`)."""

from __future__ import annotations

import math

from ..._format import number, precise

_AXES = ("OA", "PA", "IA")

MAX_BUDGET = 1.0
MAX_ACCELERATION = 1e5
"""The largest acceleration an option may give [g]: beyond any accelerometer's range (and
the k5 a⁵ terms of 1e300 g overflow float64)."""
MAX_FREQUENCY = 1e9
"""The largest sinusoid frequency an option may give [Hz]."""
"""The largest budget δ* taken [g]: above 1 g it is a unit slip (mg or ppm typed as g)."""


def implausible_option(budget, mean_accel, sine, sine_freq, rms) -> tuple[str, str] | None:
    """The first option whose value cannot be meant, and why: (option, message); None when
    every value is plausible (`rms` None: not given)."""
    if not (math.isfinite(budget) and 0 < budget <= MAX_BUDGET):
        return "--budget", (
            f"{precise(budget)}; the budget must be positive and at most {MAX_BUDGET:g} g: it "
            "is the admissible vibration error δ* in g (e.g. 5e-4 for 0.5 mg)."
        )
    top = f"at most {MAX_ACCELERATION:g} g"
    if not (math.isfinite(mean_accel) and mean_accel != 0 and abs(mean_accel) <= MAX_ACCELERATION):
        return "--mean-accel", (
            f"{precise(mean_accel)} g; it must be finite, non-zero (the multiplicative limits "
            f"divide by it) and {top} in size."
        )
    if not all(math.isfinite(b) and 0 <= b <= MAX_ACCELERATION for b in sine):
        return "--sine", (
            f"{' '.join(repr(b) for b in sine)} g; the amplitudes (OA PA IA) must be finite, "
            f"non-negative and {top}, e.g. 1.2 1.2 0.5."
        )
    if not (math.isfinite(sine_freq) and 0 < sine_freq <= MAX_FREQUENCY):
        return "--sine-freq", (
            f"{precise(sine_freq)} Hz; the frequency must be finite, positive and at most "
            f"{MAX_FREQUENCY:g} Hz."
        )
    if rms is not None and not (math.isfinite(rms) and 0 <= rms <= MAX_ACCELERATION):
        return "--rms", f"{precise(rms)} g; the RMS must be finite, non-negative and {top}."
    return None


def _num(value, width=10) -> str:
    # 4 significant figures; ∞ where a term has no sensitivity
    return f"{number(value):>{width}}"


def tolerance_lines(
    *, budget, mean_accel, sine, sine_freq, sigma, source, unit, table
) -> list[str]:
    """The printed summary: the environment, the legend of the columns, one row per
    coefficient and, with a passport (`unit` "aks05" or "al1m"), its total δ_V against δ*."""
    rows, total = table["rows"], table["total_vibration_error_g"]
    checked = total is not None
    amplitudes = ", ".join(f"{axis} {b:g}" for axis, b in zip(_AXES, sine, strict=True))
    lines = [
        f"budget δ* = {budget:g} g, mean a3 = {mean_accel:g} g",
        f"vibration: sine {amplitudes} g at {sine_freq:g} Hz (in phase)",
        f"           random σ = {sigma:.4g} g on every axis ({source})",
        "limits on |coefficient|, in each row's unit (column unit):",
        "  paper     the paper's fixed budget shares and closed forms, eqs. (13), (15)",
        f"  gradient  the paper's share of δ* over the exact sensitivity |∂δ_V/∂k| at "
        f"a3 = {mean_accel:g} g (jax.grad)",
        "  full δ*   δ* over |∂δ_V/∂k|: that coefficient alone using the whole budget",
    ]
    header = f"{'coef':<5}{'unit':<7}{'paper':>10}{'gradient':>10}{'full δ*':>10}"
    if checked:
        # (Worded without "EXCEEDS", which marks only a coefficient over its limit.)
        lines.append(
            f"check: |{unit} passport coefficient| against the gradient limit (not the paper "
            "column): ok or over it"
        )
        lines.append("δ_V part: ∂δ_V/∂k · k, that coefficient's share of the unit's δ_V at a3 [g]")
        header += f"{unit + ' |k|':>11}{'δ_V part [g]':>14}  check"
    lines.append(header)
    for name, row in rows.items():
        line = (
            f"{'A1' if name == 'asymmetry' else name:<5}{row['unit']:<7}"
            f"{_num(row['paper_method'])}{_num(row['gradient_paper_shares'])}"
            f"{_num(row['gradient_full_budget'])}"
        )
        if checked:
            mark = "ok" if row["within"] else "EXCEEDS"
            line += f"{_num(row['passport'], 11)}{_num(row['vibration_error_part_g'], 14)}  {mark}"
        lines.append(line)
    if not checked:
        lines.append(
            "total vibration error δ_V: no device coefficients given (--unit aks05 or al1m "
            "checks a passport's total against δ*)"
        )
        return lines
    verdict = "within" if table["within_budget"] else "EXCEEDS"
    return [
        *lines,
        f"{unit} passport: Table 4 of the vibration-error paper ('Improving the accuracy "
        "of a navigation accelerometer in rocket flight'), which gives no m31, m32 (taken "
        "as 0)",
        f"δ_V: the exact shift of the mean output at a3 = {mean_accel:g} g, the sum of the "
        "parts above",
        f"total vibration error δ_V = {total:.3g} g against the budget δ* = {budget:g} g: "
        f"{verdict}",
    ]


def tolerance_json(*, budget, mean_accel, sine, sine_freq, sigma, source, unit, table) -> dict:
    """The `--json` document (without the provenance): the inputs, the limits in ppm units,
    the passport check and the assumptions."""
    check = {}
    if table["total_vibration_error_g"] is not None:
        check = {
            "unit_check": {
                "passport": unit,
                "judged_against": "gradient_paper_shares",
                "total_vibration_error_g": table["total_vibration_error_g"],
                "within_budget": table["within_budget"],
            }
        }
    return {
        "budget_g": budget,
        "mean_acceleration_g": mean_accel,
        "sine_amplitude_g": list(sine),
        "sine_frequency_Hz": sine_freq,
        "random_rms_g": sigma,
        "random_source": source,
        "limits_ppm": table["rows"],
        **check,
        "assumptions": {
            "paper_method": "fixed budget shares, eqs. (13), (15) of the vibration-error paper",
            "gradient": "exact sensitivities by jax.grad of the vibration error at "
            "the mean a3, the paper's share per coefficient",
            "random_vibration": "Gaussian, same σ on every axis, fully correlated",
            "precision": "float64",
        },
    }
