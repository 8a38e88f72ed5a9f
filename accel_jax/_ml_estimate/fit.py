"""Beyond the paper: the exact-sine fit of the sensing-element record (Levenberg–Marquardt
over a diffrax solution), whitened by the error covariance."""

from __future__ import annotations

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, ArrayLike

from .._pendulum import Restoring, SensingElement, solve_sensing_element
from .disturbances import Scalar, SeriesLike, StateCovariance
from .estimate import MLEstimate, _check_times, _inverse3, _prepare_covariance, ml_estimate


class NonlinearFit(eqx.Module):
    """Weighted nonlinear least-squares fit of the sensing-element motion.

    **Fields:**

    - `constant_angle`: α̂_P [rad].
    - `initial_angle`: α̂_zm(0) [rad]; `initial_rate`: α̂_zm'(0) [rad/s].
    - `covariance`: Gauss–Newton covariance of (α_P, α_zm(0), α_zm'(0)/ω0) [rad²],
        (Jᵀ R⁻¹ J)⁻¹ at the solution, shape (3, 3).
    - `result`: optimistix's `RESULTS` code; `num_steps`: Levenberg–Marquardt steps.
    """

    constant_angle: Scalar
    initial_angle: Scalar
    initial_rate: Scalar
    covariance: StateCovariance
    result: optx.RESULTS
    num_steps: Array


def _whitener(covariance, mask):
    if covariance.ndim == 1:
        scale = 1 / jnp.sqrt(covariance)
        return lambda r: r * scale
    chol = jnp.linalg.cholesky(covariance)
    return lambda r: jax.scipy.linalg.solve_triangular(chol, r, lower=True)


@eqx.filter_jit
def _fit(
    element,
    ts,
    samples,
    covariance,
    mask,
    guess,
    rtol,
    atol,
    *,
    restoring,
    max_steps,
    throw,
    ode_rtol,
    ode_atol,
    ode_max_steps,
):
    whiten = _whitener(covariance, mask)
    omega0 = element.natural_frequency

    def model(params):
        # Under vmap, optimistix evaluates both branches of its accept/reject choices, so a
        # finished element can carry non-finite trial values; a NaN initial state would make
        # the adaptive solve shrink its step until max_steps and stall the whole batch.
        params = jnp.where(jnp.isfinite(params), params, 0.0)
        alpha_p, angle0, scaled_rate0 = params
        solution = solve_sensing_element(
            element,
            angle0,
            scaled_rate0 * omega0,
            ts,
            restoring=restoring,
            adjoint=diffrax.ForwardMode(),
            rtol=ode_rtol,
            atol=ode_atol,
            max_steps=ode_max_steps,
            throw=False,
        )
        return alpha_p + solution.angle

    def whitened(params):
        r = samples - model(params)
        if mask is not None:
            r = r * mask
        return whiten(r)

    # optimistix's Cauchy test compares the change of each residual with atol + rtol·|r|:
    # multiplying the whitened residuals by a typical σ puts them back in radians, where
    # atol means the same as for the parameters (and the argmin is unchanged).
    variances = covariance if covariance.ndim == 1 else jnp.diagonal(covariance)
    scale = jnp.sqrt(jnp.mean(variances))

    def residuals(params, args):
        return scale * whitened(params)

    solver = optx.LevenbergMarquardt(rtol=rtol, atol=atol)
    solution = optx.least_squares(residuals, solver, guess, max_steps=max_steps, throw=throw)
    params = solution.value
    jac = jax.jacfwd(whitened)(params)
    covariance3 = _inverse3(jac.T @ jac)
    return NonlinearFit(
        constant_angle=params[0],
        initial_angle=params[1],
        initial_rate=params[2] * omega0,
        covariance=covariance3,
        result=solution.result,
        num_steps=solution.stats["num_steps"],
    )


def fit_sensing_element(
    ts: SeriesLike,
    samples: SeriesLike,
    element: SensingElement,
    *,
    covariance: ArrayLike,
    initial_guess: MLEstimate | None = None,
    restoring: Restoring = "sine",
    mask: SeriesLike | None = None,
    rtol: float = 1e-9,
    atol: float = 1e-12,
    max_steps: int = 64,
    ode_rtol: float = 1e-12,
    ode_atol: float = 1e-15,
    ode_max_steps: int = 16384,
    throw: bool = True,
) -> NonlinearFit:
    """Fit α_P and the initial state (α_zm(0), α_zm'(0)) of eq. (1) to pickoff samples.

    Minimises ‖L⁻¹(α* − α_P − α_zm(t; α_zm(0), α_zm'(0)))‖², R = L Lᵀ, with optimistix's
    Levenberg–Marquardt; α_zm is a diffrax solve of eq. (1) (forward-mode sensitivities)
    with the element's ω0 and ξ known a priori (as the paper assumes of ω and ξ). For
    Gaussian errors this is the maximum-likelihood estimate of the nonlinear model: the
    reference against which the linear estimator and its compensation are judged.

    **Arguments:**

    - `ts` [s], `samples` [rad], `covariance` [rad²], `mask`: as in `ml_estimate`
        (ts ≥ 0: the motion is parametrised by its state at t = 0).
    - `element`: ω0 [rad/s], ξ [1/s].
    - `initial_guess`: an `MLEstimate` at ω = ω_d to start from (α_zm(0) = α̂_S,
        α_zm'(0) = ω_d α̂_C − ξ α̂_S); `None` computes it.
    - `restoring`: the model's right-hand side (`"sine"` by default).
    - `rtol`, `atol`: Levenberg–Marquardt tolerances on the parameters [rad];
        `max_steps`: its step limit (Python int).
    - `ode_rtol`, `ode_atol`: tolerances of the inner diffrax solve [rad];
        `ode_max_steps`: its step limit (a failed inner solve gives NaN residuals and a
        failed fit, never a silent number).
    - `throw`: raise if the fit fails; with `False` the code is in `result`.

    **Returns:** a `NonlinearFit`.

    Precision: float64 expected (errors of 1e-12 rad are resolved).

    On the CPU, a vmapped batch of these fits needs jaxlib 0.10.2's XLA:CPU scheduler
    workaround, which `import accel_jax` sets (see `accel_jax._runtime`).
    """
    if not (isinstance(max_steps, int) and max_steps > 0):
        raise ValueError(f"max_steps must be a positive Python int, got {max_steps!r}.")
    omega_d = element.damped_frequency
    if initial_guess is None:
        initial_guess = ml_estimate(ts, samples, omega_d, covariance, mask=mask)
    elif not isinstance(initial_guess, MLEstimate):
        raise ValueError(f"initial_guess must be an MLEstimate or None, got {initial_guess!r}.")
    ts = _check_times(ts)
    covariance_, mask_ = _prepare_covariance(covariance, ts.shape[0], ts.dtype, mask)
    samples = jnp.asarray(samples, ts.dtype)
    if samples.shape != ts.shape:
        raise ValueError(f"samples must have the shape of ts {ts.shape}, got {samples.shape}.")
    z = initial_guess.state
    guess = jnp.stack(
        [z[0], z[2], (omega_d * z[1] - element.decay_rate * z[2]) / element.natural_frequency]
    ).astype(ts.dtype)
    return _fit(
        element,
        ts,
        samples,
        covariance_,
        mask_,
        guess,
        rtol,
        atol,
        restoring=restoring,
        max_steps=max_steps,
        throw=throw,
        ode_rtol=ode_rtol,
        ode_atol=ode_atol,
        ode_max_steps=ode_max_steps,
    )
