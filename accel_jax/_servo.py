"""Closed forms of the closed-loop servo accelerometer (docs/models.md §1, eqs. (1)-(7), (13)-(15)).

Every function takes a `ServoParams` and returns arrays of its dtype; all are jit-, vmap-
and grad-safe. Units are SI: output volts per m/s² of input acceleration.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._params import ServoParams, _concrete


def loop_stiffness(params: ServoParams) -> Float[Array, ""]:
    """c + k_dm·l·k_dp·k_y [N·m/rad]: elastic plus electrical (feedback) stiffness."""
    return params.stiffness + feedback_stiffness(params)


def feedback_stiffness(params: ServoParams) -> Float[Array, ""]:
    """k_dm·l·k_dp·k_y [N·m/rad]: the moment the loop returns per radian of deflection."""
    p = params
    return p.torquer_gain * p.pendulum_length * p.pickoff_gain * p.amplifier_gain


def transfer_function(params: ServoParams) -> tuple[Float[Array, 2], Float[Array, 4]]:
    """Coefficients of W(p) = U_out/a, docs/models.md eq. (1), highest power first.

    W(p) = m l² k_dp k_y (T_dm p + 1) / [(J p² + μ p + c)(T_dm p + 1) + k_dm l k_dp k_y]

    **Returns:** `(numerator, denominator)` with numerator `[b1, b0]` [V·s²/m · (s, 1)] and
    denominator `[a3, a2, a1, a0]`. With T_dm = 0 the leading coefficients are zero and the
    system is second order. The output filter T_f is not part of eq. (1).
    """
    p = params
    gain = p.pendulum_mass * p.pendulum_length**2 * p.pickoff_gain * p.amplifier_gain
    tdm = p.torquer_time_constant
    numerator = jnp.stack([gain * tdm, gain])
    denominator = jnp.stack(
        [
            p.moment_of_inertia * tdm,
            p.moment_of_inertia + p.damping * tdm,
            p.damping + p.stiffness * tdm,
            loop_stiffness(p),
        ]
    )
    return numerator, denominator


def transfer_function_test_signal(
    params: ServoParams,
) -> tuple[Float[Array, 1], Float[Array, 4]]:
    """Coefficients of W_test(p) = U_amp/U_test (before the output filter), highest power first.

    The test voltage drives an extra torquer winding, so its moment passes through the same
    torquer lag as the feedback moment:

    W_test(p) = k_dm l k_dp k_y / [(J p² + μ p + c)(T_dm p + 1) + k_dm l k_dp k_y],

    which is docs/models.md eq. (3) when T_dm = 0. Sign convention: a positive test voltage gives a
    positive output.
    """
    _, denominator = transfer_function(params)
    return feedback_stiffness(params)[None], denominator


def scale_factor(params: ServoParams) -> Float[Array, ""]:
    """K_a = m l² k_dp k_y / (c + k_dm l k_dp k_y) [V/(m/s²)], docs/models.md eq. (2)."""
    p = params
    gain = p.pendulum_mass * p.pendulum_length**2 * p.pickoff_gain * p.amplifier_gain
    return gain / loop_stiffness(p)


def time_constant(params: ServoParams) -> Float[Array, ""]:
    """T = sqrt(J / (c + k_dm l k_dp k_y)) [s], eq. (4); also the aperiodic T2 (15)."""
    return jnp.sqrt(params.moment_of_inertia / loop_stiffness(params))


def damping_ratio(params: ServoParams) -> Float[Array, ""]:
    """ξ = (μ/2) / sqrt(J (c + k_dm l k_dp k_y)), eq. (5), dimensionless."""
    return 0.5 * params.damping / jnp.sqrt(params.moment_of_inertia * loop_stiffness(params))


def natural_frequency(params: ServoParams) -> Float[Array, ""]:
    """Undamped natural frequency 1/T [rad/s] of the second-order test response."""
    return 1.0 / time_constant(params)


def closed_loop_test_gain(params: ServoParams) -> Float[Array, ""]:
    """K_test = k_dm l k_dp k_y / (c + k_dm l k_dp k_y), eq. (6), dimensionless."""
    return feedback_stiffness(params) / loop_stiffness(params)


def shape_factor(params: ServoParams) -> Float[Array, ""]:
    """γ = m l² / J, the exact factor in K_a = γ T² k_dp k_y (eq. 7; the paper rounds it to 3/4)."""
    p = params
    return p.pendulum_mass * p.pendulum_length**2 / p.moment_of_inertia


def aperiodic_time_constants(
    params: ServoParams,
) -> tuple[Float[Array, ""], Float[Array, ""], Float[Array, ""], Float[Array, ""]]:
    """(T1, T2, T3, T4) [s] of the aperiodic test response, eqs. (12)-(15).

    T1 = μ/(c + k_dm l k_dp k_y) (13), T2 = T (4), and T3 ≥ T4 the time constants of
    (T3 p + 1)(T4 p + 1): T1 = T3 + T4 (14), T2 = sqrt(T3 T4) (15). Defined only for
    ξ ≥ 1 (T1 ≥ 2 T2); otherwise this raises (eagerly a `ValueError`, under jit an
    `EqxRuntimeError`) rather than returning NaN.
    """
    t1 = params.damping / loop_stiffness(params)
    t2 = time_constant(params)
    discriminant = 0.25 * t1**2 - t2**2
    concrete = None
    try:
        concrete = float(discriminant) if jnp.ndim(discriminant) == 0 else None
    except Exception:  # traced
        concrete = None
    if concrete is not None and concrete < 0:
        raise ValueError(
            f"The device is oscillatory (ξ = {float(damping_ratio(params)):.4g} < 1): the "
            "aperiodic time constants T3, T4 do not exist. Use time_constant and "
            "damping_ratio instead."
        )
    discriminant = eqx.error_if(
        discriminant,
        discriminant < 0,
        "aperiodic_time_constants: the device is oscillatory (ξ < 1); T3, T4 do not exist.",
    )
    root = jnp.sqrt(jnp.maximum(discriminant, 0.0))
    return t1, t2, 0.5 * t1 + root, 0.5 * t1 - root


def scale_factor_from_time_constant(
    time_constant_s, pickoff_amplifier_gain, shape_factor_value
) -> Float[Array, ""]:
    """K̂_a = γ T² k_dp k_y [V/(m/s²)], eq. (7): the identification's final step.

    **Arguments:**

    - `time_constant_s`: identified T (or refined T2 in the aperiodic case) [s].
    - `pickoff_amplifier_gain`: k_dp·k_y [V/m], e.g. from `pickoff_gain_from_stops`.
    - `shape_factor_value`: γ = m l²/J, or the paper's 3/4 (`accel_jax.PAPER_GAMMA`).
    """
    return shape_factor_value * time_constant_s**2 * pickoff_amplifier_gain


def relative_error_percent(estimate, truth) -> Float[Array, ""]:
    """δK_a = 100·(K̂_a − K_a)/K̂_a [%], the paper's definition (relative to the estimate)."""
    return 100.0 * (estimate - truth) / estimate


def damping_for_ratio(params: ServoParams, ratio) -> Float[Array, ...]:
    """The damping coefficient μ that gives the loop the damping ratio ξ = `ratio` (eq. (5)
    solved for μ): μ = 2 ξ √(J (c + k_dm l k_dp k_y)) [N·m·s]; the other constants of
    `params` unchanged. Vectorised over `ratio`; a concrete negative or non-finite ratio
    raises `ValueError`."""
    concrete = _concrete(ratio)
    if concrete is not None and not np.all(np.isfinite(concrete) & (concrete >= 0)):
        raise ValueError(f"damping_for_ratio: ratio must be finite and ≥ 0, got {concrete!r}.")
    return 2 * jnp.asarray(ratio) * jnp.sqrt(params.moment_of_inertia * loop_stiffness(params))


def dominant_pole_scale_factor(params: ServoParams, shape_factor, pickoff_amplifier_gain) -> float:
    """The scale factor K̂_a the oscillatory method (docs/models.md §1, steps (8)-(10)) converges to
    on a noise-free, finely sampled record of a loop with a torquer lag, predicted without
    simulating: once the fast real pole of the lag has died out, the record is a damped
    sinusoid of the dominant pole pair s = −σ ± jω_d, for which the steps return exactly
    T̂ = 1/|s| (ω from the period, ξ̂ = σ/|s| from A1/A2), so K̂_a = γ k_dp k_y / |s|².

    Host-side (NumPy roots of the test-signal denominator, concrete parameters); a loop
    without an oscillatory pair raises `ValueError`. The
    relative error is `relative_error_percent(K̂_a, scale_factor(params))`.
    """
    _, den = transfer_function_test_signal(params)
    den = np.asarray(den, dtype=float)
    roots = np.roots(den[np.argmax(den != 0) :])
    pair = roots[np.argmax(np.abs(roots.imag))]
    if pair.imag == 0:
        raise ValueError(
            "dominant_pole_scale_factor: the loop has no oscillatory pole pair (ξ ≥ 1 with "
            "these lags), so the oscillatory method does not apply."
        )
    return float(shape_factor) * float(pickoff_amplifier_gain) / abs(pair) ** 2
