"""Scale-factor identification of a user's own step record (the `accel-jax identify` job).

A measured test-signal record (`StepData`: t, u_test, u_out) may hold several changes of the
test voltage; the paper's methods (docs/models.md §1) use one step. This module picks the first
step, runs the graph-analytic method that fits the response (oscillatory for ξ < 1,
aperiodic otherwise) and, beside it, the least-squares fit of the whole segment, and states
every assumption it made, with the fit's quality as System Identification Toolbox users
read it (fit percentage, NRMSE, residual whiteness) and each fitted parameter against its
nominal value. Host-side glue around the jit-compiled estimators of `accel_jax._identify`;
it computes in the dtype JAX is configured for (the CLI enables float64).
`identify_step_records` takes several records of one device, a stop-level one by eq. (11).
The results are typed (`accel_jax._identify.step_result`: `StepIdentification`,
`StopRecordGain`); `accel_jax.report` turns one into text (`identification_summary`) and
a figure (`identification_figure`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .._data import DataError, StepData
from .._noise.whiteness import ljung_box
from .._params import PAPER_GAMMA, ServoParams
from .._servo import (
    closed_loop_test_gain,
    damping_ratio,
    relative_error_percent,
    scale_factor,
    shape_factor,
    time_constant,
)
from .._simulate.modal import _third_order_step
from . import (
    IdentificationResult,
    fit_step_response,
    identify_aperiodic,
    identify_oscillatory,
    scale_factor_from_fit,
)
from .step_result import (
    AperiodicEstimate,
    FitFailure,
    FitParameter,
    FitQuality,
    GraphEstimate,
    LeastSquaresFit,
    NominalValues,
    OscillatoryEstimate,
    StepIdentification,
    StepSegment,
    StepTraces,
    StopRecordGain,
    WhitenessTest,
)
from .stops import stop_record_gain

# Codes after which the oscillatory method hands the record to the aperiodic one.
_USE_APERIODIC = (IdentificationResult.not_oscillatory, IdentificationResult.too_few_crossings)

# The aperiodic slope comes from a local cubic over this many samples (see
# `identify_aperiodic`): with noise, raw central differences scatter δK_a by ~±10 %.
_SAVGOL_WINDOW = 101

METHODS = ("auto", "oscillatory", "aperiodic")

# The residual whiteness test: Ljung-Box over this many lags (as `diagnose` uses it), white
# when its p-value is at least this level.
WHITENESS_LAGS = 20
WHITENESS_LEVEL = 0.05
# The tail of the segment (as the methods' `tail_fraction`) whose spread is the noise σ.
_TAIL_FRACTION = 0.2


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


_RECORD_WORDS = {
    # A record's identification (`identify_step_record`, the CLI's) sets no method options:
    # its reasons say what to change in the record, not which keyword of the Python methods
    # to pass (a user's trial met "pass `steady_state`" and "use identify_aperiodic" there).
    "too_short": "The record has not settled after the step: its last part is not flat "
    "relative to the step. Record for longer after the step.",
    "no_step": "The record shows no step: the output's change is within the noise band. "
    "Check that the test signal was applied.",
    "not_oscillatory": "The response does not oscillate (no overshoot beyond the noise "
    "band, ξ ≥ 1).",
    "not_aperiodic": "The response overshoots its steady state (ξ < 1).",
}


def _reason(code) -> str:
    for name, words in _RECORD_WORDS.items():
        if bool(code == getattr(IdentificationResult, name)):
            return words
    return IdentificationResult[code]


@jax.jit
def _fitted_response(ts, step_time, time_constant, damping, torquer, fraction, filter_tc, g, u0):
    """The order-3 fit's model output U0 + G s(t) on the record's grid [V] (`StepFit`)."""
    shape = _third_order_step(ts, step_time, time_constant, damping, torquer, fraction, filter_tc)
    return u0 + g * shape


def _extremum_times(ts, u_out, steady_state, direction, t1, t2) -> tuple[float, float]:
    """Times of the overshoot A1 and the undershoot A2 the oscillatory method read: the
    largest deviation from U_ss either way between the crossings t1 and t2 (one period,
    which holds one extremum of each sign)."""
    inside = (ts > t1) & (ts < t2)
    if not np.any(inside):
        return float("nan"), float("nan")
    deviation = np.where(inside, direction * (u_out - steady_state), 0.0)
    return float(ts[np.argmax(deviation)]), float(ts[np.argmin(deviation)])


def _quality(u_out, model, n_tail) -> FitQuality:
    """The fit's quality as the System Identification Toolbox reports it: `compare`'s fit
    percentage and `goodnessOfFit`'s NRMSE (both over the whole segment), the residual's
    rms against the noise σ, and the Ljung-Box test of the residual's whiteness.

    The noise σ does not come from the fit: it is the spread of successive differences of
    the settled tail, std(Δu)/√2, which the slow remainder of the ringing does not inflate
    as the tail's own standard deviation would (a reference-device record 4 ms after the
    step still rings at 5e-4 of the step: a tail std of 2.6e-4 V against 1e-5 V of noise).
    Correlated noise has smaller differences than spread, so its residual stands out of a
    ±2σ band drawn with this σ.
    """
    residual = u_out - model
    nrmse = float(np.linalg.norm(residual) / np.linalg.norm(u_out - u_out.mean()))
    test = ljung_box(residual, lags=WHITENESS_LAGS)
    return FitQuality(
        fit_percent=100.0 * (1.0 - nrmse),
        nrmse=nrmse,
        residual_rms_V=float(np.sqrt(np.mean(residual**2))),
        noise_std_V=float(np.std(np.diff(u_out[-n_tail:])) / np.sqrt(2.0)),
        whiteness=WhitenessTest(
            test="Ljung-Box",
            statistic=test["statistic"],
            lags=test["lags"],
            p_value=test["p_value"],
            level=WHITENESS_LEVEL,
            white=bool(test["p_value"] >= WHITENESS_LEVEL),
            autocorrelation=test["autocorrelation"],
            band_95=1.959963984540054 / np.sqrt(residual.size),
        ),
    )


def _parameter_rows(fit, k_fit, k_std, params: ServoParams, test_step: float) -> list[FitParameter]:
    """One row per parameter the order-3 fit estimates (T, ξ, T_dm, G, U0) or reports (K_a):
    its nominal value (None where the device does not fix one), estimate, σ from the fit's
    covariance, and the shift (estimate − nominal)/σ. SI units, named in `unit`."""
    std = np.sqrt(np.diag(np.asarray(fit.covariance, dtype=np.float64)))
    rows = [
        ("T", "time constant, eq. (4)", "s", time_constant(params), fit.time_constant, std[0]),
        ("ξ", "damping ratio, eq. (5)", "1", damping_ratio(params), fit.damping_ratio, std[1]),
        (
            "T_dm",
            "torquer time constant",
            "s",
            params.torquer_time_constant,
            fit.torquer_time_constant,
            std[2],
        ),
        (
            "G",
            "step gain K_test·ΔU_test",
            "V",
            closed_loop_test_gain(params) * test_step,
            fit.gain,
            std[3],
        ),
        ("U0", "pre-step level", "V", None, fit.offset, std[4]),
        ("K_a", "scale factor γ T² k_dp k_y", "V/(m/s²)", scale_factor(params), k_fit, k_std),
    ]
    out = []
    for name, description, unit, nominal, estimate, sigma in rows:
        nominal = None if nominal is None else float(nominal)
        estimate, sigma = float(estimate), float(sigma)
        usable = nominal is not None and np.isfinite(sigma) and sigma > 0
        out.append(
            FitParameter(
                name=name,
                description=description,
                unit=unit,
                nominal=nominal,
                estimate=estimate,
                std=sigma,
                shift_in_std=(
                    (estimate - nominal) / sigma if nominal is not None and usable else None
                ),
            )
        )
    return out


def identify_step_record(
    data: StepData,
    params: ServoParams,
    *,
    method: str = "auto",
    gamma: str | float = "exact",
) -> StepIdentification:
    """Identify the scale factor K_a from the first test-signal step of a record.

    **Arguments:**

    - `data`: a validated step record (`read_csv`), t [s], u_test [V], u_out [V].
    - `params`: the nominal device: k_dp k_y for eq. (7), T_f and T_dm for the lag
        correction (16) and the order-3 fit, γ = m l²/J, and the nominal K_a to compare with.
    - `method`: `"auto"` (oscillatory; aperiodic when the response does not oscillate),
        `"oscillatory"` or `"aperiodic"`.
    - `gamma`: `"exact"` (m l²/J of `params`), `"paper"` (3/4) or a number.

    **Returns:** a `StepIdentification`: the segment used (`segment`); the graph-analytic
    estimate (`graph`, an `OscillatoryEstimate` or `AperiodicEstimate`: T or T1..T4, ξ,
    K̂_a and δK_a against the nominal K_a, and what it read off the record: U_ss and the
    crossings t1, t2 and extrema A1, A2, or the inflection); the order-3 least-squares fit
    (`fit`, a `LeastSquaresFit`: T, ξ, T_dm, G, U0, K̂_a ± σ, δK_a, `parameters` (each
    against its nominal value, shift in σ) and `quality` (fit percentage and NRMSE as
    MATLAB's `compare` and `goodnessOfFit` define them, the residual's rms, the noise σ of
    the settled tail, and the Ljung-Box whiteness test of the residual); a `FitFailure`
    when the fit did not succeed); the nominal values (`nominal`); the assumptions; and
    `traces` (the segment's `t_s`, `u_out_V` and, when the fit succeeded, `model_V`, for
    `identification_figure`). Its `to_dict()` is the CLI's JSON (without the traces).
    Raises `DataError` when the record cannot be used, with the reason.
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

    graph: GraphEstimate | None = None
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
            steady, t1, t2 = float(osc.steady_state), float(osc.t1), float(osc.t2)
            before = u_out[ts < step_time]
            initial = before.mean() if before.size else u_out[0]
            direction = 1.0 if steady >= initial else -1.0
            time_a1, time_a2 = _extremum_times(ts, u_out, steady, direction, t1, t2)
            graph = OscillatoryEstimate(
                method="oscillatory (Mironov, Fominov & Maletin, steps (7)-(10))",
                time_constant_s=float(osc.time_constant),
                damping_ratio=float(osc.damping_ratio),
                period_s=t2 - t1,
                scale_factor=float(osc.scale_factor),
                steady_state_V=steady,
                crossing_t1_s=t1,
                crossing_t2_s=t2,
                overshoot_A1_V=float(osc.overshoot),
                overshoot_A1_time_s=time_a1,
                undershoot_A2_V=float(osc.undershoot),
                undershoot_A2_time_s=time_a2,
                dKa_percent=percent(float(osc.scale_factor)),
            )
        else:
            tried.append(("oscillatory", code))
            if method == "oscillatory" or not any(code == c for c in _USE_APERIODIC):
                raise DataError(f"oscillatory method: {_reason(code)}")
    if graph is None:
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
        graph = AperiodicEstimate(
            method="aperiodic (Mironov, Fominov & Maletin, steps 1-10 with the lag "
            "correction (16))",
            T1_s=float(ape.t1),
            T2_s=float(ape.t2),
            T3_s=float(ape.t3),
            T4_s=float(ape.t4),
            time_constant_s=float(ape.time_constant),
            damping_ratio=float(ape.damping_ratio),
            lag_correction_s=lag,
            scale_factor=float(ape.scale_factor),
            steady_state_V=float(ape.steady_state),
            inflection_time_s=step_time + float(ape.inflection_time_measured),
            max_slope_V_per_s=float(ape.max_slope),
            dKa_percent=percent(float(ape.scale_factor)),
        )

    feedback_fraction = float(closed_loop_test_gain(params))
    filter_tc = float(params.filter_time_constant)
    fit = fit_step_response(
        ts,
        u_out,
        order=3,
        step_time=step_time,
        feedback_fraction=feedback_fraction,
        filter_time_constant=filter_tc,
        throw=False,
    )
    model_v = None
    fit_out: LeastSquaresFit | FitFailure
    if fit.result == IdentificationResult.successful:
        k_fit, k_std = scale_factor_from_fit(fit, gain, gamma_value)
        model = _fitted_response(
            jnp.asarray(ts),
            *(
                jnp.asarray(x, ts.dtype)
                for x in (
                    step_time,
                    fit.time_constant,
                    fit.damping_ratio,
                    fit.torquer_time_constant,
                    feedback_fraction,
                    filter_tc,
                    fit.gain,
                    fit.offset,
                )
            ),
        )
        model_v = np.asarray(model, dtype=np.float64)
        n_tail = max(4, int(round(_TAIL_FRACTION * ts.size)))
        fit_out = LeastSquaresFit(
            method="least squares, order 3 (T, ξ, T_dm; known T_f), Levenberg-Marquardt",
            time_constant_s=float(fit.time_constant),
            time_constant_std_s=float(fit.time_constant_std),
            damping_ratio=float(fit.damping_ratio),
            damping_ratio_std=float(fit.damping_ratio_std),
            torquer_time_constant_s=float(fit.torquer_time_constant),
            residual_rms_V=float(fit.residual_rms),
            scale_factor=float(k_fit),
            scale_factor_std=float(k_std),
            dKa_percent=percent(k_fit),
            dKa_std_percent=float(100 * k_std / k_fit),
            torquer_time_constant_std_s=float(np.sqrt(fit.covariance[2, 2])),
            gain_V=float(fit.gain),
            offset_V=float(fit.offset),
            known_feedback_fraction=feedback_fraction,
            known_filter_time_constant_s=filter_tc,
            parameters=_parameter_rows(fit, k_fit, k_std, params, test_step),
            quality=_quality(u_out, model_v, n_tail),
        )
    else:
        fit_out = FitFailure(_reason(fit.result))
    return StepIdentification(
        segment=StepSegment(
            samples=int(stop - start),
            t_start_s=float(ts[0]),
            t_end_s=float(ts[-1]),
            step_time_s=step_time,
            test_step_V=test_step,
            sample_rate_Hz=1.0 / data.sample_period,
        ),
        graph=graph,
        fit=fit_out,
        nominal=NominalValues(
            scale_factor=nominal,
            time_constant_s=float(time_constant(params)),
            damping_ratio=float(damping_ratio(params)),
            torquer_time_constant_s=float(params.torquer_time_constant),
            pickoff_amplifier_gain_V_per_m=gain,
            shape_factor=gamma_value,
        ),
        assumptions={
            "units": "K_a in V/(m/s²); δK_a = 100 (K̂_a − K_a)/K̂_a % against the nominal K_a",
            "segment": "the first change of u_test up to the next one (or the record's end)",
            "steady_state": "mean of the last 20 % of the segment, which must be settled",
            "crossings": "linear interpolation with a noise hysteresis band (6σ of the tail)",
            "aperiodic_slope": f"Savitzky-Golay local cubic over {_SAVGOL_WINDOW} samples",
            "gamma": str(gamma),
            "k_dp_k_y": "from the nominal device (eq. 11 needs a ±U_test stop test)",
            "precision": "float64" if ts.dtype == np.float64 else str(ts.dtype),
            "fit_percent": "MATLAB compare: 100 (1 − ‖y − ŷ‖/‖y − mean(y)‖) over the segment",
            "nrmse": "MATLAB goodnessOfFit 'NRMSE': ‖y − ŷ‖/‖y − mean(y)‖ (0 is perfect)",
            "noise_std": "std(Δu)/√2, successive differences of the last 20 % of the "
            "segment (settled)",
            "whiteness": f"Ljung-Box over {WHITENESS_LAGS} lags of the residual y − ŷ, no "
            f"degrees of freedom removed for the fit; white when p ≥ {WHITENESS_LEVEL:g}",
        },
        traces=StepTraces(t_s=ts, u_out_V=u_out, model_V=model_v),
    )


def identify_step_records(
    datasets: list[StepData],
    params: ServoParams,
    *,
    method: str = "auto",
    gamma: str | float = "exact",
) -> list[StepIdentification | StopRecordGain]:
    """Several records of one device (the `accel-jax identify A.csv B.csv …` job), in order.

    A record whose test levels drive the pendulum onto its stops (max |u_test| · K_test at
    least half the output at a stop, k_dp k_y h_max / 2) gives k_dp k_y by eq. (11):
    a `StopRecordGain` (the values of `stop_record_gain`); every other record is identified
    as by `identify_step_record` (a `StepIdentification`). A record that cannot be used
    raises `DataError`.
    """
    reach = 0.5 * float(params.pickoff_gain * params.amplifier_gain * params.stop_displacement)
    k_test = float(closed_loop_test_gain(params))
    results: list[StepIdentification | StopRecordGain] = []
    for data in datasets:
        if float(abs(data.u_test).max()) * k_test >= reach:
            results.append(StopRecordGain(**stop_record_gain(data, params)))
        else:
            results.append(identify_step_record(data, params, method=method, gamma=gamma))
    return results
