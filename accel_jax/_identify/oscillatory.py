"""The oscillatory method (ξ < 1), docs/models.md §1 section 3.1: crossings of the steady-state
line give the period, eq. (8); the overshoot/undershoot ratio gives ξ, eq. (9);
T = √(1 − ξ²)/ω, eq. (10)."""

from __future__ import annotations

from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array

from .record import (
    _CROSSING_FIT_WIDTH,
    _NOISE_SIGMAS,
    IdentificationResult,
    Scalar,
    ScalarLike,
    SeriesLike,
    _fail_if,
    _first,
    _last,
    _parabolic_peak,
    _record_arguments,
    _summarise,
    _validate_record,
)

# ---------------------------------------------------------------------------------------
# Oscillatory method, section 3.1


class OscillatoryEstimate(eqx.Module):
    """Result of `identify_oscillatory` (docs/models.md §1, eqs. (7)-(10)).

    **Fields:**

    - `steady_state`: U_ss [V], the level the response settles to.
    - `t1`, `t2`: the first crossing of the steady-state line after the step and the
        crossing one full period later [s], on the record's clock.
    - `period`: t2 − t1 [s].
    - `angular_frequency`: ω = 2π/(t2 − t1) [rad/s], eq. (8) (the damped frequency).
    - `overshoot`: A1 = max |U − U_ss| between t1 and the middle crossing [V].
    - `undershoot`: A2 = max |U − U_ss| between the middle crossing and t2 [V].
    - `damping_ratio`: ξ = 1/√(1 + π²/ln²(A1/A2)), eq. (9).
    - `time_constant`: T = √(1 − ξ²)/ω [s], eq. (10).
    - `scale_factor`: K̂_a = γ T² k_dp k_y [V/(m/s²)], eq. (7).
    - `result`: an `IdentificationResult`; the numbers are finite placeholders unless it is
        `successful`.
    """

    steady_state: Scalar
    t1: Scalar
    t2: Scalar
    period: Scalar
    angular_frequency: Scalar
    overshoot: Scalar
    undershoot: Scalar
    damping_ratio: Scalar
    time_constant: Scalar
    scale_factor: Scalar
    result: IdentificationResult


def _crossing(ts, deviation, label, fit_width, k, exists, crossing):
    """Time of a hysteresis transition's zero crossing (see `_transitions`).

    The transition completes at sample k (first beyond the far band edge); the last sample
    before it beyond the near edge is a (between them all samples are inside the band). The
    bracketing pair j, j + 1 is the first sign change of the deviation after a. A straight
    line is fitted by weighted least squares to the pair (weight 1) and to the samples of
    a..k whose deviation d is within w = `fit_width` (12σ, twice the band's noise part) of
    zero, with weight (1 − (d/w)²)², vanishing at ±w. For a noiseless record w = 0 (or far
    narrower than one sample's change), so the pair is all that counts and the fit is
    linear interpolation between the bracketing samples (error O(dt² U''/U')); with noise
    it averages over the band instead of trusting one noisy pair.

    The weights are continuous (C¹) in the samples, and the pair changes only where a sample
    crosses zero, where both pairs give that sample's time: the crossing time is a
    continuous, piecewise-smooth function of the record (kinks where a sample crosses the
    line), and its autodiff derivative is that of the interpolation. An unweighted fit over
    a..k instead jumped by O(dt² U''/U') each time a sample entered or left the band, and
    finite differences across such a jump disagreed with the gradient.
    """
    index = jnp.arange(ts.shape[0], dtype=jnp.int32)
    k = jnp.where(exists, k, 1)
    # The last sample outside the band before k (it lies beyond the near edge: had one
    # been beyond the far edge, the transition would have completed there).
    a, _ = _last((index < k) & (label != 0))
    return _fit_crossing(ts, deviation, fit_width, a, k, crossing)


def _transitions(label):
    """The first two transitions of the Schmitt trigger on `label` (+1/−1 beyond the band's
    upper/lower edge, 0 inside), whose state starts at −1 (`label[0]` is −1).

    The state is the label of the last sample outside the band; it changes to +1 at the
    first sample labelled +1 (k₁) and back to −1 at the first sample labelled −1 after k₁
    (k₂). Returns (k₁, k₁ exists, k₂, k₂ exists); an index that does not exist is 0. Two
    masked arg-max reductions: the same indices as a forward fill of the state (cumulative
    max, gather, cumulative count of changes) at a fraction of the cost on XLA:CPU, where
    cumulative scans are several passes each.
    """
    index = jnp.arange(label.shape[0], dtype=jnp.int32)
    up = label > 0
    k1, has_1 = _first(up)
    down = (label < 0) & (index > k1) & has_1
    k2, has_2 = _first(down)
    return k1, has_1, k2, has_2


def _rising_crossing(ts, deviation, band, fit_width, below, has_below, limit, crossing):
    """The upward zero crossing that ends the first full period (t2), and whether it exists.

    After the second hysteresis transition at sample `below` (the signal has gone below
    −band; `has_below` says whether it exists), t2 is the first upward sign change of the
    deviation before sample `limit`. The third transition
    (rising above +band) is not required: for ξ ≳ 0.75 the overshoot after t2 is below the
    noise (at ξ = 0.77 it is 1.2e-5 of the step), while the crossing itself is still steep
    (the signal rises from the undershoot A2). The fit window runs from the last sample
    below −band to the first above +band, or, where there is none, as far past the sign
    change as it began before it; with the third transition present this is exactly the
    hysteresis crossing of `_crossing`.
    """
    n = ts.shape[0]
    index = jnp.arange(n, dtype=jnp.int32)
    rises = jnp.concatenate([(deviation[:-1] < 0) & (deviation[1:] >= 0), jnp.zeros(1, bool)])
    candidate = rises & (index >= below) & (index + 1 < limit)
    first, found = _first(candidate)
    exists = has_below & found
    j = jnp.where(exists, first, 1)
    a, _ = _last((index <= j) & (deviation < -band))
    above = (index > j) & (deviation > band)
    first_above, any_above = _first(above)
    k_far = jnp.where(any_above, first_above, n - 1)
    k = jnp.minimum(k_far, jnp.minimum(j + 1 + (j - a), n - 1))
    k = jnp.maximum(k, j + 1)
    return _fit_crossing(ts, deviation, fit_width, a, k, crossing), exists


def _add(left, right):
    return tuple(a + b for a, b in zip(left, right, strict=True))


@jax.custom_jvp
def _weighted_moments(weight, x, y):
    """(Σw, Σwx, Σwy, Σwx², Σwxy) over the last axis, in one pass.

    One variadic reduction: five `jnp.sum`s sharing the products w·x and w·y made XLA:CPU
    write those products out and reduce each separately, ten times slower (46 µs against
    4 µs per 5 001-sample record; `benchmarks/bench.py` profiles it). The sums are the
    same up to summation order (rounding). Differentiable: the JVP below is written with
    plain sums, which JAX can transpose for reverse mode.
    """
    wx, wy = weight * x, weight * y
    operands = (weight, wx, wy, wx * x, wx * y)
    zero = jnp.zeros((), weight.dtype)
    return jax.lax.reduce(operands, (zero,) * 5, _add, (weight.ndim - 1,))


@_weighted_moments.defjvp
def _weighted_moments_jvp(primals, tangents):
    weight, x, y = primals
    d_weight, d_x, d_y = tangents
    d_wx = d_weight * x + weight * d_x
    terms = (
        d_weight,
        d_wx,
        d_weight * y + weight * d_y,
        d_wx * x + weight * x * d_x,
        d_wx * y + weight * x * d_y,
    )
    return _weighted_moments(weight, x, y), tuple(jnp.sum(t, axis=-1) for t in terms)


def _fit_crossing(ts, deviation, fit_width, a, k, crossing):
    """Weighted straight-line zero crossing over samples a..k (see `_crossing`)."""
    index = jnp.arange(ts.shape[0], dtype=jnp.int32)
    window = (index >= a) & (index <= k)
    return _fit_line(ts, deviation, window, index < k, ts[a], ts[k], fit_width, crossing)


def _fit_line(t, d, window, before_k, t_a, t_k, fit_width, crossing):
    """The fit of `_fit_crossing` on samples t, d (the whole record, or a window of it):
    `window` marks a..k, `before_k` the samples before k."""
    position = jnp.arange(t.shape[0], dtype=jnp.int32)
    # The deviations at a and k lie beyond opposite band edges, so a sign change exists.
    positive = d >= 0
    sign_change = jnp.concatenate([positive[1:] != positive[:-1], jnp.zeros(1, bool)])
    j = jnp.argmax(window & before_k & sign_change)
    pair = (position == j) | (position == j + 1)
    ratio = d / jnp.where(fit_width > 0, fit_width, 1.0)
    near = window & (fit_width > 0) & (jnp.abs(ratio) < 1)
    weight = pair + jnp.where(near, (1 - ratio**2) ** 2, 0.0)
    x = jnp.where(weight > 0, t - t_k, 0.0)  # centred on t_k for conditioning
    y = jnp.where(weight > 0, d, 0.0)
    sw, sx, sy, sxx, sxy = _weighted_moments(weight, x, y)
    denominator = sw * sxx - sx * sx
    slope = (sw * sxy - sx * sy) / jnp.where(denominator > 0, denominator, 1.0)
    intercept = (sy - slope * sx) / sw
    safe_slope = jnp.where(slope != 0, slope, 1.0)
    t_cross = jnp.clip(t_k - intercept / safe_slope, t_a, t_k)
    if crossing == "nearest":
        j = jnp.argmin(jnp.where(window, jnp.abs(t - t_cross), jnp.inf))
        t_cross = t[j]
    return t_cross


def _window(length: int, end, n: int):
    """Sample indices end − length + 1 … end, clipped into the record, and which are real
    (not clipped)."""
    raw = end - length + 1 + jnp.arange(length, dtype=jnp.int32)
    return jnp.clip(raw, 0, n - 1), raw >= 0


def _last_before(mask_at, end, length: int, n: int):
    """`_last` of a mask over samples 0 … end, searched in the `length` samples ending at
    `end`: (index, 0 when none; exact: True when it is `_last` of the whole mask). Exact when
    found in the window, or when the window reaches sample 0 (then there is none)."""
    idx, real = _window(length, end, n)
    local, found = _last(real & mask_at(idx))
    return jnp.where(found, idx[local], 0), found | (end - length + 1 <= 0)


def _fit_crossing_window(ts, deviation, fit_width, a, k, crossing, length: int):
    """`_fit_crossing` over the `length` samples ending at k: the same fit (the same
    weights, summed in another order: equal to rounding) whenever k − a < length."""
    idx, real = _window(length, k, ts.shape[0])
    window = real & (idx >= a)
    return _fit_line(ts[idx], deviation[idx], window, idx < k, ts[a], ts[k], fit_width, crossing)


def _crossing_window(ts, deviation, label, fit_width, k, exists, crossing, length: int):
    """`_crossing` from the `length` samples before the transition: (time, exact)."""
    n = ts.shape[0]
    k = jnp.where(exists, k, 1)
    a, exact = _last_before(lambda idx: (idx < k) & (label[idx] != 0), k, length, n)
    return _fit_crossing_window(ts, deviation, fit_width, a, k, crossing, length), exact


def _rising_crossing_window(
    ts, deviation, band, fit_width, below, has_below, limit, crossing, length: int
):
    """`_rising_crossing` with its fit window searched within `length` samples of the sign
    change: (time, exists, exact). Exact when the last sample below −band lies within
    `length` samples before it: then the window ends within 2·length − 1 samples of its
    start, and a first sample above +band further on than `length` cannot end it."""
    n = ts.shape[0]
    index = jnp.arange(n, dtype=jnp.int32)
    rises = jnp.concatenate([(deviation[:-1] < 0) & (deviation[1:] >= 0), jnp.zeros(1, bool)])
    candidate = rises & (index >= below) & (index + 1 < limit)
    first, found = _first(candidate)
    exists = has_below & found
    j = jnp.where(exists, first, 1)
    a, exact = _last_before(lambda idx: deviation[idx] < -band, j, length, n)
    ahead = j + 1 + jnp.arange(length, dtype=jnp.int32)
    above = (ahead < n) & (deviation[jnp.clip(ahead, 0, n - 1)] > band)
    local, any_above = _first(above)
    k_far = jnp.where(any_above, ahead[local], n - 1)
    k = jnp.minimum(k_far, jnp.minimum(j + 1 + (j - a), n - 1))
    k = jnp.maximum(k, j + 1)
    t2 = _fit_crossing_window(ts, deviation, fit_width, a, k, crossing, 2 * length)
    return t2, exists, exact


def _largest_between(ts, signed_deviation, start, stop, extremum):
    """The largest sample of `signed_deviation` strictly between times start and stop (its
    parabolic vertex for "parabolic"), 0 when no sample lies between. The largest sample is
    a max reduction, not an arg-max and a gather: XLA:CPU vectorises the first, and the
    two gave ~3 µs against ~20 µs per 5 001-sample record (docs/performance.md)."""
    inside = (ts > start) & (ts < stop)
    masked = jnp.where(inside, signed_deviation, -jnp.inf)
    if extremum == "parabolic":
        n = ts.shape[0]
        j = jnp.argmax(masked)
        y_minus = signed_deviation[jnp.maximum(j - 1, 0)]
        y_plus = signed_deviation[jnp.minimum(j + 1, n - 1)]
        _, peak = _parabolic_peak(y_minus, signed_deviation[j], y_plus)
        # Some sample inside ⟺ the arg-max (of finite values inside, −∞ outside) is inside.
        return jnp.where(inside[j], peak, 0.0)
    # The deviations are finite (`_summarise` replaces a non-finite record), so the
    # largest is −∞ exactly when no sample lies between.
    peak = jnp.max(masked)
    return jnp.where(peak > -jnp.inf, peak, 0.0)


@eqx.filter_jit
def _identify_oscillatory(
    ts,
    u,
    pickoff_amplifier_gain,
    shape_factor,
    step_time,
    steady_state,
    saturation_level,
    n_tail: int,
    crossing: str,
    extremum: str,
    period_from: str,
    throw: bool,
) -> OscillatoryEstimate:
    estimate, _ = _oscillatory_estimate(
        ts,
        u,
        pickoff_amplifier_gain,
        shape_factor,
        step_time,
        steady_state,
        saturation_level,
        n_tail,
        crossing,
        extremum,
        period_from,
        None,
    )
    return _fail_if(estimate.result, estimate, throw)


def _oscillatory_estimate(
    ts,
    u,
    pickoff_amplifier_gain,
    shape_factor,
    step_time,
    steady_state,
    saturation_level,
    n_tail: int,
    crossing: str,
    extremum: str,
    period_from: str,
    window: int | None,
) -> tuple[OscillatoryEstimate, Array]:
    """The estimate, and whether it is exact. `window=None`: over the whole record, always
    exact. `window=L` (the Monte Carlo kernel's fast path): each crossing fit is searched
    and summed over ≤ 2L samples about its sign change instead of masked passes over the
    whole record; where that gives the whole-record answer (to rounding) the flag is True,
    else the caller must use `window=None`. The failed estimates' placeholders may differ."""
    R = IdentificationResult
    record = _summarise(ts, u, step_time, steady_state, n_tail, saturation_level)
    ts, band = record.ts, record.band
    n = ts.shape[0]
    index = jnp.arange(n, dtype=jnp.int32)
    # Deviation from the steady state, oriented so the response rises towards zero from
    # below whatever the direction of the step: crossings 1 and 3 go up, crossing 2 down.
    deviation = record.direction * (record.u - record.steady_state)
    label = jnp.where(deviation > band, 1, jnp.where(deviation < -band, -1, 0))
    if step_time is not None:  # None: the step at the first sample (see `_summarise`)
        label = jnp.where(ts >= record.step_time, label, -1)
    label = label.at[0].set(-1)
    # Crossings inside the tail do not count: there the deviation is of the size of the
    # tail's own settling (a not-quite-settled aperiodic record crosses its tail mean
    # there), and U_ss is only defined by the tail.
    label = jnp.where(index < n - n_tail, label, 0)
    # Schmitt trigger: its first two transitions (the state is the label of the last sample
    # outside the band).
    k1, has_1, k2, has_2 = _transitions(label)

    # Width of the crossing fit's weights from the noise alone (not the band's floor), so
    # a noiseless record gives pure linear interpolation. The noise variance comes from the
    # tail's first differences, var(Δu)/2: a tail that still rings (a short record) would
    # otherwise pass its ringing off as noise, widen the fit over the curved stretch about
    # the slow t2 crossing and lengthen the period (+1.1 µs, +0.11 % in K_a at 5 ms of the
    # reference device, issue 24). Computed without jnp.std, whose gradient at σ = 0 (a
    # settled noiseless tail) is NaN.
    tail = record.u[n - n_tail :]
    variance = 0.5 * jnp.mean(jnp.diff(tail) ** 2)
    noisy = variance > 0
    sigma = jnp.where(noisy, jnp.sqrt(jnp.where(noisy, variance, 1.0)), 0.0)
    fit_width = _CROSSING_FIT_WIDTH * _NOISE_SIGMAS * sigma
    if window is None:
        t1 = _crossing(ts, deviation, label, fit_width, k1, has_1, crossing)
        t_mid = _crossing(ts, deviation, label, fit_width, k2, has_2, crossing)
        t2, has_3 = _rising_crossing(
            ts, deviation, band, fit_width, k2, has_2, n - n_tail, crossing
        )
        exact = jnp.array(True)
    else:
        t1, exact_1 = _crossing_window(ts, deviation, label, fit_width, k1, has_1, crossing, window)
        t_mid, exact_2 = _crossing_window(
            ts, deviation, label, fit_width, k2, has_2, crossing, window
        )
        t2, has_3, exact_3 = _rising_crossing_window(
            ts, deviation, band, fit_width, k2, has_2, n - n_tail, crossing, window
        )
        exact = exact_1 & exact_2 & exact_3
    overshoot = _largest_between(ts, deviation, t1, t_mid, extremum)
    undershoot = _largest_between(ts, -deviation, t_mid, t2, extremum)

    decaying = (undershoot > 0) & (overshoot > undershoot)
    ok = has_3 & decaying
    # Zeros of e^{−at}(A cos ωt + B sin ωt) are exactly π/ω apart, so for the second-order
    # response the half period between the two steep crossings measures the same ω.
    measured = 2 * (t_mid - t1) if period_from == "half" else t2 - t1
    period = jnp.where(ok, measured, 1.0)
    angular_frequency = 2 * jnp.pi / period  # eq. (8)
    log_decrement = jnp.log(jnp.where(ok, overshoot / jnp.where(ok, undershoot, 1.0), 2.0))
    # eq. (9) written as L/√(L² + π²): the same value, finite as L → 0.
    damping_ratio = log_decrement / jnp.sqrt(log_decrement**2 + jnp.pi**2)
    time_constant = jnp.sqrt(1 - damping_ratio**2) / angular_frequency  # eq. (10)
    scale_factor = shape_factor * time_constant**2 * pickoff_amplifier_gain  # eq. (7)

    result = R.where(decaying, R.successful, R.not_decaying)
    result = R.where(has_3, result, R.too_few_crossings)
    result = R.where(has_1, result, R.not_oscillatory)
    common = record.common
    result = R.where(common == R.successful, result, common)

    estimate = OscillatoryEstimate(
        steady_state=record.steady_state,
        t1=t1,
        t2=t2,
        period=period,
        angular_frequency=angular_frequency,
        overshoot=overshoot,
        undershoot=undershoot,
        damping_ratio=damping_ratio,
        time_constant=time_constant,
        scale_factor=scale_factor,
        result=result,
    )
    return estimate, exact


def _check_options(crossing: str, extremum: str, period: str) -> None:
    """The static settings of `identify_oscillatory` (and of the Monte Carlo kernel)."""
    if crossing not in ("linear", "nearest"):
        raise ValueError(f"crossing must be 'linear' or 'nearest', got {crossing!r}.")
    if extremum not in ("sample", "parabolic"):
        raise ValueError(f"extremum must be 'sample' or 'parabolic', got {extremum!r}.")
    if period not in ("full", "half"):
        raise ValueError(f"period must be 'full' or 'half', got {period!r}.")


def identify_oscillatory(
    ts: SeriesLike,
    u_out: SeriesLike,
    *,
    pickoff_amplifier_gain: ScalarLike,
    shape_factor: ScalarLike,
    step_time: ScalarLike | None = None,
    steady_state: ScalarLike | None = None,
    tail_fraction: float = 0.2,
    crossing: Literal["linear", "nearest"] = "linear",
    extremum: Literal["sample", "parabolic"] = "sample",
    period: Literal["full", "half"] = "full",
    saturation_level: ScalarLike | None = None,
    throw: bool = True,
) -> OscillatoryEstimate:
    """Scale factor from an oscillatory step response (ξ < 1), docs/models.md §1 section 3.1.

    The deviation from the steady state crosses the steady-state line at t1, half a period
    later, and at t2 one period after t1: ω = 2π/(t2 − t1) (8); A1, A2 are the overshoot
    and undershoot between these crossings: ξ = 1/√(1 + π²/ln²(A1/A2)) (9);
    T = √(1 − ξ²)/ω (10); K̂_a = γ T² k_dp k_y (7). The step may go up or down.

    Crossings are counted with hysteresis: a crossing is complete only when the deviation
    has gone from below −b to above +b (or back), b = 6σ + 1e-6·|step|, σ the standard
    deviation of the tail, so noise chatter around the line is not counted. The last
    crossing, t2, only needs the deviation to have been below −b: for ξ ≳ 0.75 the
    overshoot after t2 is below the noise. Its time comes
    from a weighted straight-line fit to the two samples bracketing the line and, with
    weights tapering to zero at 12σ', the samples near it, σ' the tail's white-noise level
    from its first differences (noiseless: linear interpolation between the bracketing
    samples, even when the tail still rings). The estimate is a continuous, piecewise-smooth
    function of the record, so `jax.grad` through it matches finite differences taken
    without crossing a kink (a sample passing the line or a new largest sample).

    **Arguments:**

    - `ts`: sample times [s], strictly increasing, shape `(n,)`.
    - `u_out`: output voltage [V], shape `(n,)`. The pre-step level is the mean of the
        samples before `step_time` (`u_out[0]` when there are none).
    - `pickoff_amplifier_gain`: k_dp k_y [V/m], e.g. from `pickoff_gain_from_stops`.
    - `shape_factor`: γ = m l²/J (or the paper's 3/4).
    - `step_time`: time the test signal was applied [s]; default `ts[0]`.
    - `steady_state`: U_ss [V]; default the mean of the last `tail_fraction` of the record
        (which must then be settled, else `too_short`).
    - `tail_fraction`: fraction of the record used for U_ss and the noise σ (static).
    - `crossing`: `"linear"` (interpolated crossing times) or `"nearest"` (the sample
        nearest to it) (static).
    - `extremum`: `"sample"` (largest sample) or `"parabolic"` (vertex of the parabola
        through the largest sample and its neighbours, uniform spacing assumed) (static).
    - `period` (static): `"full"`, the paper's t2 − t1; or `"half"`, 2(t_mid − t1) from
        the first two crossings. Both are exact for a second-order response (its zero
        crossings are exactly half a period apart). With noise at high ξ the crossing t2
        is shallow (the signal rises from the small undershoot A2 towards a next
        overshoot below the noise) and its time scatters, while t1 and t_mid stay steep:
        at ξ = 0.8 and noise 1e-5 of the step, "full" is biased by −6.5 ± 2.8 % in the
        period and "half" by well under 0.1 %. A lag (T_dm, T_f) makes the early crossings
        slightly non-periodic, so compare both on your device.
    - `saturation_level`: optional rail [V]; any |U| at or above it flags `saturated`.
        Without it, a flat top at the record's extreme is flagged.
    - `throw`: raise on failure (default); `False` returns the result code instead.

    **Returns:**

    An `OscillatoryEstimate` (its `t2` is the measured t2 whichever `period` is used).
    """
    n_tail = _validate_record("identify_oscillatory", ts, u_out, tail_fraction)
    _check_options(crossing, extremum, period)
    head, tail, _ = _record_arguments(
        ts, u_out, pickoff_amplifier_gain, shape_factor, step_time, steady_state, saturation_level
    )
    return _identify_oscillatory(
        *head,
        *tail,
        n_tail,
        crossing,
        extremum,
        period,
        throw,
    )
