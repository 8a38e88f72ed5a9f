"""The step diagnosis's domain check (host side, NumPy, no model of the loop): is a record
the step response of a DC-coupled servo accelerometer on the nominal device's time scale?"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from ..._data import NominalDevice, StepData
from ..._params import ServoParams
from ..._servo import damping_ratio, time_constant
from .segments import segments, sequence_key, time_text


def _nominal_rise(base: ServoParams) -> float:
    """Time [s] the nominal loop (ideal lags) takes to reach half its settled step: the
    second-order step response 1 + (p₂e^{p₁t} − p₁e^{p₂t})/(p₁ − p₂), poles
    p = (−ξ ± √(ξ² − 1))/T, on a fine grid (NumPy, complex poles for ξ < 1)."""
    period = float(time_constant(base))
    zeta = float(damping_ratio(base))
    if abs(zeta - 1) < 1e-6:
        zeta = 1 + 1e-6  # a double pole: the limit, to 1e-6
    root = np.sqrt(complex(zeta**2 - 1))
    p1, p2 = (-zeta + root) / period, (-zeta - root) / period
    t = np.linspace(0, 20 * period * max(zeta, 1.0), 20001)
    y = (1 + (p2 * np.exp(p1 * t) - p1 * np.exp(p2 * t)) / (p1 - p2)).real
    return float(t[np.argmax(y >= 0.5)])


class _Change(NamedTuple):
    """One checked change: the output's settled change and its largest excursion from the
    level before [V], and the time [s] it takes to reach half the settled change (None
    where it does not)."""

    settled_change_V: float
    excursion_V: float
    rise_s: float | None


def check_domain(data: StepData, nominal: NominalDevice, floor: float) -> tuple[list[str], dict]:
    """Model-free checks that the record is a DC-coupled servo accelerometer's step
    response on the nominal device's time scale. Returns (problems, measurements)."""
    y = np.asarray(data.u_out)
    dt = data.sample_period
    edges = segments(sequence_key(data))
    period = float(time_constant(nominal.params))
    settle = max(int(4 * period / dt), 8)
    rows: list[_Change] = []
    for j in range(1, edges.size - 1):
        start, stop = edges[j], edges[j + 1]
        prev_start = edges[j - 1]
        if stop - start < settle or start - prev_start < settle:
            continue
        before = float(np.mean(y[start - max((start - prev_start) // 4, 2) : start]))
        after = float(np.mean(y[stop - max((stop - start) // 4, 2) : stop]))
        excursion = float(np.max(np.abs(y[start:stop] - before)))
        if excursion <= 0 or excursion < 10 * floor:
            continue
        target = after - before
        crossed = np.flatnonzero(np.abs(y[start:stop] - before) >= 0.5 * abs(target))
        rows.append(
            _Change(
                settled_change_V=target,
                excursion_V=excursion,
                rise_s=float(crossed[0] * dt) if crossed.size and abs(target) > 0 else None,
            )
        )
    measured: dict[str, Any] = {"changes_checked": len(rows)}
    problems = []
    if not rows:
        measured["note"] = (
            "no change with settled segments on both sides (each at least 4 T of the nominal "
            "device) and a response above the noise: the domain was not checked"
        )
        return problems, measured
    ratio = float(np.median([abs(r.settled_change_V) / r.excursion_V for r in rows]))
    measured["settled_over_excursion"] = ratio
    if ratio < 0.4:
        problems.append(
            "the output returns to its previous level after each step (settled change "
            f"{ratio:.0%} of the transient excursion): not the step response of a DC-coupled "
            "servo accelerometer (a velocity-output or AC-coupled sensor?)"
        )
        return problems, measured
    rises = [r.rise_s for r in rows if r.rise_s is not None]
    nominal_rise = _nominal_rise(nominal.params)
    measured["rise_time_s"] = float(np.median(rises)) if rises else None
    measured["nominal_rise_time_s"] = nominal_rise
    if rises:
        factor = float(np.median(rises)) / max(nominal_rise, dt)
        measured["rise_time_ratio"] = factor
        if factor > 3 or (factor < 1 / 3 and nominal_rise > 2 * dt):
            # Under one sample period the nominal rise is not resolved: the ratio is to the
            # period, a lower bound (a record in ms read as s: 397 ms against 379 µs, 1 ms
            # samples, is at least 397×, not "379 µs … 397×").
            apart = (
                f"time scales {factor:.3g}× apart"
                if nominal_rise >= dt
                else f"under one sample period ({time_text(dt)}): time scales at least "
                f"{factor:.3g}× apart"
            )
            problems.append(
                f"the transients reach half their step in {time_text(np.median(rises))}, the "
                f"nominal device's in {time_text(nominal_rise)}, {apart} (a different device, "
                "or time in other units than seconds? give the device's values with --params)"
            )
    return problems, measured
