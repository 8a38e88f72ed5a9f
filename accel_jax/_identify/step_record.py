"""Scale-factor identification of a user's own step record (the `accel-jax identify` job).

A measured test-signal record (`StepData`: t, u_test, u_out) may hold several changes of the
test voltage; the paper's methods (SPEC.md §1) use one step. This module picks the first
step, runs the graph-analytic method that fits the response (oscillatory for ξ < 1,
aperiodic otherwise) and, beside it, the least-squares fit of the whole segment, and states
every assumption it made. Host-side glue around the jit-compiled estimators of
`accel_jax._identify`; it computes in the dtype JAX is configured for (the CLI enables float64).
"""

from __future__ import annotations

import numpy as np

from .._data import DataError, StepData
from .._params import PAPER_GAMMA, ServoParams
from .._servo import closed_loop_test_gain, relative_error_percent, scale_factor, shape_factor
from . import (
    IdentificationResult,
    fit_step_response,
    identify_aperiodic,
    identify_oscillatory,
    scale_factor_from_fit,
)

# Codes after which the oscillatory method hands the record to the aperiodic one.
_USE_APERIODIC = (IdentificationResult.not_oscillatory, IdentificationResult.too_few_crossings)

# The aperiodic slope comes from a local cubic over this many samples (see
# `identify_aperiodic`): with noise, raw central differences scatter δK_a by ~±10 %.
_SAVGOL_WINDOW = 101

METHODS = ("auto", "oscillatory", "aperiodic")


def _first_step(data: StepData) -> tuple[int, int, float, float]:
    """(start, stop, step_time, test_step): the segment [start, stop) holding the first
    change of u_test, the time it was applied and its size [V]."""
    u_test = np.asarray(data.u_test)
    changes = np.flatnonzero(np.diff(u_test) != 0)
    if changes.size == 0:
        if u_test[0] == 0:
            raise DataError(
                "the test voltage u_test never changes and is zero: the record holds no "
                "test-signal step to identify from."
            )
        # A record that starts with the step applied: from rest at t[0].
        return 0, len(u_test), float(data.t[0]), float(u_test[0])
    first = int(changes[0]) + 1  # u_test[i] holds on [t_i, t_{i+1}): the step is at t[first]
    stop = int(changes[1]) + 1 if changes.size > 1 else len(u_test)
    return 0, stop, float(data.t[first]), float(u_test[first] - u_test[first - 1])


def _reason(code) -> str:
    return IdentificationResult[code]


def identify_step_record(
    data: StepData,
    params: ServoParams,
    *,
    method: str = "auto",
    gamma: str | float = "exact",
) -> dict:
    """Identify the scale factor K_a from the first test-signal step of a record.

    **Arguments:**

    - `data`: a validated step record (`read_csv`), t [s], u_test [V], u_out [V].
    - `params`: the nominal device: k_dp k_y for eq. (7), T_f and T_dm for the lag
        correction (16) and the order-3 fit, γ = m l²/J, and the nominal K_a to compare with.
    - `method`: `"auto"` (oscillatory; aperiodic when the response does not oscillate),
        `"oscillatory"` or `"aperiodic"`.
    - `gamma`: `"exact"` (m l²/J of `params`), `"paper"` (3/4) or a number.

    **Returns:** a dict (JSON-ready) with the segment used, the graph-analytic estimate
    (`graph`: method, T or T1..T4, ξ, K̂_a and δK_a against the nominal K_a), the order-3
    least-squares fit (`fit`: T, ξ, T_dm, K̂_a ± σ, δK_a), the nominal values and the
    assumptions. Raises `DataError` when the record cannot be used, with the reason.
    """
    if method not in METHODS:
        raise DataError(f"method must be one of {METHODS}, got {method!r}.")
    if isinstance(gamma, str):
        if gamma not in ("exact", "paper"):
            raise DataError(f"gamma must be 'exact', 'paper' or a number, got {gamma!r}.")
        gamma_value = float(shape_factor(params)) if gamma == "exact" else PAPER_GAMMA
    else:
        gamma_value = float(gamma)
        if not (np.isfinite(gamma_value) and gamma_value > 0):
            raise DataError(f"gamma must be a positive number, got {gamma!r}.")
    start, stop, step_time, test_step = _first_step(data)
    ts = np.asarray(data.t[start:stop], dtype=np.float64)
    u_out = np.asarray(data.u_out[start:stop], dtype=np.float64)
    gain = float(params.pickoff_gain * params.amplifier_gain)
    lag = float(params.torquer_time_constant + params.filter_time_constant)
    nominal = float(scale_factor(params))

    def percent(estimate):
        return float(relative_error_percent(estimate, nominal))

    graph: dict = {}
    tried = []
    if method in ("auto", "oscillatory"):
        osc = identify_oscillatory(
            ts,
            u_out,
            pickoff_amplifier_gain=gain,
            shape_factor=gamma_value,
            step_time=step_time,
            throw=False,
        )
        code = osc.result
        if code == IdentificationResult.successful:
            graph = {
                "method": "oscillatory (SPEC.md §1, steps (7)-(10))",
                "time_constant_s": float(osc.time_constant),
                "damping_ratio": float(osc.damping_ratio),
                "period_s": float(osc.t2 - osc.t1),
                "scale_factor": float(osc.scale_factor),
            }
        else:
            tried.append(("oscillatory", code))
            if method == "oscillatory" or not any(code == c for c in _USE_APERIODIC):
                raise DataError(f"oscillatory method: {_reason(code)}")
    if not graph:
        ape = identify_aperiodic(
            ts,
            u_out,
            pickoff_amplifier_gain=gain,
            shape_factor=gamma_value,
            lag_correction=lag,
            step_time=step_time,
            derivative="savgol",
            smoothing_window=_SAVGOL_WINDOW,
            throw=False,
        )
        if ape.result != IdentificationResult.successful:
            before = "".join(f"{m} method: {_reason(c)}; " for m, c in tried)
            raise DataError(f"{before}aperiodic method: {_reason(ape.result)}")
        graph = {
            "method": "aperiodic (SPEC.md §1, steps 1-10 with the lag correction (16))",
            "T1_s": float(ape.t1),
            "T2_s": float(ape.t2),
            "T3_s": float(ape.t3),
            "T4_s": float(ape.t4),
            "time_constant_s": float(ape.time_constant),
            "damping_ratio": float(ape.damping_ratio),
            "lag_correction_s": lag,
            "scale_factor": float(ape.scale_factor),
        }
    graph["dKa_percent"] = percent(graph["scale_factor"])

    fit = fit_step_response(
        ts,
        u_out,
        order=3,
        step_time=step_time,
        feedback_fraction=float(closed_loop_test_gain(params)),
        filter_time_constant=float(params.filter_time_constant),
        throw=False,
    )
    if fit.result == IdentificationResult.successful:
        k_fit, k_std = scale_factor_from_fit(fit, gain, gamma_value)
        fit_out = {
            "method": "least squares, order 3 (T, ξ, T_dm; known T_f), Levenberg-Marquardt",
            "time_constant_s": float(fit.time_constant),
            "time_constant_std_s": float(fit.time_constant_std),
            "damping_ratio": float(fit.damping_ratio),
            "damping_ratio_std": float(fit.damping_ratio_std),
            "torquer_time_constant_s": float(fit.torquer_time_constant),
            "residual_rms_V": float(fit.residual_rms),
            "scale_factor": float(k_fit),
            "scale_factor_std": float(k_std),
            "dKa_percent": percent(k_fit),
            "dKa_std_percent": float(100 * k_std / k_fit),
        }
    else:
        fit_out = {"failed": _reason(fit.result)}
    return {
        "segment": {
            "samples": int(stop - start),
            "t_start_s": float(ts[0]),
            "t_end_s": float(ts[-1]),
            "step_time_s": step_time,
            "test_step_V": test_step,
            "sample_rate_Hz": 1.0 / data.sample_period,
        },
        "graph": graph,
        "fit": fit_out,
        "nominal": {
            "scale_factor": nominal,
            "pickoff_amplifier_gain_V_per_m": gain,
            "shape_factor": gamma_value,
        },
        "assumptions": {
            "units": "K_a in V/(m/s²); δK_a = 100 (K̂_a − K_a)/K̂_a % against the nominal K_a",
            "segment": "the first change of u_test up to the next one (or the record's end)",
            "steady_state": "mean of the last 20 % of the segment, which must be settled",
            "crossings": "linear interpolation with a noise hysteresis band (6σ of the tail)",
            "aperiodic_slope": f"Savitzky-Golay local cubic over {_SAVGOL_WINDOW} samples",
            "gamma": str(gamma),
            "k_dp_k_y": "from the nominal device (eq. 11 needs a ±U_test stop test)",
            "precision": "float64" if ts.dtype == np.float64 else str(ts.dtype),
        },
    }
