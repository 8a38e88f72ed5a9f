"""`accel-jax info`: the closed-form characteristics of a device."""

from __future__ import annotations

from ..._servo import (
    closed_loop_test_gain,
    damping_ratio,
    scale_factor,
    shape_factor,
    time_constant,
)


def info_lines(label: str, params) -> list[str]:
    """The device `params` under the heading `label`: K_a, T, ξ, K_test and γ."""
    return [
        f"{label}:",
        f"  scale factor K_a      = {float(scale_factor(params)):.6g} V/(m/s²)",
        f"  time constant T       = {float(time_constant(params)):.6g} s",
        f"  damping ratio ξ       = {float(damping_ratio(params)):.6g}",
        f"  test gain K_test      = {float(closed_loop_test_gain(params)):.6g}",
        f"  shape factor γ=ml²/J  = {float(shape_factor(params)):.6g}",
    ]
