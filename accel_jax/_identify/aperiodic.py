"""The aperiodic method (ξ > 1), docs/models.md §1 section 3.2: the tangent at the maximum slope
gives T1 = T3 + T4 and the tangent estimate T2 = √(T3 T4), eqs. (13)-(15); T2 is refined
by solving t_inflection(T1, T2) = T0 (step 8) with a root finder; lag correction (16)."""

from __future__ import annotations

from typing import Literal

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .._checks import check_uniform_grid
from .record import (
    _CRITICAL_TOLERANCE,
    IdentificationResult,
    Scalar,
    ScalarLike,
    SeriesLike,
    Values,
    ValuesLike,
    _fail_if,
    _parabolic_peak,
    _record_arguments,
    _summarise,
    _validate_record,
)

# ---------------------------------------------------------------------------------------
# Aperiodic method, section 3.2


class AperiodicEstimate(eqx.Module):
    """Result of `identify_aperiodic` (docs/models.md §1, eqs. (12)-(16), steps 1-10).

    W_test = K_test/((T3 p + 1)(T4 p + 1)) = K_test/(T2² p² + T1 p + 1), T3 ≥ T4. All times
    are measured from the step time.

    **Fields:**

    - `steady_state`: U_ss [V].
    - `max_slope`: tg α, the steepest slope dU/dt [V/s], negative for a step down
        (vertex of the parabola through the peak of the central-difference derivative and
        its neighbours, locally uniform spacing assumed).
    - `inflection_time_measured`: time of the largest slope after the step [s].
    - `inflection_time`: T0 = measured − lag_correction [s], eq. (16).
    - `t1`: T1 = (U_ss − U0)/tg α = T3 + T4 [s] (steps 3, 5; exact for this model), U0 the
        output at the inflection relative to the pre-step level.
    - `t4_tangent`: the paper's T4 = T0 − U0/tg α [s] (step 4, where the tangent meets the
        initial level; an approximation).
    - `t2_initial`: √(T3 T4) from the tangent values, eq. (15) (step 7) [s].
    - `t2`: refined T2 [s]: the root of t_inflection(T1, T2) = T0 (step 8).
    - `t3`, `t4`: T1/2 ± √(T1²/4 − T2²) with the refined T2 [s].
    - `time_constant`: T = refined T2 [s], eq. (4).
    - `damping_ratio`: ξ = T1/(2 T2).
    - `root_residual`: t_inflection(T1, T2) − T0 at the returned T2 [s].
    - `scale_factor`: K̂_a = γ T2² k_dp k_y [V/(m/s²)], eq. (7).
    - `result`: an `IdentificationResult`.
    """

    steady_state: Scalar
    max_slope: Scalar
    inflection_time_measured: Scalar
    inflection_time: Scalar
    t1: Scalar
    t4_tangent: Scalar
    t2_initial: Scalar
    t2: Scalar
    t3: Scalar
    t4: Scalar
    time_constant: Scalar
    damping_ratio: Scalar
    root_residual: Scalar
    scale_factor: Scalar
    result: IdentificationResult


def inflection_time_ratio(ratio: ValuesLike) -> Values:
    """t_inflection/T1 of the step response of 1/((T3 p + 1)(T4 p + 1)), given r = 2 T2/T1.

    With T3,4 = T1/2 (1 ± q), q = √(1 − r²): t_inflection = T3 T4 ln(T3/T4)/(T3 − T4)
    = T1 r² atanh(q)/(2q) (the paper's recurrence of step 8). Increases monotonically
    from 0 (r → 0) to 1/2 (r = 1, ξ = 1, t_inflection = T2).

    **Arguments:**

    - `ratio`: r = 2 T2/T1 = 1/ξ in (0, 1].

    **Returns:**

    t_inflection/T1, dimensionless.
    """
    ratio = jnp.asarray(ratio)
    r = jnp.clip(ratio, jnp.finfo(ratio.dtype).tiny, 1.0)
    q = jnp.sqrt(jnp.maximum((1 - r) * (1 + r), 0.0))
    near_critical = q < 1e-3
    q_safe = jnp.where(near_critical, 0.5, q)
    r_safe = jnp.where(near_critical, np.sqrt(0.75), r)
    # atanh(q) = ln((1 + q)/r) is exact here and, unlike atanh, stays finite as r → 0.
    atanh_over_q = jnp.where(
        near_critical,
        1 + q**2 / 3 + q**4 / 5,
        (jnp.log1p(q_safe) - jnp.log(r_safe)) / q_safe,
    )
    return 0.5 * r**2 * atanh_over_q


def _central_derivative(ts, v, smoothing_window: int):
    interior = (v[2:] - v[:-2]) / (ts[2:] - ts[:-2])
    first = (v[1] - v[0]) / (ts[1] - ts[0])
    last = (v[-1] - v[-2]) / (ts[-1] - ts[-2])
    derivative = jnp.concatenate([first[None], interior, last[None]])
    if smoothing_window > 1:
        kernel = jnp.full(smoothing_window, 1.0 / smoothing_window, derivative.dtype)
        derivative = jnp.convolve(derivative, kernel, mode="same")
    return derivative


_SAVGOL_ORDER = 3


def _savgol_kernels(window: int) -> tuple[np.ndarray, np.ndarray]:
    """Value and first-derivative weights of a centred local cubic least-squares fit.

    Row j of pinv(V), V[i, p] = i**p for i = -m..m, gives the fitted p-th Taylor coefficient
    at the centre; computed in float64 NumPy (static, trace time). The derivative weights are
    per sample interval.
    """
    half = window // 2
    offsets = np.arange(-half, half + 1, dtype=np.float64)
    vander = offsets[:, None] ** np.arange(_SAVGOL_ORDER + 1)[None, :]
    pinv = np.linalg.pinv(vander)
    return pinv[0], pinv[1]


def _savgol(ts, v, window: int):
    """Smoothed value and slope by a sliding local cubic fit (uniform grid assumed).

    Exact for cubic polynomials, so at an inflection (where the slope is quadratic in t) the
    slope peak is unbiased to O(dt⁴ f⁽⁵⁾) instead of the O(w²) bias a moving average of the
    slope has. Edge samples (within window/2 of either end) are not valid and must not be
    searched.
    """
    value_w, slope_w = _savgol_kernels(window)
    dt = (ts[-1] - ts[0]) / (ts.shape[0] - 1)
    # jnp.convolve flips the kernel; the weights are for offsets −m..m, so flip them first.
    value = jnp.convolve(v, jnp.asarray(value_w[::-1], v.dtype), mode="same")
    slope = jnp.convolve(v, jnp.asarray(slope_w[::-1], v.dtype), mode="same") / dt
    return value, slope


@eqx.filter_jit
def _identify_aperiodic(
    ts,
    u,
    pickoff_amplifier_gain,
    shape_factor,
    lag_correction,
    step_time,
    steady_state,
    saturation_level,
    n_tail: int,
    derivative_method: str,
    smoothing_window: int,
    throw: bool,
) -> AperiodicEstimate:
    R = IdentificationResult
    record = _summarise(ts, u, step_time, steady_state, n_tail, saturation_level)
    ts, band, dtype = record.ts, record.band, record.u.dtype
    n = ts.shape[0]
    index = jnp.arange(n)
    after = ts >= record.step_time
    # Oriented rise from the pre-step level: 0 → V_ss > 0 whatever the step direction.
    rise = record.direction * (record.u - record.initial)
    rise_ss = record.amplitude
    # Overshoot before the tail only: a monotone response that has not quite settled rises
    # above its tail mean inside the tail.
    before_tail = after & (index < n - n_tail)
    overshoots = jnp.any(before_tail & (record.direction * (record.u - record.steady_state) > band))

    if derivative_method == "savgol":
        smooth_rise, derivative = _savgol(ts, rise, smoothing_window)
    else:
        smooth_rise, derivative = rise, _central_derivative(ts, rise, smoothing_window)
    edge = smoothing_window // 2 + 1
    searchable = after & (index >= edge) & (index < n - edge)
    k = jnp.argmax(jnp.where(searchable, derivative, -jnp.inf))
    k = jnp.clip(k, 1, n - 2)
    offset, max_slope = _parabolic_peak(derivative[k - 1], derivative[k], derivative[k + 1])
    t_peak = ts[k] + offset * 0.5 * (ts[k + 1] - ts[k - 1])
    max_slope = jnp.where(max_slope > 0, max_slope, 1.0)
    # The curve is straight at the inflection, so linear interpolation of U there is exact
    # to O(dt³) (of the locally fitted curve for "savgol", which also averages the noise).
    rise_at_peak = jnp.interp(t_peak, ts, smooth_rise)
    inflection_time_measured = t_peak - record.step_time
    inflection_time = inflection_time_measured - lag_correction  # eq. (16)

    t1 = (rise_ss - rise_at_peak) / max_slope  # steps 3, 5
    t4_tangent = inflection_time - rise_at_peak / max_slope  # step 4
    t3_tangent = t1 - t4_tangent  # step 6
    t2_initial = jnp.sqrt(jnp.maximum(t3_tangent * t4_tangent, 0.0))  # step 7, eq. (15)

    # Step 8: with T1 fixed, t_inflection(T1, T2) = T0 for r = 2T2/T1 ∈ (0, 1]. The ratio
    # T0/T1 must lie in (0, 1/2]; within _CRITICAL_TOLERANCE above 1/2 it is ξ = 1.
    safe_t1 = jnp.where(t1 > 0, t1, 1.0)
    ratio = inflection_time / safe_t1
    critical = 0.5 * (1 + _CRITICAL_TOLERANCE)
    has_root = (t1 > 0) & (ratio > 0) & (ratio <= critical)
    target = jnp.clip(jnp.where(has_root, ratio, 0.25), 0.0, 0.5)
    eps = float(jnp.finfo(dtype).eps)
    solver = optx.Bisection(rtol=64 * eps, atol=64 * eps, flip=False)
    r0 = jnp.clip(2 * t2_initial / safe_t1, 0.0, 1.0)
    solution = optx.root_find(
        lambda r, target: inflection_time_ratio(r) - target,
        solver,
        r0,
        args=target,
        options=dict(lower=jnp.zeros((), dtype), upper=jnp.ones((), dtype)),
        max_steps=256,
        throw=False,
    )
    converged = solution.result == optx.RESULTS.successful
    has_root = has_root & converged
    r = jnp.where(has_root, solution.value, 1.0)
    t2 = 0.5 * r * safe_t1
    root_residual = (inflection_time_ratio(r) - ratio) * safe_t1
    q = jnp.sqrt(jnp.maximum((1 - r) * (1 + r), 0.0))
    t3, t4 = 0.5 * safe_t1 * (1 + q), 0.5 * safe_t1 * (1 - q)
    scale_factor = shape_factor * t2**2 * pickoff_amplifier_gain  # eq. (7), step 10

    result = R.where(has_root, R.successful, R.no_root)
    result = R.where(overshoots, R.not_aperiodic, result)
    common = record.common
    result = R.where(common == R.successful, result, common)

    estimate = AperiodicEstimate(
        steady_state=record.steady_state,
        max_slope=record.direction * max_slope,
        inflection_time_measured=inflection_time_measured,
        inflection_time=inflection_time,
        t1=t1,
        t4_tangent=t4_tangent,
        t2_initial=t2_initial,
        t2=t2,
        t3=t3,
        t4=t4,
        time_constant=t2,
        damping_ratio=1 / r,
        root_residual=root_residual,
        scale_factor=scale_factor,
        result=result,
    )
    return _fail_if(result, estimate, throw)


def identify_aperiodic(
    ts: SeriesLike,
    u_out: SeriesLike,
    *,
    pickoff_amplifier_gain: ScalarLike,
    shape_factor: ScalarLike,
    lag_correction: ScalarLike = 0.0,
    step_time: ScalarLike | None = None,
    steady_state: ScalarLike | None = None,
    tail_fraction: float = 0.2,
    derivative: Literal["central", "savgol"] = "central",
    smoothing_window: int = 1,
    saturation_level: ScalarLike | None = None,
    throw: bool = True,
) -> AperiodicEstimate:
    """Scale factor from an aperiodic step response (ξ > 1), docs/models.md §1 section 3.2.

    Steps 1-10 of the paper: the largest slope tg α of U_out at T0 (corrected for the lags
    by `lag_correction`, eq. (16)); T1 = (U_ss − U0)/tg α = T3 + T4 (exact for the two-
    exponential response); the tangent estimates T4, T3 and T2 = √(T3 T4) (15); then T2
    refined as the root of t_inflection(T1, T2) = T0 (step 8, solved by bisection on
    r = 2T2/T1 ∈ (0, 1] with optimistix; T0 = T1/2 gives ξ = 1 and T2 = T0); and
    K̂_a = γ T2² k_dp k_y (7).

    **Arguments:**

    - `ts`, `u_out`: the record, as in `identify_oscillatory`.
    - `pickoff_amplifier_gain`: k_dp k_y [V/m].
    - `shape_factor`: γ = m l²/J (or 3/4).
    - `lag_correction`: T_f + T_dm [s] subtracted from the measured inflection time (16).
    - `step_time`: time the test signal was applied [s]; default `ts[0]`. Times T0, T4 are
        measured from it.
    - `steady_state`, `tail_fraction`, `saturation_level`, `throw`: as in
        `identify_oscillatory`.
    - `derivative` (static): `"central"` differences, optionally followed by a centred
        moving average of `smoothing_window` samples (1 = none; the average flattens the
        slope peak and biases tg α low, so K̂_a high: +1.4 % at 31 samples on the aperiodic
        reference device); or `"savgol"`, a Savitzky-Golay local cubic least-squares fit
        over `smoothing_window` samples (odd, at least 5) giving both the slope and the
        smoothed U at the inflection: unbiased to O(dt⁴) at the slope peak, the choice for
        noisy records. Both assume (and "savgol" requires) a uniform time grid.
    - `smoothing_window`: width in samples (odd), see `derivative`.

    **Returns:**

    An `AperiodicEstimate`.
    """
    n_tail = _validate_record("identify_aperiodic", ts, u_out, tail_fraction)
    if derivative not in ("central", "savgol"):
        raise ValueError(f"derivative must be 'central' or 'savgol', got {derivative!r}.")
    # Odd, so that the centred moving average does not shift the slope peak by dt/2.
    if not isinstance(smoothing_window, int) or smoothing_window < 1 or smoothing_window % 2 == 0:
        raise ValueError(
            f"smoothing_window must be a positive odd int (samples), got {smoothing_window!r}."
        )
    if derivative == "savgol":
        if smoothing_window < _SAVGOL_ORDER + 2:
            raise ValueError(
                f"derivative='savgol' fits a local cubic: smoothing_window must be at least "
                f"{_SAVGOL_ORDER + 2} samples, got {smoothing_window}."
            )
        check_uniform_grid(ts, "identify_aperiodic(derivative='savgol')")
    if smoothing_window > jnp.shape(ts)[0] // 4:
        raise ValueError(
            f"smoothing_window={smoothing_window} is too wide for a record of "
            f"{jnp.shape(ts)[0]} samples."
        )
    head, tail, dtype = _record_arguments(
        ts, u_out, pickoff_amplifier_gain, shape_factor, step_time, steady_state, saturation_level
    )
    return _identify_aperiodic(
        *head,
        jnp.asarray(lag_correction, dtype),
        *tail,
        n_tail,
        derivative,
        smoothing_window,
        throw,
    )
