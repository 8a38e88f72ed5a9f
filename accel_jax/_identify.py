"""In-flight identification of the scale factor from the test-signal step response.

SPEC.md §1 (Mironov, Fominov & Maletin): a constant test voltage U_test applied to an extra
torquer winding gives the second-order step response of W_test = K_test/(T²p² + 2ξTp + 1).

- Oscillatory case (ξ < 1, section 3.1): crossings of the steady-state line give the period,
  eq. (8); the overshoot/undershoot ratio gives ξ, eq. (9); T = √(1 − ξ²)/ω, eq. (10).
- Aperiodic case (ξ > 1, section 3.2): the tangent at the maximum slope gives T1 = T3 + T4
  and the tangent estimate T2 = √(T3 T4), eqs. (13)-(15); T2 is refined by solving
  t_inflection(T1, T2) = T0 (step 8) with a root finder; lag correction eq. (16).
- k_dp k_y from the outputs on the mechanical stops, eq. (11); K̂_a = γ T² k_dp k_y, eq. (7).
- Beyond the paper: a least-squares fit of the whole record to the second-order model, or to
  the third-order model with the torquer lag T_dm, with parameter covariance.

Every estimator takes one record `(ts, u_out)` of fixed length, is jit-compiled, and is
vmappable over records (`jax.vmap(lambda u: identify_oscillatory(ts, u, ...))(batch)`):
crossings and extrema are found with masks, cumulative sums and argmax, never with
data-dependent shapes. Expected failures (too few crossings, no root, …) are reported as an
`IdentificationResult` code; `throw=True` turns a failure into a runtime error with the
code's message, `throw=False` returns finite placeholder numbers for masking in sweeps.
Precision follows the dtype of the record; times, volts and gains are SI.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Float

from ._checks import check_uniform_grid
from ._params import _concrete

# Shape aliases, defined once: jaxtyping's shape strings inside annotations read as broken
# forward references to linters.
Scalar = Float[Array, ""]
ScalarLike = Float[ArrayLike, ""]
Series = Float[Array, " n"]
SeriesLike = Float[ArrayLike, " n"]
Values = Float[Array, "..."]
ValuesLike = Float[ArrayLike, "..."]
Matrix = Float[Array, "p p"]

_MIN_SAMPLES = 16
# Half-width of the noise band, in standard deviations of the tail: a crossing counts only
# once the deviation has gone from below −band to above +band (hysteresis), and an
# aperiodic record "overshoots" only beyond +band. White Gaussian noise exceeds 6σ with
# probability 1e-9 per sample, so chatter cannot produce a false crossing or overshoot.
_NOISE_SIGMAS = 6.0
# Floor of the band relative to the step, for noiseless records (σ = 0).
_BAND_FLOOR = 1e-6
# The tail counts as settled when the means of its two halves differ by less than this
# fraction of the step (plus their noise): a drifting tail biases U_ss and every crossing.
_SETTLE_TOLERANCE = 1e-3
# A flat top at the record's extreme longer than this fraction of the record is a rail.
_PLATEAU_FRACTION = 0.01
# |T0/T1 − 1/2| within this relative tolerance of the critical ratio counts as ξ = 1.
_CRITICAL_TOLERANCE = 1e-3
# Squarings available to `_expm`: matrices up to 1-norm 2^62.
_MAX_SQUARINGS = 64
# Smallest T_dm/T the order-3 fit represents (the torquer equation divides by it).
_TORQUER_FLOOR = 1e-6
# Half-width of the tapered weights of the crossing-time line fit, in multiples of the
# noise part 6σ of the band: twice it also weighs the samples just beyond the band edges
# (σ = 1e-4 on a 1 V step at 1 MHz: period error 0.8 µs rms, versus 0.9 µs with 1×).
# Without noise (σ = 0) the fit is linear interpolation between the bracketing samples.
_CROSSING_FIT_WIDTH = 2.0


class IdentificationResult(eqx.Enumeration):
    """Outcome of an identification or fit; `successful` or the reason it failed."""

    successful = ""
    non_finite = "The record (ts, u_out, step_time or steady_state) contains NaN or inf."
    no_step = (
        "The record shows no step: |U_ss − U(0)| is within the noise band. Check that the "
        "test signal was applied, and `step_time`."
    )
    too_short = (
        "The record has not settled: the tail (last `tail_fraction` of the record) is not "
        "flat relative to the step. Record for longer, or pass `steady_state`."
    )
    saturated = (
        "The output sits flat at a rail (pendulum on a stop or amplifier saturated): the "
        "linear step-response formulas do not apply. Reduce U_test."
    )
    not_oscillatory = (
        "The response does not oscillate (no overshoot beyond the noise band, ξ ≥ 1): use "
        "identify_aperiodic."
    )
    too_few_crossings = (
        "Fewer than three crossings of the steady-state line (one full period after the "
        "first): record for longer after the step, or the undershoot is below the noise."
    )
    not_decaying = (
        "The undershoot A2 is not smaller than the overshoot A1 (ξ ≤ 0, or noise dominates "
        "the extrema): eq. (9) does not apply."
    )
    not_aperiodic = "The response overshoots its steady state (ξ < 1): use identify_oscillatory."
    no_root = (
        "Step 8 has no root: the (lag-corrected) inflection time T0 is not in (0, T1/2] "
        "(ξ < 1, too large a lag_correction, or too much noise in the slope)."
    )
    fit_not_converged = "The least-squares fit did not converge within max_steps."


# ---------------------------------------------------------------------------------------
# Shared record handling


def _record_dtype(ts, u_out):
    dtype = jnp.result_type(ts, u_out)
    if not jnp.issubdtype(dtype, jnp.floating):
        dtype = jnp.result_type(float)
    return dtype


def _validate_record(name: str, ts, u_out, tail_fraction: float) -> int:
    """Structure checks at call/trace time (tier 1 errors); returns the tail length."""
    ts_shape, u_shape = jnp.shape(ts), jnp.shape(u_out)
    if len(ts_shape) != 1 or len(u_shape) != 1:
        raise ValueError(
            f"{name}: ts and u_out must be 1-D (one record), got shapes {ts_shape} and "
            f"{u_shape}; vmap over a batch of records instead, e.g. "
            f"jax.vmap(lambda u: {name}(ts, u, ...))(batch)."
        )
    if ts_shape != u_shape:
        raise ValueError(
            f"{name}: ts and u_out must have the same length, got {ts_shape[0]} and "
            f"{u_shape[0]} samples."
        )
    n = ts_shape[0]
    if n < _MIN_SAMPLES:
        raise ValueError(f"{name}: the record has {n} samples; at least {_MIN_SAMPLES} are needed.")
    if not 0.0 < tail_fraction <= 0.5:
        raise ValueError(f"{name}: tail_fraction must be in (0, 0.5], got {tail_fraction!r}.")
    concrete_ts = _concrete(ts)
    if concrete_ts is not None and np.all(np.isfinite(concrete_ts)):
        if not np.all(np.diff(concrete_ts) > 0):
            raise ValueError(f"{name}: ts must be strictly increasing.")
    return max(4, int(round(tail_fraction * n)))


def _as_dtype(value, dtype):
    return None if value is None else jnp.asarray(value, dtype=dtype)


def _step_time(step_time, ts, dtype):
    # Always an array (never None) so that passing it or not shares one compilation.
    return jnp.asarray(ts[0] if step_time is None else step_time, dtype)


def _saturation_level(level, dtype):
    return jnp.asarray(jnp.inf if level is None else level, dtype)


class _Record(eqx.Module):
    """One record, sanitised, with the levels and noise band every method uses."""

    ts: Series
    u: Series
    step_time: Scalar
    initial: Scalar  # pre-step level [V]
    steady_state: Scalar  # U_ss [V]
    direction: Scalar  # +1 for a step up, −1 for a step down
    amplitude: Scalar  # |U_ss − U(0)| [V]
    band: Scalar  # half-width of the noise band [V]
    finite: Array
    settled: Array
    saturated: Array
    has_step: Array


def _summarise(ts, u, step_time, steady_state, n_tail, saturation_level) -> _Record:
    n = u.shape[0]
    dtype = u.dtype
    finite = jnp.all(jnp.isfinite(ts)) & jnp.all(jnp.isfinite(u)) & jnp.isfinite(step_time)
    if steady_state is not None:
        finite = finite & jnp.isfinite(steady_state)
    # NaN-free placeholders: with throw=False the result code carries the failure and
    # every number stays finite, so a batch sweep can mask per element.
    index_time = jnp.arange(n, dtype=dtype)
    ts = jnp.where(finite, ts, index_time)
    u = jnp.where(finite, u, jnp.zeros_like(u))
    step_time = jnp.where(finite, step_time, ts[0])

    pre = ts < step_time
    n_pre = jnp.sum(pre, dtype=jnp.int32)  # counts in int32: int64 sums are slow on XLA:CPU
    initial = jnp.where(n_pre > 0, jnp.sum(jnp.where(pre, u, 0)) / jnp.maximum(n_pre, 1), u[0])
    tail = u[n - n_tail :]
    sigma = jnp.std(tail)
    tail_mean = jnp.mean(tail)
    u_ss = tail_mean if steady_state is None else jnp.where(finite, steady_state, tail_mean)
    step = u_ss - initial
    direction = jnp.where(step >= 0, 1.0, -1.0).astype(dtype)
    amplitude = jnp.abs(step)
    quantum = 32 * jnp.finfo(dtype).eps * jnp.max(jnp.abs(u))
    band = _NOISE_SIGMAS * sigma + jnp.maximum(_BAND_FLOOR * amplitude, quantum)
    has_step = amplitude > 2 * band

    if steady_state is None:
        half = n_tail // 2
        drift = jnp.abs(jnp.mean(tail[half:]) - jnp.mean(tail[:half]))
        settled = drift <= _SETTLE_TOLERANCE * amplitude + 8 * sigma / np.sqrt(n_tail)
    else:
        settled = jnp.array(True)

    # A rail shows as a flat top (many samples at exactly the extreme value) before the
    # tail, away from both the initial and the steady-state level.
    region = (ts >= step_time) & (jnp.arange(n, dtype=jnp.int32) < n - n_tail)
    n_region = jnp.sum(region, dtype=jnp.int32)
    min_run = jnp.maximum(3, _PLATEAU_FRACTION * n_region)
    saturated = jnp.array(False)
    for sign in (1.0, -1.0):
        signed = sign * u
        extreme = jnp.max(jnp.where(region, signed, -jnp.inf))
        at_extreme = region & (signed >= extreme - 4 * jnp.finfo(dtype).eps * jnp.abs(extreme))
        away = (jnp.abs(extreme - sign * u_ss) > band) & (jnp.abs(extreme - sign * initial) > band)
        saturated = saturated | ((jnp.sum(at_extreme, dtype=jnp.int32) >= min_run) & away)
    saturated = saturated | jnp.any(jnp.abs(u) >= saturation_level)

    return _Record(
        ts=ts,
        u=u,
        step_time=step_time,
        initial=initial,
        steady_state=u_ss,
        direction=direction,
        amplitude=amplitude,
        band=band,
        finite=finite,
        settled=settled,
        saturated=saturated,
        has_step=has_step,
    )


def _common_result(record: _Record) -> IdentificationResult:
    """The failure codes every method shares; the most fundamental wins (applied last)."""
    R = IdentificationResult
    result = R.where(record.has_step, R.successful, R.no_step)
    result = R.where(record.settled, result, R.too_short)
    # A rail distorts the tail too, so it is reported ahead of "not settled".
    result = R.where(record.saturated, R.saturated, result)
    return R.where(record.finite, result, R.non_finite)


def _parabolic_peak(y_minus, y_zero, y_plus):
    """Vertex (offset in samples, value) of the parabola through three equispaced samples.

    Falls back to the middle sample when the samples are not concave, and keeps the vertex
    within one sample (noise can make the curvature tiny and the extrapolation wild).
    """
    curvature = y_minus - 2 * y_zero + y_plus
    concave = curvature < 0
    safe = jnp.where(concave, curvature, -1.0)
    offset = jnp.where(concave, jnp.clip(0.5 * (y_minus - y_plus) / safe, -1.0, 1.0), 0.0)
    return offset, y_zero - 0.25 * (y_minus - y_plus) * offset


def _fail_if(result: IdentificationResult, token, throw: bool):
    if throw:
        token = result.error_if(token, result != IdentificationResult.successful)
    return token


# ---------------------------------------------------------------------------------------
# Oscillatory method, section 3.1


class OscillatoryEstimate(eqx.Module):
    """Result of `identify_oscillatory` (SPEC.md §1, eqs. (7)-(10)).

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
    a = jnp.max(jnp.where((index < k) & (label != 0), index, 0))
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
    k1, has_1 = jnp.argmax(up), jnp.any(up)
    down = (label < 0) & (index > k1) & has_1
    k2, has_2 = jnp.argmax(down), jnp.any(down)
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
    exists = has_below & jnp.any(candidate)
    j = jnp.where(exists, jnp.argmax(candidate), 1)
    a = jnp.max(jnp.where((index <= j) & (deviation < -band), index, 0))
    above = (index > j) & (deviation > band)
    k_far = jnp.where(jnp.any(above), jnp.argmax(above), n - 1)
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
    n = ts.shape[0]
    index = jnp.arange(n, dtype=jnp.int32)
    window = (index >= a) & (index <= k)
    # The deviations at a and k lie beyond opposite band edges, so a sign change exists.
    positive = deviation >= 0
    sign_change = jnp.concatenate([positive[1:] != positive[:-1], jnp.zeros(1, bool)])
    j = jnp.argmax(window & (index < k) & sign_change)
    pair = (index == j) | (index == j + 1)
    ratio = deviation / jnp.where(fit_width > 0, fit_width, 1.0)
    near = window & (fit_width > 0) & (jnp.abs(ratio) < 1)
    weight = pair + jnp.where(near, (1 - ratio**2) ** 2, 0.0)
    x = jnp.where(weight > 0, ts - ts[k], 0.0)  # centred on t_k for conditioning
    y = jnp.where(weight > 0, deviation, 0.0)
    sw, sx, sy, sxx, sxy = _weighted_moments(weight, x, y)
    denominator = sw * sxx - sx * sx
    slope = (sw * sxy - sx * sy) / jnp.where(denominator > 0, denominator, 1.0)
    intercept = (sy - slope * sx) / sw
    safe_slope = jnp.where(slope != 0, slope, 1.0)
    t_cross = jnp.clip(ts[k] - intercept / safe_slope, ts[a], ts[k])
    if crossing == "nearest":
        j = jnp.argmin(jnp.where(window, jnp.abs(ts - t_cross), jnp.inf))
        t_cross = ts[j]
    return t_cross


def _largest_between(ts, signed_deviation, start, stop, extremum):
    inside = (ts > start) & (ts < stop)
    j = jnp.argmax(jnp.where(inside, signed_deviation, -jnp.inf))
    peak = signed_deviation[j]
    if extremum == "parabolic":
        n = ts.shape[0]
        y_minus = signed_deviation[jnp.maximum(j - 1, 0)]
        y_plus = signed_deviation[jnp.minimum(j + 1, n - 1)]
        _, peak = _parabolic_peak(y_minus, peak, y_plus)
    return jnp.where(jnp.any(inside), peak, 0.0)


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
    R = IdentificationResult
    record = _summarise(ts, u, step_time, steady_state, n_tail, saturation_level)
    ts, band = record.ts, record.band
    n = ts.shape[0]
    index = jnp.arange(n, dtype=jnp.int32)
    # Deviation from the steady state, oriented so the response rises towards zero from
    # below whatever the direction of the step: crossings 1 and 3 go up, crossing 2 down.
    deviation = record.direction * (record.u - record.steady_state)
    label = jnp.where(deviation > band, 1, jnp.where(deviation < -band, -1, 0))
    label = jnp.where(ts >= record.step_time, label, -1).at[0].set(-1)
    # Crossings inside the tail do not count: there the deviation is of the size of the
    # tail's own settling (a not-quite-settled aperiodic record crosses its tail mean
    # there), and U_ss is only defined by the tail.
    label = jnp.where(index < n - n_tail, label, 0)
    # Schmitt trigger: its first two transitions (the state is the label of the last sample
    # outside the band).
    k1, has_1, k2, has_2 = _transitions(label)

    # Width of the crossing fit's weights from the noise alone (not the band's floor), so
    # a noiseless record gives pure linear interpolation. σ is computed here without
    # jnp.std, whose gradient at σ = 0 (a settled noiseless tail) is NaN.
    tail = record.u[n - n_tail :]
    variance = jnp.mean((tail - jnp.mean(tail)) ** 2)
    noisy = variance > 0
    sigma = jnp.where(noisy, jnp.sqrt(jnp.where(noisy, variance, 1.0)), 0.0)
    fit_width = _CROSSING_FIT_WIDTH * _NOISE_SIGMAS * sigma
    t1 = _crossing(ts, deviation, label, fit_width, k1, has_1, crossing)
    t_mid = _crossing(ts, deviation, label, fit_width, k2, has_2, crossing)
    t2, has_3 = _rising_crossing(ts, deviation, band, fit_width, k2, has_2, n - n_tail, crossing)
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
    common = _common_result(record)
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
    return _fail_if(result, estimate, throw)


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
    """Scale factor from an oscillatory step response (ξ < 1), SPEC.md §1 section 3.1.

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
    weights tapering to zero at 12σ, the samples near it (noiseless: linear interpolation
    between the bracketing samples). The estimate is a continuous, piecewise-smooth
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
    if crossing not in ("linear", "nearest"):
        raise ValueError(f"crossing must be 'linear' or 'nearest', got {crossing!r}.")
    if extremum not in ("sample", "parabolic"):
        raise ValueError(f"extremum must be 'sample' or 'parabolic', got {extremum!r}.")
    if period not in ("full", "half"):
        raise ValueError(f"period must be 'full' or 'half', got {period!r}.")
    dtype = _record_dtype(ts, u_out)
    return _identify_oscillatory(
        jnp.asarray(ts, dtype),
        jnp.asarray(u_out, dtype),
        jnp.asarray(pickoff_amplifier_gain, dtype),
        jnp.asarray(shape_factor, dtype),
        _step_time(step_time, ts, dtype),
        _as_dtype(steady_state, dtype),
        _saturation_level(saturation_level, dtype),
        n_tail,
        crossing,
        extremum,
        period,
        throw,
    )


# ---------------------------------------------------------------------------------------
# Aperiodic method, section 3.2


class AperiodicEstimate(eqx.Module):
    """Result of `identify_aperiodic` (SPEC.md §1, eqs. (12)-(16), steps 1-10).

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
    eps = jnp.finfo(dtype).eps
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
    common = _common_result(record)
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
    """Scale factor from an aperiodic step response (ξ > 1), SPEC.md §1 section 3.2.

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
    dtype = _record_dtype(ts, u_out)
    return _identify_aperiodic(
        jnp.asarray(ts, dtype),
        jnp.asarray(u_out, dtype),
        jnp.asarray(pickoff_amplifier_gain, dtype),
        jnp.asarray(shape_factor, dtype),
        jnp.asarray(lag_correction, dtype),
        _step_time(step_time, ts, dtype),
        _as_dtype(steady_state, dtype),
        _saturation_level(saturation_level, dtype),
        n_tail,
        derivative,
        smoothing_window,
        throw,
    )


# ---------------------------------------------------------------------------------------
# k_dp k_y from the stops, eq. (11)


def pickoff_gain_from_stops(
    u_plus: ValuesLike,
    u_minus: ValuesLike,
    h_plus: ValuesLike,
    h_minus: ValuesLike,
) -> Values:
    """k_dp k_y = ½ (U⁺/h⁺ − U⁻/h⁻) [V/m], SPEC.md eq. (11).

    With ±U_test large enough to hold the pendulum on its stops, the output is
    U± = ±k_dp k_y h± + U_offset. Averaging the two slopes cancels the offset exactly when
    h⁺ = h⁻ (in general it leaves ½ U_offset (1/h⁺ − 1/h⁻)).

    **Arguments:**

    - `u_plus`: output on the positive stop [V] (positive).
    - `u_minus`: output on the negative stop [V] (negative).
    - `h_plus`, `h_minus`: the stop displacements as positive magnitudes [m].

    **Returns:**

    k_dp k_y [V/m]. Concrete inputs are checked (`ValueError`); traced ones are not.
    """
    for name, value in (("h_plus", h_plus), ("h_minus", h_minus)):
        concrete = _concrete(value)
        if concrete is not None and not np.all(np.isfinite(concrete) & (concrete > 0)):
            raise ValueError(
                f"pickoff_gain_from_stops: {name} must be a positive magnitude in metres, "
                f"got {concrete!r}."
            )
    plus, minus = _concrete(u_plus), _concrete(u_minus)
    if plus is not None and not np.all(np.isfinite(plus) & (plus > 0)):
        raise ValueError(
            f"pickoff_gain_from_stops: u_plus (output on the + stop) must be positive, got "
            f"{plus!r} V; check the sign convention or swap the arguments."
        )
    if minus is not None and not np.all(np.isfinite(minus) & (minus < 0)):
        raise ValueError(
            f"pickoff_gain_from_stops: u_minus (output on the − stop) must be negative, got "
            f"{minus!r} V; check the sign convention or swap the arguments."
        )
    return 0.5 * (jnp.asarray(u_plus) / h_plus - jnp.asarray(u_minus) / h_minus)


# ---------------------------------------------------------------------------------------
# Least-squares fit of the whole record (beyond the paper)


def _damped_cos_sin(x, damping_ratio):
    """e^{−ξx} cos(βx) and e^{−ξx} sin(βx)/β, β = √(1 − ξ²), for any ξ ≥ 0, x ≥ 0.

    Both are entire in z = β²x² (cos √z and sin √z/√z), so one expression covers ξ < 1,
    ξ = 1 and ξ > 1 (cosh, sinh): a Taylor series near z = 0 and the trigonometric or
    hyperbolic closed form elsewhere, each fed only inputs inside its own branch so that
    values and gradients stay finite at ξ = 1.
    """
    xi = damping_ratio
    z = (1 - xi) * (1 + xi) * x**2
    series = jnp.abs(z) < 1e-3
    decay = jnp.exp(-xi * x)
    cos_series = 1 - z / 2 + z**2 / 24 - z**3 / 720 + z**4 / 40320
    sin_series = 1 - z / 6 + z**2 / 120 - z**3 / 5040 + z**4 / 362880
    # ξ < 1
    oscillatory = z >= 1e-3
    beta = jnp.sqrt(jnp.where(oscillatory, (1 - xi) * (1 + xi), 1.0))
    cos_osc = decay * jnp.cos(beta * x)
    sin_osc = decay * jnp.sin(beta * x) / beta
    # ξ > 1: e^{−ξx}cosh(ax) = ½ e^{−(ξ−a)x}(1 + e^{−2ax}), ξ − a = 1/(ξ + a): no overflow
    # of cosh and no cancellation in ξ − a.
    aperiodic = z <= -1e-3
    a = jnp.sqrt(jnp.where(aperiodic, (xi - 1) * (xi + 1), 1.0))
    a_x = jnp.where(aperiodic, a * x, 1.0)
    slow = jnp.exp(-x / (xi + a))
    cos_ap = 0.5 * slow * (1 + jnp.exp(-2 * a_x))
    sin_ap = -0.5 * slow * jnp.expm1(-2 * a_x) / a
    damped_cos = jnp.where(series, decay * cos_series, jnp.where(oscillatory, cos_osc, cos_ap))
    damped_sin = jnp.where(series, decay * x * sin_series, jnp.where(oscillatory, sin_osc, sin_ap))
    return damped_cos, damped_sin


def second_order_step(
    tau: ValuesLike,
    time_constant: ScalarLike,
    damping_ratio: ScalarLike,
) -> Values:
    """Unit step response of 1/(T²p² + 2ξTp + 1) at times τ after the step (0 for τ ≤ 0).

    s(τ) = 1 − e^{−ξx}(cos βx + ξ sin βx/β), x = τ/T, β = √(1 − ξ²); one smooth
    implementation for ξ < 1, ξ = 1 and ξ > 1 (finite gradients at ξ = 1).

    **Arguments:**

    - `tau`: time since the step [s].
    - `time_constant`: T [s].
    - `damping_ratio`: ξ ≥ 0.

    **Returns:**

    The response, dimensionless.
    """
    tau = jnp.asarray(tau)
    x = jnp.maximum(tau, 0.0) / time_constant
    damped_cos, damped_sin = _damped_cos_sin(x, damping_ratio)
    return jnp.where(tau > 0, 1 - damped_cos - damping_ratio * damped_sin, 0.0)


def _expm(matrix):
    """Matrix exponential of a small matrix: scaling and squaring of a Taylor polynomial.

    The matrix is scaled by 2^-s to 1-norm ≤ 1/4, where the degree-13 Taylor remainder is
    below 0.25^14/14! ≈ 2e-20, then squared s times. Cheaper to compile than the general
    `jax.scipy.linalg.expm` (which carries five Padé orders), and forward- and
    reverse-differentiable.
    """
    norm = jnp.max(jnp.sum(jnp.abs(matrix), axis=-2))
    squarings = jnp.ceil(jnp.log2(jnp.maximum(norm, 1e-300) / 0.25))
    squarings = jax.lax.stop_gradient(jnp.clip(squarings, 0, _MAX_SQUARINGS))
    scaled = matrix * 2.0**-squarings
    identity = jnp.eye(matrix.shape[-1], dtype=matrix.dtype)
    result = identity
    for degree in range(13, 0, -1):  # Horner: I + A(I + A/2(I + A/3(…)))
        result = identity + scaled @ result / degree
    return jax.lax.fori_loop(
        0,
        _MAX_SQUARINGS,
        lambda i, power: jnp.where(i < squarings, power @ power, power),
        result,
    )


def _third_order_step(
    ts,
    step_time,
    time_constant,
    damping_ratio,
    torquer_time_constant,
    feedback_fraction,
    filter_time_constant=0.0,
):
    """Step response of 1/[(T²p² + 2ξTp + 1 − K)(T_dm p + 1) + K] on a uniform grid.

    This is the test-signal transfer function divided by its DC gain K, so it settles to 1.
    In time x = t/T the loop is y'' + 2ξy' + (1 − K)y = m, ε m' = K(u − y) − m with
    ε = T_dm/T (the torquer moment m lags the error); a known output filter 1/(T_f p + 1)
    outside the loop adds ε_f z' = y − z, ε_f = T_f/T, and the output is z (y when
    T_f = 0). Exact discretisation of this companion form for a unit step u: expm of the
    augmented matrix [[A, B], [0, 0]]·h gives the transition Φ and the step-input term Γ
    (Van Loan), then a `lax.scan` over samples.
    """
    dtype = ts.dtype
    k = feedback_fraction
    eps = torquer_time_constant / time_constant
    filtered = filter_time_constant > 0
    eps_f = jnp.where(filtered, filter_time_constant / time_constant, 1.0)
    zero, one = jnp.zeros((), dtype), jnp.ones((), dtype)
    a_matrix = jnp.stack(
        [
            jnp.stack([zero, one, zero, zero]),
            jnp.stack([-(1 - k) * one, -2 * damping_ratio, one, zero]),
            jnp.stack([-k / eps, zero, -1 / eps, zero]),
            jnp.stack([1 / eps_f, zero, zero, -1 / eps_f]),
        ]
    )
    b_vector = jnp.stack([zero, zero, k / eps, zero])
    augmented = jnp.zeros((5, 5), dtype).at[:4, :4].set(a_matrix).at[:4, 4].set(b_vector)

    n = ts.shape[0]
    spacing = (ts[-1] - ts[0]) / (n - 1) / time_constant
    tau = (ts - step_time) / time_constant
    started = tau > 0
    first = jnp.argmax(started)
    first_interval = jnp.where(jnp.any(started), tau[first], 0.0)
    # One batched expm for the regular step and the partial first interval after the step
    # (the step may fall between samples).
    exponentials = jax.vmap(_expm)(
        augmented[None] * jnp.stack([spacing, first_interval])[:, None, None]
    )
    transition, forcing = exponentials[0, :4, :4], exponentials[0, :4, 4]
    forcing_first = exponentials[1, :4, 4]

    def step(state, inputs):
        now_started, was_started = inputs
        advanced = transition @ state + forcing
        new = jnp.where(was_started, advanced, forcing_first)
        new = jnp.where(now_started, new, jnp.zeros_like(new))
        return new, jnp.where(filtered, new[3], new[0])

    was_started = jnp.concatenate([jnp.zeros(1, bool), started[:-1]])
    _, response = jax.lax.scan(step, jnp.zeros(4, dtype), (started, was_started))
    return response / k


class StepFit(eqx.Module):
    """Least-squares fit of a step-response record (beyond the paper).

    Order 2: U(t) = U0 + G s(t − t_step; T, ξ), s the unit step response of
    1/(T²p² + 2ξTp + 1). Order 3: s the unit step response of
    1/[(T²p² + 2ξTp + 1 − K)(T_dm p + 1) + K], K = `feedback_fraction` (the test-signal
    transfer function with the torquer lag, `accel_jax.transfer_function_test_signal`,
    divided by c + k_dm l k_dp k_y and by its DC gain K), so G = K_test U_test in both.

    **Fields:**

    - `time_constant`: T [s].
    - `damping_ratio`: ξ.
    - `torquer_time_constant`: T_dm [s] (order 3; 0 for order 2).
    - `gain`: G = U_ss − U0 [V] (K_test U_test).
    - `offset`: U0, the pre-step level [V].
    - `residual_rms`: root mean square of the residuals [V].
    - `covariance`: covariance of (T, ξ, [T_dm,] G, U0) in those units, σ̂²(JᵀJ)⁻¹ with J
        the Jacobian of the residuals in these parameters at the optimum and
        σ̂² = RSS/(n − p). Shape `(4, 4)` (order 2) or `(5, 5)` (order 3). Non-finite when
        a parameter is not identifiable from the record (singular JᵀJ).
    - `time_constant_std`, `damping_ratio_std`: square roots of its diagonal [s], [-].
    - `result`: an `IdentificationResult` (`fit_not_converged` on failure).
    """

    time_constant: Scalar
    damping_ratio: Scalar
    torquer_time_constant: Scalar
    gain: Scalar
    offset: Scalar
    residual_rms: Scalar
    covariance: Matrix
    time_constant_std: Scalar
    damping_ratio_std: Scalar
    result: IdentificationResult


def _initial_guess(ts, u, step_time, n_tail):
    """(T, ξ) from the moments of the record, valid for any ξ, and the record summary.

    For s(τ), the unit step response of 1/(T²p² + 2ξTp + 1), the Laplace transform of
    1 − s at p → 0 gives M0 = ∫(1 − s)dτ = 2ξT and M1 = ∫τ(1 − s)dτ = T²(4ξ² − 1), so
    T = √(M0² − M1), ξ = M0/(2T). These integrals average the noise, need no crossing or
    inflection (no failure near ξ = 1), and cost two sums. If the record is too short for
    them, the half-rise time (≈ 1.7 T for a well-damped response) is used instead.
    """
    record = _summarise(ts, u, step_time, None, n_tail, jnp.asarray(jnp.inf, u.dtype))
    ts = record.ts
    after = ts >= record.step_time
    amplitude = jnp.where(record.amplitude > 0, record.amplitude, 1.0)
    deficit = jnp.where(after, 1 - record.direction * (record.u - record.initial) / amplitude, 0)
    tau = jnp.where(after, ts - record.step_time, 0.0)
    widths = jnp.diff(ts)
    mean_deficit = 0.5 * (deficit[1:] + deficit[:-1])  # trapezoid rule
    moment0 = jnp.sum(widths * mean_deficit)
    moment1 = jnp.sum(widths * 0.5 * (tau[1:] * deficit[1:] + tau[:-1] * deficit[:-1]))
    square = moment0**2 - moment1
    valid = (moment0 > 0) & (square > 0)
    time_constant = jnp.sqrt(jnp.where(valid, square, 1.0))
    damping = moment0 / (2 * time_constant)

    half = jnp.argmax((deficit <= 0.5) & after)
    spacing = (ts[-1] - ts[0]) / (ts.shape[0] - 1)
    fallback_t = jnp.maximum((ts[half] - record.step_time) / 1.7, 2 * spacing)
    time_constant = jnp.where(valid, time_constant, fallback_t)
    damping = jnp.clip(jnp.where(valid, damping, 0.7), 0.05, 20.0)
    return time_constant, damping, record


@eqx.filter_jit
def _fit_step_response(
    ts,
    u,
    step_time,
    initial,
    feedback_fraction,
    filter_time_constant,
    n_tail: int,
    order: int,
    throw: bool,
    max_steps: int,
) -> StepFit:
    dtype = u.dtype
    guess_t, guess_xi, record = _initial_guess(ts, u, step_time, n_tail)
    ts, u = record.ts, record.u
    if initial is not None:
        guess_t, guess_xi = initial[0], initial[1]
    guess_tdm = 0.1 * guess_t if (initial is None or len(initial) < 3) else initial[2]
    reference_t = guess_t
    scale = jnp.where(record.amplitude > 0, record.amplitude, 1.0)

    # Physical parameters in units of the initial guess, so all columns of J are O(1):
    # (T/T_ref, ξ, [T_dm/T_ref,] G/scale, (U0 − U_initial)/scale).
    def physical_residuals(normalised, _):
        time_constant = reference_t * normalised[0]
        damping = normalised[1]
        gain = scale * normalised[-2]
        offset = record.initial + scale * normalised[-1]
        if order == 2:
            shape = second_order_step(ts - record.step_time, time_constant, damping)
        else:
            tdm = reference_t * normalised[2]
            shape = _third_order_step(
                ts,
                record.step_time,
                time_constant,
                damping,
                tdm,
                feedback_fraction,
                filter_time_constant,
            )
        return (offset + gain * shape - u) / scale

    # The solver works on unconstrained coordinates: log(T/T_ref) and log ξ (positive), and
    # for T_dm the square root of T_dm/T_ref − floor: T_dm = 0 is a legitimate optimum at
    # the boundary, where a logarithm would drift towards −∞ by O(1) steps and never meet
    # the step-size termination test; with the square root it is an ordinary minimum.
    def to_physical(theta):
        parts = [jnp.exp(theta[0]), jnp.exp(theta[1])]
        if order == 3:
            parts.append(theta[2] ** 2 + _TORQUER_FLOOR)
        return jnp.stack(parts + [theta[-2], theta[-1]])

    start = [jnp.zeros((), dtype), jnp.log(guess_xi)]
    if order == 3:
        start.append(jnp.sqrt(jnp.maximum(guess_tdm / reference_t - _TORQUER_FLOOR, 0.0)))
    start += [record.direction * record.amplitude / scale, jnp.zeros((), dtype)]
    theta0 = jnp.stack([jnp.asarray(value, dtype) for value in start])

    tolerance = float(np.sqrt(np.finfo(dtype).eps))
    solver = optx.LevenbergMarquardt(rtol=tolerance, atol=tolerance)
    solution = optx.least_squares(
        lambda theta, args: physical_residuals(to_physical(theta), args),
        solver,
        theta0,
        max_steps=max_steps,
        throw=False,
    )
    theta = solution.value
    normalised = to_physical(theta)
    time_constant, damping = reference_t * normalised[0], normalised[1]
    tdm = reference_t * normalised[2] if order == 3 else jnp.zeros((), dtype)
    gain, offset = scale * normalised[-2], record.initial + scale * normalised[-1]
    # Covariance from the Jacobian in the physical parameters: the same as the delta
    # method from the solver's coordinates in the interior, and still finite at T_dm → 0.
    jacobian, residual = jax.jacfwd(lambda x: (physical_residuals(x, None),) * 2, has_aux=True)(
        normalised
    )
    n, p = u.shape[0], theta.shape[0]
    variance = jnp.sum(residual**2) / (n - p)
    normal = jacobian.T @ jacobian
    covariance_normalised = variance * jnp.linalg.solve(normal, jnp.eye(p, dtype=dtype))
    units = [reference_t, jnp.ones((), dtype)] + ([reference_t] if order == 3 else [])
    units = jnp.stack(units + [scale, scale])
    covariance = units[:, None] * covariance_normalised * units[None, :]

    R = IdentificationResult
    converged = solution.result == optx.RESULTS.successful
    finite_fit = jnp.all(jnp.isfinite(theta))
    result = R.where(converged & finite_fit, R.successful, R.fit_not_converged)
    result = R.where(record.finite, result, R.non_finite)
    ok = result == R.successful

    def placeholder(x):
        # Finite numbers on failure (throw=False), for masking in batch sweeps.
        return jnp.where(ok, x, jnp.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0))

    (time_constant, damping, tdm, gain, offset, residual, covariance) = (
        placeholder(x) for x in (time_constant, damping, tdm, gain, offset, residual, covariance)
    )
    fit = StepFit(
        time_constant=time_constant,
        damping_ratio=damping,
        torquer_time_constant=tdm,
        gain=gain,
        offset=offset,
        residual_rms=scale * jnp.sqrt(jnp.mean(residual**2)),
        covariance=covariance,
        time_constant_std=jnp.sqrt(covariance[0, 0]),
        damping_ratio_std=jnp.sqrt(covariance[1, 1]),
        result=result,
    )
    return _fail_if(result, fit, throw)


def fit_step_response(
    ts: SeriesLike,
    u_out: SeriesLike,
    *,
    order: Literal[2, 3] = 2,
    step_time: ScalarLike | None = None,
    initial: Sequence[ScalarLike] | None = None,
    feedback_fraction: ScalarLike = 1.0,
    filter_time_constant: ScalarLike = 0.0,
    tail_fraction: float = 0.2,
    max_steps: int = 1024,
    throw: bool = True,
) -> StepFit:
    """Fit the whole step-response record by Levenberg-Marquardt (optimistix).

    Beyond the paper: every sample is used instead of two crossings and two extrema, so the
    estimate degrades gracefully with noise, works on both sides of ξ = 1, and (order 3)
    estimates the torquer lag T_dm that the paper's methods neglect. See `StepFit` for the
    models. Order 2 uses the closed-form response (any grid); order 3 simulates by exact
    discretisation on the record's grid, which must be uniform.

    **Arguments:**

    - `ts`, `u_out`: the record, shapes `(n,)` [s], [V].
    - `order`: 2 or 3 (static).
    - `step_time`: time the test signal was applied [s]; default `ts[0]`.
    - `initial`: `(T, ξ)` or `(T, ξ, T_dm)` [s, -, s] to start from. Default: from the
        moments of the record, M0 = ∫(1 − s)dτ = 2ξT and M1 = ∫τ(1 − s)dτ = T²(4ξ² − 1)
        (any ξ, no crossing needed), with T_dm = 0.1 T.
    - `feedback_fraction`: K = K_test (order 3 only), the share of the loop stiffness that
        is electrical; ≈ 0.996 for the reference device.
    - `filter_time_constant`: a known output filter T_f [s] (order 3 only; default 0, no
        filter). It sits outside the loop (it is not in eq. (1)) and delays the record like
        T_dm does, so an order-3 fit that ignores it reports T_dm + T_f in its
        `torquer_time_constant` and a biased T: −0.43 % in K̂_a on the reference device.
    - `tail_fraction`: as in `identify_oscillatory`: the tail gives U_ss for the initial
        guess (static).
    - `max_steps`: iteration limit of the solver (static). Typical fits take tens of
        steps; an order-3 fit whose optimum is T_dm = 0 (no lag resolvable above the
        noise) converges to that boundary slowly, in a few hundred.
    - `throw`: raise when the fit fails (default); `False` returns the result code.

    **Returns:**

    A `StepFit`.
    """
    n_tail = _validate_record("fit_step_response", ts, u_out, tail_fraction)
    if order not in (2, 3):
        raise ValueError(f"order must be 2 or 3, got {order!r}.")
    if initial is not None and len(initial) not in (2, 3):
        raise ValueError(f"initial must be (T, ξ) or (T, ξ, T_dm), got {len(initial)} values.")
    concrete_tf = _concrete(filter_time_constant)
    if concrete_tf is not None and not (np.isfinite(concrete_tf) and concrete_tf >= 0):
        raise ValueError(
            f"filter_time_constant must be a finite T_f >= 0 s, got {float(concrete_tf)!r} s."
        )
    if order == 2 and (concrete_tf is None or concrete_tf != 0):
        raise ValueError(
            "filter_time_constant needs order=3 (the order-2 model has no lag); got order=2."
        )
    if order == 3:
        check_uniform_grid(ts, "fit_step_response(order=3)", "Resample the record or use order=2.")
    dtype = _record_dtype(ts, u_out)
    if initial is not None:
        initial = tuple(jnp.asarray(value, dtype) for value in initial)
    return _fit_step_response(
        jnp.asarray(ts, dtype),
        jnp.asarray(u_out, dtype),
        _step_time(step_time, ts, dtype),
        initial,
        jnp.asarray(feedback_fraction, dtype),
        jnp.asarray(filter_time_constant, dtype),
        n_tail,
        order,
        throw,
        max_steps,
    )


def scale_factor_from_fit(
    fit: StepFit,
    pickoff_amplifier_gain: ScalarLike,
    shape_factor: ScalarLike,
) -> tuple[Scalar, Scalar]:
    """K̂_a = γ T² k_dp k_y from a fit, with its standard deviation by the delta method.

    **Arguments:**

    - `fit`: a `StepFit`.
    - `pickoff_amplifier_gain`: k_dp k_y [V/m] (taken as exact).
    - `shape_factor`: γ (taken as exact).

    **Returns:**

    `(scale_factor, std)` [V/(m/s²)]; the relative std is 2 σ_T/T.
    """
    scale_factor = shape_factor * fit.time_constant**2 * pickoff_amplifier_gain
    return scale_factor, scale_factor * 2 * fit.time_constant_std / fit.time_constant
