"""What every identification method shares: the shape aliases, the tuning constants, the
`IdentificationResult` codes, and the record summary (steady state, step, noise band,
settling and saturation checks)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._params import _concrete

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
    common: IdentificationResult  # the failure codes every method shares (`_common_result`)


def _sums(left, right):
    return tuple(a + b for a, b in zip(left, right, strict=True))


def _positions(n: int):
    """Sample indices 0 … n − 1 as floats (exact), for index searches by min/max: XLA:CPU
    vectorises a float min/max reduction but not an arg-max (a (value, index) pair
    reduction), which took ~4× as long per 5 001-sample record (docs/performance.md).
    float64 where JAX has it (exact to 2^53), else float32 up to 2^24 samples, else int32
    (exact, slower)."""
    dtype = jax.dtypes.canonicalize_dtype(jnp.float64)  # float32 without jax_enable_x64
    if dtype != jnp.float64 and n > 2**24:
        dtype = jnp.int32
    return jnp.arange(n, dtype=dtype)


def _first(mask):
    """(index of the first True of a 1-D mask, whether there is one); index 0 when none.

    One min reduction over the masked indices; the flag is whether it found one."""
    n = mask.shape[0]
    k = jnp.min(jnp.where(mask, _positions(n), n))
    found = k < n
    return jnp.where(found, k, 0).astype(jnp.int32), found


def _last(mask):
    """(index of the last True of a 1-D mask, whether there is one); index 0 when none.

    One max reduction over the masked indices (see `_first`)."""
    n = mask.shape[0]
    k = jnp.max(jnp.where(mask, _positions(n), -1))
    found = k >= 0
    return jnp.where(found, k, 0).astype(jnp.int32), found


def _summarise(ts, u, step_time, steady_state, n_tail, saturation_level) -> _Record:
    """The record's summary. `step_time=None` (static): the step at the first sample, as
    `step_time=ts[0]` gives, without the passes that look for samples before it (the Monte
    Carlo kernel's records)."""
    n = u.shape[0]
    dtype = u.dtype
    at_start = step_time is None
    if at_start:
        step_time = ts[0]
    finite = jnp.all(jnp.isfinite(ts)) & jnp.all(jnp.isfinite(u)) & jnp.isfinite(step_time)
    if steady_state is not None:
        finite = finite & jnp.isfinite(steady_state)
    # NaN-free placeholders: with throw=False the result code carries the failure and
    # every number stays finite, so a batch sweep can mask per element.
    index_time = jnp.arange(n, dtype=dtype)
    ts = jnp.where(finite, ts, index_time)
    u = jnp.where(finite, u, jnp.zeros_like(u))
    step_time = jnp.where(finite, step_time, ts[0])

    if at_start:
        initial = u[0]  # no sample before the step
    else:
        pre = ts < step_time
        n_pre = jnp.sum(pre, dtype=jnp.int32)  # counts in int32: int64 sums are slow on XLA:CPU
        initial = jnp.where(
            n_pre > 0, jnp.sum(jnp.where(pre, u, 0)) / jnp.maximum(n_pre, 1), u[0]
        )
    tail = u[n - n_tail :]
    sigma = jnp.std(tail)
    tail_mean = jnp.mean(tail)
    u_ss = tail_mean if steady_state is None else jnp.where(finite, steady_state, tail_mean)
    step = u_ss - initial
    direction = jnp.where(step >= 0, 1.0, -1.0).astype(dtype)
    amplitude = jnp.abs(step)
    # The record's extremes: the largest and the smallest sample before the tail (a rail's
    # flat top) and the largest |U| (the rounding quantum, the saturation level). They only
    # decide flags and the band's rounding floor, never a value that is differentiated, so
    # they are taken of the record without its tangent. Three max reductions: XLA:CPU
    # fused them with the record's other passes, where one variadic reduction of the three
    # (which does not vectorise) cost several times as much in the Monte Carlo kernel.
    region = jnp.arange(n, dtype=jnp.int32) < n - n_tail
    if not at_start:
        region = region & (ts >= step_time)
    values = jax.lax.stop_gradient(u)
    low = jnp.asarray(-jnp.inf, dtype)
    top = jnp.max(jnp.where(region, values, low))
    bottom = jnp.max(jnp.where(region, -values, low))
    largest = jnp.max(jnp.abs(values))
    quantum = 32 * jnp.finfo(dtype).eps * largest
    band = _NOISE_SIGMAS * sigma + jnp.maximum(_BAND_FLOOR * amplitude, quantum)
    has_step = amplitude > 2 * band

    if steady_state is None:
        half = n_tail // 2
        drift = jnp.abs(jnp.mean(tail[half:]) - jnp.mean(tail[:half]))
        settled = drift <= _SETTLE_TOLERANCE * amplitude + 8 * sigma / np.sqrt(n_tail)
    else:
        settled = jnp.array(True)

    # A rail shows as a flat top (many samples at exactly the extreme value) before the
    # tail, away from both the initial and the steady-state level. Both counts in one pass.
    n_region = jnp.sum(region, dtype=jnp.int32)
    min_run = jnp.maximum(3, _PLATEAU_FRACTION * n_region)
    near = 4 * jnp.finfo(dtype).eps
    zero = jnp.zeros((), jnp.int32)
    counts = jax.lax.reduce(
        (
            (region & (values >= top - near * jnp.abs(top))).astype(jnp.int32),
            (region & (-values >= bottom - near * jnp.abs(bottom))).astype(jnp.int32),
        ),
        (zero, zero),
        _sums,
        (0,),
    )
    saturated = jnp.array(False)
    for sign, extreme, count in ((1.0, top, counts[0]), (-1.0, bottom, counts[1])):
        away = (jnp.abs(extreme - sign * u_ss) > band) & (jnp.abs(extreme - sign * initial) > band)
        saturated = saturated | ((count >= min_run) & away)
    # Some |U| at or above the level ⟺ the largest |U| is.
    saturated = saturated | (largest >= saturation_level)

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
        common=_common_result(finite, settled, saturated, has_step),
    )


def _common_result(finite, settled, saturated, has_step) -> IdentificationResult:
    """The failure codes every method shares; the most fundamental wins (applied last)."""
    R = IdentificationResult
    result = R.where(has_step, R.successful, R.no_step)
    result = R.where(settled, result, R.too_short)
    # A rail distorts the tail too, so it is reported ahead of "not settled".
    result = R.where(saturated, R.saturated, result)
    return R.where(finite, result, R.non_finite)


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


def _record_arguments(
    ts, u_out, pickoff_amplifier_gain, shape_factor, step_time, steady_state, saturation_level
):
    """The record's arguments in its one floating dtype, as the jitted estimators take them:
    ((ts, u_out, k_dp k_y, γ), (step time, steady state, saturation level), dtype)."""
    dtype = _record_dtype(ts, u_out)
    record_ts, u, gain, shape = (
        jnp.asarray(v, dtype) for v in (ts, u_out, pickoff_amplifier_gain, shape_factor)
    )
    head = (record_ts, u, gain, shape)
    tail = (
        _step_time(step_time, ts, dtype),
        _as_dtype(steady_state, dtype),
        _saturation_level(saturation_level, dtype),
    )
    return head, tail, dtype
