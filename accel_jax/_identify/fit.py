"""Beyond the paper: a least-squares fit of the whole record to the second-order model, or
to the third-order model with the torquer lag T_dm (and a known output filter), with
parameter covariance; the scale factor from the fit."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .._checks import check_uniform_grid
from .._params import _concrete
from .._simulate.modal import _third_order_step, second_order_step
from .record import (
    _TORQUER_FLOOR,
    IdentificationResult,
    Matrix,
    Scalar,
    ScalarLike,
    SeriesLike,
    _fail_if,
    _record_dtype,
    _step_time,
    _summarise,
    _validate_record,
)


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
    scale_factor = jnp.asarray(shape_factor) * fit.time_constant**2 * pickoff_amplifier_gain
    return scale_factor, scale_factor * 2 * fit.time_constant_std / fit.time_constant
