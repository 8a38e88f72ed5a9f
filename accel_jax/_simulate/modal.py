"""Closed-form and companion-form step responses of the normalised loop, the models the
identification fits evaluate: `second_order_step` (1/(T²p² + 2ξTp + 1), one smooth
expression for ξ < 1, ξ = 1, ξ > 1) and `_third_order_step` (the test-signal transfer
function with the torquer lag T_dm and a known output filter T_f, by the exact
discretisation of its companion form), with the small matrix exponential `_expm` both
forward- and reverse-differentiable (the fits' implicit gradients need the latter)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .matrix import _expm

ScalarLike = Float[ArrayLike, ""]
Values = Float[Array, "..."]
ValuesLike = Float[ArrayLike, "..."]


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
