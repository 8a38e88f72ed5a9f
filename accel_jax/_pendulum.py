"""Motion of the sensing element of a linear-acceleration meter (docs/models.md §2).

Bezvesilna & Podchashinskyi: the pickoff angle is α(t) = α_P + α_zm(t), with α_P constant
(proportional to the measured acceleration) and α_zm the free precession oscillation

    α_zm'' + 2 ξ α_zm' + ω0² sin α_zm = 0                                     (1)

(ξ is a decay rate in 1/s, not a damping ratio). Three right-hand sides are available:
`"sine"` (exact, eq. 1), `"cubic"` (sin α ≈ α − α³/6, the paper's refined model) and
`"linear"` (sin α ≈ α, the model behind the estimator's eq. 2).

Closed forms used as references:

- linear: α_zm = A e^{−ξt} sin(ω_d t + φ), ω_d = sqrt(ω0² − ξ²);
- cubic, to O(A³) (the paper's eq. 11, a Lindstedt–Poincaré solution):
  α_zm ≈ A e^{−ξt} sin(ω_z t + φ) + (A³/192) e^{−ξt} sin 3(ω_z t + φ),
  ω_z = ω_d (1 − A²/16).

The ODE is solved with diffrax (Dopri8 by default) on the scaled state (α, α'/ω0), so the
step-size tolerances act on angles in radians. Every function is pure, jit-compiled where
it matters, and vmappable over amplitude, phase, ξ, ω0, the sampling interval δ and, through
a mask of fixed maximum length, the record length K. Precision follows the inputs: the
linearisation errors studied here (1e-10…1e-5 rad) need float64 (enable x64 yourself).
"""

from __future__ import annotations

from typing import Literal

import diffrax
import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._params import _as_float, _concrete

Scalar = Float[Array, ""]
ScalarLike = Float[ArrayLike, ""]
Series = Float[Array, " n"]
SeriesLike = Float[ArrayLike, " n"]

Restoring = Literal["sine", "cubic", "linear"]
_RESTORING = ("sine", "cubic", "linear")
InitialForm = Literal["linear", "lindstedt"]
_FORMS = ("linear", "lindstedt")


class SensingElement(eqx.Module):
    """Free oscillation of the sensing element, eq. (1): α'' + 2ξα' + ω0² sin α = 0.

    Both fields are array leaves (vmap over a batch of elements, differentiate with
    respect to them). Checked on construction when concrete: ω0 > 0 and 0 ≤ ξ < ω0
    (underdamped: the ML model (2) assumes an oscillation).

    **Fields:**

    - `natural_frequency`: ω0 [rad/s], the small-amplitude angular frequency of the
        precession oscillation.
    - `decay_rate`: ξ [1/s], the decay rate of the oscillation envelope e^{−ξt}.
    """

    natural_frequency: Float[Array, ""] = eqx.field(converter=_as_float)
    decay_rate: Float[Array, ""] = eqx.field(converter=_as_float, default=0.0)

    def __check_init__(self):
        omega = _concrete(self.natural_frequency)
        xi = _concrete(self.decay_rate)
        if omega is not None:
            if not np.all(np.isfinite(omega)) or not np.all(omega > 0):
                raise ValueError(
                    f"SensingElement.natural_frequency must be finite and positive, got "
                    f"{omega!r} rad/s (an angular frequency: 2π × the frequency in Hz)."
                )
        if xi is not None:
            if not np.all(np.isfinite(xi)) or not np.all(xi >= 0):
                raise ValueError(
                    f"SensingElement.decay_rate must be finite and non-negative, got {xi!r} "
                    "1/s; use 0 for an undamped element."
                )
        if omega is not None and xi is not None and not np.all(xi < omega):
            raise ValueError(
                f"SensingElement.decay_rate ξ = {xi!r} 1/s must be below natural_frequency "
                f"ω0 = {omega!r} rad/s: the model is an underdamped oscillation."
            )

    @property
    def damped_frequency(self) -> Scalar:
        """ω_d = sqrt(ω0² − ξ²) [rad/s], the frequency of the linear damped oscillation."""
        return jnp.sqrt(self.natural_frequency**2 - self.decay_rate**2)


def amplitude_frequency(element: SensingElement, amplitude: ScalarLike) -> Scalar:
    """Frequency of the cubic (α − α³/6) oscillation of amplitude A, to O(A²) [rad/s].

    ω_z = ω_d (1 − A²/16), the paper's ω0zm of eq. (11) (with ω_d in place of ω0 when
    ξ > 0; they differ by O(ξ²/ω0)). For the exact sine the O(A²) term is the same.
    """
    return element.damped_frequency * (1 - jnp.asarray(amplitude) ** 2 / 16)


def _check_form(form) -> None:
    if form not in _FORMS:
        raise ValueError(f"form must be one of {_FORMS}, got {form!r}.")


def _check_restoring(restoring) -> None:
    if restoring not in _RESTORING:
        raise ValueError(
            f"restoring must be one of {_RESTORING} (exact sin α, α − α³/6, or α), "
            f"got {restoring!r}."
        )


def initial_state(
    element: SensingElement,
    amplitude: ScalarLike,
    phase: ScalarLike,
    *,
    form: InitialForm = "linear",
) -> tuple[Scalar, Scalar]:
    """Initial angle α_zm(0) [rad] and rate α_zm'(0) [rad/s] of a motion of given A and φ.

    - `form="linear"`: the linear damped solution A e^{−ξt} sin(ω_d t + φ):
      α(0) = A sin φ, α'(0) = A (ω_d cos φ − ξ sin φ).
    - `form="lindstedt"`: the paper's refined solution (11),
      e^{−ξt}[A sin ψ + (A³/192) sin 3ψ], ψ = ω_z t + φ, ω_z = ω_d(1 − A²/16): the initial
      state of a nonlinear (sine or cubic) motion whose amplitude and phase are the
      paper's A_0zm, φ_0zm to O(A³).

    **Arguments:** `element`; `amplitude` A [rad]; `phase` φ [rad] (at t = 0); `form`.

    **Returns:** `(angle, rate)` in rad and rad/s.
    """
    _check_form(form)
    amplitude = jnp.asarray(amplitude)
    phase = jnp.asarray(phase)
    xi = element.decay_rate
    if form == "linear":
        angle = amplitude * jnp.sin(phase)
        rate = amplitude * (element.damped_frequency * jnp.cos(phase) - xi * jnp.sin(phase))
        return angle, rate
    third = amplitude**3 / 192
    omega = amplitude_frequency(element, amplitude)
    angle = amplitude * jnp.sin(phase) + third * jnp.sin(3 * phase)
    rate = omega * (amplitude * jnp.cos(phase) + 3 * third * jnp.cos(3 * phase)) - xi * angle
    return angle, rate


def linear_solution(
    element: SensingElement, amplitude: ScalarLike, phase: ScalarLike, ts: SeriesLike
) -> Series:
    """Closed form of the linear model: α_zm(t) = A e^{−ξt} sin(ω_d t + φ) [rad] at ts [s]."""
    amplitude = jnp.asarray(amplitude)
    ts = jnp.asarray(ts)
    return (
        amplitude
        * jnp.exp(-element.decay_rate * ts)
        * jnp.sin(element.damped_frequency * ts + phase)
    )


def cubic_approximation(
    element: SensingElement, amplitude: ScalarLike, phase: ScalarLike, ts: SeriesLike
) -> Series:
    """The paper's approximate solution (11) of the cubic model, at ts [s], in rad.

    α_zm(t) ≈ A e^{−ξt} sin(ω_z t + φ) + (A³/192) e^{−ξt} sin 3(ω_z t + φ),
    ω_z = ω_d (1 − A²/16). Accurate to O(A³) in amplitude; its frequency error is O(A⁴ω0),
    so the phase error grows like A⁴ ω0 t (exactly what the tests measure). With ξ > 0 the
    amplitude-dependent frequency is frozen at its initial value (the paper's choice).
    """
    ts = jnp.asarray(ts)
    psi = amplitude_frequency(element, amplitude) * ts + phase
    envelope = jnp.exp(-element.decay_rate * ts)
    return envelope * (amplitude * jnp.sin(psi) + amplitude**3 / 192 * jnp.sin(3 * psi))


class SensingElementSolution(eqx.Module):
    """A solved sensing-element motion sampled at `ts`.

    **Fields:**

    - `ts`: sample times [s], shape (n,).
    - `angle`: α_zm(t_i) [rad], shape (n,) (without the constant α_P).
    - `rate`: α_zm'(t_i) [rad/s], shape (n,).
    - `result`: diffrax's `RESULTS` code; a failed solve (with `throw=False`) leaves NaN
        angles, never plausible-looking numbers.
    - `num_steps`: accepted plus rejected solver steps.
    """

    ts: Series
    angle: Series
    rate: Series
    result: diffrax.RESULTS
    num_steps: Array


def _restoring_term(restoring: str, angle):
    if restoring == "sine":
        return jnp.sin(angle)
    if restoring == "cubic":
        return angle - angle**3 / 6
    return angle


@eqx.filter_jit
def _solve(
    element, y0, ts, rtol, atol, dt0, *, restoring, solver, max_steps, adjoint, throw, controller
):
    omega0 = element.natural_frequency
    xi = element.decay_rate

    # State (α, α'/ω0): both components are angles, so rtol/atol act in radians.
    def field(t, y, args):
        omega0, xi = args
        angle, scaled_rate = y[0], y[1]
        return jnp.stack(
            [
                omega0 * scaled_rate,
                -2 * xi * scaled_rate - omega0 * _restoring_term(restoring, angle),
            ]
        )

    solution = diffrax.diffeqsolve(
        diffrax.ODETerm(field),
        solver,
        t0=jnp.zeros((), ts.dtype),
        t1=ts[-1],
        dt0=dt0,
        y0=y0,
        args=(omega0, xi),
        saveat=diffrax.SaveAt(ts=ts),
        stepsize_controller=(
            diffrax.PIDController(rtol=rtol, atol=atol) if controller is None else controller
        ),
        max_steps=max_steps,
        adjoint=adjoint,
        throw=throw,
    )
    failed = solution.result != diffrax.RESULTS.successful
    assert solution.ys is not None  # SaveAt(ts=ts) saves the states
    ys = jnp.where(failed, jnp.nan, solution.ys)
    return SensingElementSolution(
        ts=ts,
        angle=ys[:, 0],
        rate=ys[:, 1] * omega0,
        result=solution.result,
        num_steps=solution.stats["num_steps"],
    )


def solve_sensing_element(
    element: SensingElement,
    initial_angle: ScalarLike,
    initial_rate: ScalarLike,
    ts: SeriesLike,
    *,
    restoring: Restoring = "sine",
    rtol: float = 1e-12,
    atol: float = 1e-15,
    solver: diffrax.AbstractSolver | None = None,
    max_steps: int = 1_000_000,
    adjoint: diffrax.AbstractAdjoint | None = None,
    dt0: ScalarLike | None = None,
    stepsize_controller: diffrax.AbstractStepSizeController | None = None,
    throw: bool = True,
) -> SensingElementSolution:
    """Solve eq. (1) from t = 0 with diffrax and sample it at `ts`.

    **Arguments:**

    - `element`: ω0 [rad/s], ξ [1/s].
    - `initial_angle`, `initial_rate`: α_zm(0) [rad], α_zm'(0) [rad/s] (see
        `initial_state`).
    - `ts`: strictly increasing sample times ≥ 0 [s], shape (n,).
    - `restoring`: `"sine"` (exact), `"cubic"` (α − α³/6) or `"linear"` (α).
    - `rtol`, `atol`: tolerances of the PID step-size controller on (α, α'/ω0), in rad.
        The defaults reach ~1e-14 rad over tens of periods in float64.
    - `solver`: a diffrax solver; `None` (default) is `diffrax.Dopri8()`.
    - `max_steps`: a Python int.
    - `adjoint`: diffrax adjoint; `None` is diffrax's default (reverse mode). Forward-mode
        differentiation (e.g. inside a Levenberg–Marquardt fit) needs
        `diffrax.ForwardMode()`.
    - `dt0`: initial step [s]; `None` lets the controller choose.
    - `stepsize_controller`: `None` (default) is `diffrax.PIDController(rtol, atol)`; e.g.
        `diffrax.ConstantStepSize()` with `dt0` for a fixed-step convergence study.
    - `throw`: raise diffrax's error if the solve fails; with `False` the failure is
        reported in `result` and the angles are NaN.

    **Returns:** a `SensingElementSolution`.

    Precision: that of the inputs (float64 needed for tolerances below ~1e-7).
    """
    _check_restoring(restoring)
    if not (isinstance(max_steps, int) and max_steps > 0):
        raise ValueError(f"max_steps must be a positive Python int, got {max_steps!r}.")
    ts = jnp.asarray(ts)
    if not jnp.issubdtype(ts.dtype, jnp.floating):
        ts = ts.astype(jnp.result_type(float))
    if ts.ndim != 1 or ts.shape[0] < 1:
        raise ValueError(f"ts must be a 1-D array of sample times [s], got shape {ts.shape}.")
    concrete = _concrete(ts)
    if concrete is not None:
        if not np.all(np.isfinite(concrete)) or concrete[0] < 0:
            raise ValueError(
                f"ts must be finite and ≥ 0 s (the motion starts at t = 0), got ts[0] = "
                f"{concrete[0]!r} s."
            )
        if concrete.shape[0] > 1 and not np.all(np.diff(concrete) > 0):
            raise ValueError("ts must be strictly increasing [s].")
    for name, value, unit in (
        ("initial_angle", initial_angle, "rad"),
        ("initial_rate", initial_rate, "rad/s"),
    ):
        value_c = _concrete(value)
        if value_c is not None and not np.all(np.isfinite(value_c)):
            raise ValueError(f"{name} must be finite, got {value_c!r} {unit}.")
    if solver is None:
        solver = diffrax.Dopri8()
    if adjoint is None:
        adjoint = diffrax.RecursiveCheckpointAdjoint()
    dtype = ts.dtype
    y0 = jnp.stack(
        [
            jnp.asarray(initial_angle, dtype),
            jnp.asarray(initial_rate, dtype) / element.natural_frequency.astype(dtype),
        ]
    )
    return _solve(
        element,
        y0,
        ts,
        rtol,
        atol,
        dt0,
        restoring=restoring,
        solver=solver,
        max_steps=max_steps,
        adjoint=adjoint,
        throw=throw,
        controller=stepsize_controller,
    )


def sample_times(sample_interval: ScalarLike, n_samples: int) -> Series:
    """The paper's sampling instants t_i = i·δ, i = 1..K [s] (shape (K,), K a Python int).

    `sample_interval` δ [s] may be traced (vmap over δ); it is checked when concrete.
    """
    if not (isinstance(n_samples, int | np.integer) and n_samples >= 1):
        raise ValueError(f"n_samples must be a positive Python int, got {n_samples!r}.")
    value = _concrete(sample_interval)
    if value is not None and (not np.all(np.isfinite(value)) or not np.all(value > 0)):
        raise ValueError(f"sample_interval must be finite and positive, got {value!r} s.")
    delta = _as_float(sample_interval)
    return delta * jnp.arange(1, int(n_samples) + 1, dtype=delta.dtype)


def record_mask(n_samples: int, record_length: ArrayLike) -> Array:
    """Mask (1.0 for i < K, else 0.0) selecting the first K of n_samples samples.

    Lets one compiled function run over records of different length K (vmap over K):
    simulate the longest record and pass the mask to the estimators.
    """
    value = _concrete(record_length)
    if value is not None and not np.all((value >= 1) & (value <= n_samples)):
        raise ValueError(f"record_length must lie in 1..{n_samples} samples, got {value!r}.")
    return (jnp.arange(n_samples) < record_length).astype(jnp.result_type(float))


def sample_sensing_element(
    element: SensingElement,
    amplitude: ScalarLike,
    phase: ScalarLike,
    *,
    sample_interval: ScalarLike,
    n_samples: int,
    constant_angle: ScalarLike = 0.0,
    restoring: Restoring = "sine",
    form: InitialForm = "lindstedt",
    **solve_kwargs,
) -> tuple[Series, Series]:
    """Noise-free pickoff record α(t_i) = α_P + α_zm(t_i), t_i = i·δ, i = 1..K.

    **Arguments:**

    - `element`: ω0 [rad/s], ξ [1/s].
    - `amplitude`, `phase`: A [rad] and φ [rad] of the oscillation (see `initial_state`).
    - `sample_interval`: δ [s]; `n_samples`: K (a Python int).
    - `constant_angle`: α_P [rad], the quantity the estimators recover.
    - `restoring`: right-hand side of eq. (1); `form`: how A and φ set the initial state
        (default `"lindstedt"`: the paper's A_0zm, φ_0zm of eq. 11).
    - `**solve_kwargs`: passed to `solve_sensing_element`.

    **Returns:** `(ts, angles)`, both shape (K,), in s and rad.
    """
    ts = sample_times(sample_interval, n_samples)
    angle0, rate0 = initial_state(element, amplitude, phase, form=form)
    solution = solve_sensing_element(
        element, angle0, rate0, ts, restoring=restoring, **solve_kwargs
    )
    return ts, jnp.asarray(constant_angle, ts.dtype) + solution.angle


__all__ = [
    "SensingElement",
    "SensingElementSolution",
    "amplitude_frequency",
    "cubic_approximation",
    "initial_state",
    "linear_solution",
    "record_mask",
    "sample_sensing_element",
    "sample_times",
    "solve_sensing_element",
]
