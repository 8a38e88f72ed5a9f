"""The `step` kind: a closed-loop test-signal record, its nominal model and its effects.

**Nominal model** (the idealised loop each identification method of SPEC.md §1 assumes):
the linear closed loop of `accel_jax.state_space` with no torquer lag (T_dm = 0), no output
filter (T_f = 0), no stop contact, a constant external moment M_v and white output noise:

    J θ'' + μ θ' + c θ = M_v + k_dm (U_test − k_dp k_y l θ),     U_out = k_dp k_y l θ + ε w.

The record starts settled at its first test voltage. Refitted: J, μ, c, k_dm as log-normal
deviations from the nominal values, z_i = ln(x_i/x_i⁰)/σ_i with a standard normal prior on
z_i, and M_v (no prior).

**Effects** (each `StepEffect` changes the model through one hook and is the nominal model
at z = 0):

- `torquer_lag`: T_dm > 0 (inside the loop: changes the overshoot as well as the delay);
- `output_filter`: T_f > 0 (outside the loop: delays the output only);
- `stop_saturation`: mechanical stops at U_out = ±U_stop (θ held at the stop, inelastic);
- `disturbance_drift`: M_v(t) = M_v + Ṁ (t − t_0), a slow ramp of the external moment;
- `colored_noise`: AR(1) output noise (the sampled Gauss–Markov process), e_i = φ e_{i−1} + w_i.

The simulation is the exact zero-order-hold discretisation of the loop (as
`simulate_linear`), in scaled states, with the stops applied after each sample step (a
surrogate of `simulate_nonlinear`'s stiff contact, exact to O(dt) in the release time).
Everything is float64 (enable x64: the fitted lags are ~1e-5 s against 5e-6 s samples, and
the likelihood differences used for the evidence are ~10 out of ~10⁴).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .._data import NominalDevice, StepData
from .._params import ServoParams
from .._servo import loop_stiffness, scale_factor, time_constant
from .._simulate import discretise, state_space
from .._sweep import even_chunk_size, sweep
from .base import (
    AbstractEffect,
    CandidateFit,
    DiagnosisResult,
    effect_library,
    held_out_gap,
    ljung_box,
    rank_candidates,
    register_effect,
)

REFIT_FIELDS = ("moment_of_inertia", "damping", "stiffness", "torquer_gain")
"""ServoParams fields the refit moves, each under its log-normal prior (a field given no
uncertainty in the device file stays at its nominal value)."""

HELD_OUT_FRACTION = 1 / 3
"""About this much of the record, from the input change nearest to it, is held out."""

TRANSIENT_FRACTION = 0.25
"""The first quarter of each constant-input segment counts as transient, the rest as steady."""

_N_NOMINAL = len(REFIT_FIELDS) + 1  # refitted fields + the external moment


class StepContext(eqx.Module):
    """Per-record scales and masks of a step fit (array leaves: vmappable over records).

    **Fields:** `sigma_ref` [V] the residual scale of the fit; `duration` [s]; `peak` [V]
    the largest |U_out| of the training part; `moment_unit` [N·m/V] the external moment
    that moves the settled output by 1 V (nominal device); `lag_unit` [s] the lag per unit
    of z (3 % of the nominal T); `train`, `test` (n,) 0/1 masks.
    """

    sigma_ref: jax.Array
    duration: jax.Array
    peak: jax.Array
    moment_unit: jax.Array
    lag_unit: jax.Array
    train: jax.Array
    test: jax.Array


class StepEffect(AbstractEffect):
    """An effect on a step record. Hooks (each the identity at z = 0; override one):

    - `device(params, z, ctx)`: change the loop's `ServoParams`;
    - `moment(ts, z, ctx)`: add an external moment series [N·m], shape (n,);
    - `inverse_stop(z, ctx)`: 1/U_stop [1/V] of symmetric stops (0: none);
    - `noise_pole(z, ctx)`: the AR(1) coefficient φ of the output noise (0: white).
    """

    kind = "step"

    def device(self, params: ServoParams, z, ctx) -> ServoParams:
        return params

    def moment(self, ts, z, ctx):
        return jnp.zeros_like(ts)

    def inverse_stop(self, z, ctx):
        return jnp.zeros_like(z[0])

    def noise_pole(self, z, ctx):
        return jnp.zeros_like(z[0])


@register_effect
class TorquerLag(StepEffect):
    """Torquer electrical lag T_dm = lag_unit·z² inside the loop."""

    name = "torquer_lag"
    parameter_names = ("torquer_time_constant_s",)
    description = "magnetoelectric torquer time constant T_dm inside the loop"

    def device(self, params, z, ctx):
        return eqx.tree_at(lambda p: p.torquer_time_constant, params, ctx.lag_unit * z[0] ** 2)

    def initial_guess(self, context):
        return np.array([1.0])

    def physical(self, z, context):
        return {"torquer_time_constant_s": float(context["lag_unit"] * z[0] ** 2)}


@register_effect
class OutputFilter(StepEffect):
    """Output filter T_f = lag_unit·z² outside the loop."""

    name = "output_filter"
    parameter_names = ("filter_time_constant_s",)
    description = "output (amplifier) filter time constant T_f outside the loop"

    def device(self, params, z, ctx):
        return eqx.tree_at(lambda p: p.filter_time_constant, params, ctx.lag_unit * z[0] ** 2)

    def initial_guess(self, context):
        return np.array([1.0])

    def physical(self, z, context):
        return {"filter_time_constant_s": float(context["lag_unit"] * z[0] ** 2)}


@register_effect
class StopSaturation(StepEffect):
    """Mechanical stops at U_out = ±peak/|z| (θ clipped there, velocity zeroed)."""

    name = "stop_saturation"
    parameter_names = ("stop_output_V",)
    description = "mechanical stops reached (output clipped at ±k_dp k_y h_max)"

    def inverse_stop(self, z, ctx):
        return jnp.abs(z[0]) / ctx.peak

    def initial_guess(self, context):
        # Just below the observed peak, so that the stops are touched and the gradient acts.
        return np.array([1.03])

    def physical(self, z, context):
        if abs(z[0]) == 0:
            return {"stop_output_V": float("inf"), "stop_displacement_m": float("inf")}
        stop = context["peak"] / abs(z[0])
        return {"stop_output_V": float(stop), "stop_displacement_m": float(stop / context["gain"])}


@register_effect
class DisturbanceDrift(StepEffect):
    """External moment ramp Ṁ (t − t_0); z = 1 moves the settled output by 10 mV over the
    record."""

    name = "disturbance_drift"
    parameter_names = ("moment_rate_Nm_per_s",)
    description = "slow drift of the external moment, M_v(t) = M_v + Ṁ t"

    def moment(self, ts, z, ctx):
        return z[0] * 1e-2 * ctx.moment_unit * (ts - ts[0]) / ctx.duration

    def initial_guess(self, context):
        return np.array([0.0])

    def physical(self, z, context):
        rate = z[0] * 1e-2 * context["moment_unit"] / context["duration"]
        return {
            "moment_rate_Nm_per_s": float(rate),
            "output_drift_V_per_s": float(rate / context["moment_unit"]),
        }


@register_effect
class ColoredNoise(StepEffect):
    """AR(1) (sampled Gauss–Markov) output noise, φ = tanh z."""

    name = "colored_noise"
    parameter_names = ("ar1_coefficient",)
    description = "correlated (Gauss–Markov) output noise instead of white"

    def noise_pole(self, z, ctx):
        return jnp.tanh(z[0])

    def initial_guess(self, context):
        return np.array([0.2])

    def physical(self, z, context):
        phi = float(np.tanh(z[0]))
        tau = -context["dt"] / np.log(abs(phi)) if 0 < abs(phi) < 1 else float("nan")
        return {"ar1_coefficient": phi, "correlation_time_s": float(tau)}


# --------------------------------------------------------------------------------------
# The model
# --------------------------------------------------------------------------------------


def _effects() -> list[StepEffect]:
    return [cls() for cls in effect_library("step").values()]


def _slot_size(effects) -> int:
    return max(effect.n_params for effect in effects)


def _refitted_device(base: ServoParams, z, prior_sigma) -> ServoParams:
    values = [getattr(base, f) * jnp.exp(prior_sigma[i] * z[i]) for i, f in enumerate(REFIT_FIELDS)]
    params = eqx.tree_at(lambda p: [getattr(p, f) for f in REFIT_FIELDS], base, values)
    zero = jnp.zeros_like(base.damping)
    return eqx.tree_at(
        lambda p: (p.torquer_time_constant, p.filter_time_constant), params, (zero, zero)
    )


SIMULATION_UNROLL = 4
"""Sample steps per iteration of the simulation's scan (fewer loop overheads on CPU)."""


def simulate_step(params: ServoParams, ts, test_voltage, moment, inverse_stop=0.0):
    """Noise-free U_out [V] of the linear loop on a uniform grid, with optional stops.

    Exact zero-order-hold discretisation of `state_space(params)` (inputs: U_test [V] and
    the external moment [N·m], each held from its sample to the next), in states scaled to
    O(1) (θ as the amplifier voltage k_dp k_y l θ). Starts at rest under the first input
    samples. With `inverse_stop` = 1/U_stop > 0 [1/V], after each sample step the deflection
    is clipped to |k_dp k_y l θ| ≤ U_stop and the velocity zeroed there (an inelastic stop,
    the O(dt) surrogate of `simulate_nonlinear`'s contact). Output at t_i: before sample i
    acts, as `simulate_linear` (they agree to rounding without stops). Float64 expected;
    jit/vmap/grad-safe.

    **Arguments:** `params` (its `external_moment` is ignored: pass it in `moment`), `ts`
    [s] (n,), `test_voltage` [V] (n,), `moment` [N·m] (n,), `inverse_stop` [1/V].

    **Returns:** U_out [V], shape (n,).
    """
    a, b, c, d = state_space(params)
    gain = params.pickoff_gain * params.amplifier_gain * params.pendulum_length  # V/rad
    period = time_constant(params)
    one = jnp.ones_like(gain)
    state_scale = jnp.stack([1 / gain, 1 / (gain * period), params.torquer_gain, one])
    input_scale = jnp.stack([one, params.torquer_gain])  # U_test in V, moment in k_dm·V
    b = b[:, jnp.array([0, 2])]
    d = d[:, jnp.array([0, 2])]
    a_s = a * state_scale[None, :] / state_scale[:, None]
    b_s = b * input_scale[None, :] / state_scale[:, None]
    c_s = c * state_scale[None, :]
    d_s = d * input_scale[None, :]
    dt = (ts[-1] - ts[0]) / (ts.shape[0] - 1)
    ad, bd = discretise(a_s, b_s, dt)
    inputs = jnp.stack([test_voltage, moment / params.torquer_gain], axis=1)

    # At rest under the first inputs: (c + k_dm k_dp k_y l) θ = k_dm U_test + M.
    drive = params.torquer_gain * (test_voltage[0] + inputs[0, 1])
    amp = gain * drive / loop_stiffness(params)
    x0 = jnp.stack([amp, 0 * amp, test_voltage[0] - amp, amp])
    has_stop = inverse_stop > 0
    stop = 1 / jnp.where(has_stop, inverse_stop, 1.0)

    def step(x, inputs_pair):
        # y_i = C x_i + D u_{i−1} (D carries only the derivative terms of the ideal lags).
        u_previous, u_now = inputs_pair
        y = c_s[0] @ x + d_s[0] @ u_previous
        x = ad @ x + bd @ u_now
        clipped = has_stop & (jnp.abs(x[0]) > stop)
        x = x.at[0].set(jnp.where(clipped, jnp.sign(x[0]) * stop, x[0]))
        x = x.at[1].set(jnp.where(clipped, 0.0, x[1]))
        return x, y

    previous = jnp.concatenate([inputs[:1], inputs[:-1]])
    _, ys = jax.lax.scan(step, x0, (previous, inputs), unroll=SIMULATION_UNROLL)
    return ys


def _model(z, candidate, base, prior_sigma, ctx, ts, u_test):
    """Prediction and AR(1) coefficient of candidate `candidate` (0: the nominal model,
    i: nominal + effect i − 1) at scaled parameters z = [refit fields, M_v, effect slot]."""
    effects = _effects()
    params = _refitted_device(base, z, prior_sigma)
    moment = jnp.full_like(ts, base.external_moment) + z[len(REFIT_FIELDS)] * ctx.moment_unit
    inverse_stop = jnp.zeros_like(ts[0])
    phi = jnp.zeros_like(ts[0])
    slot = z[_N_NOMINAL:]
    for i, effect in enumerate(effects, start=1):
        # Every effect sees zeros unless it is the candidate: exactly the nominal model.
        ze = jnp.where(candidate == i, slot[: effect.n_params], 0.0)
        params = effect.device(params, ze, ctx)
        moment = moment + effect.moment(ts, ze, ctx)
        inverse_stop = inverse_stop + effect.inverse_stop(ze, ctx)
        phi = phi + effect.noise_pole(ze, ctx)
    return simulate_step(params, ts, u_test, moment, inverse_stop), phi


def _innovations(error, phi):
    """One-step prediction errors of AR(1) noise (exact first term), shape (n,)."""
    first = jnp.sqrt(1 - phi**2) * error[:1]
    return jnp.concatenate([first, error[1:] - phi * error[:-1]])


FIT_TOLERANCE = 1e-7
"""rtol = atol of the Levenberg–Marquardt fits (on the O(1) scaled parameters)."""

FIT_MAX_STEPS = 100

BATCH_CHUNK = 16
"""Records fitted per compiled call. A vmapped batch runs until its slowest fit converges,
so modest chunks waste little; and very large single batches (600 records) were seen to
stall XLA's CPU runtime."""


def _fit_record(base, prior_sigma, ctx, ts, u_test, u_out, guesses, candidates):
    """Fit the nominal model and every candidate (vmapped over candidates) to one record."""
    n_params = guesses.shape[1]

    def residuals(z, candidate):
        prediction, phi = _model(z, candidate, base, prior_sigma, ctx, ts, u_test)
        data = _innovations(u_out - prediction, phi) * ctx.train / ctx.sigma_ref
        # The nominal model has no effect slot: pin it at 0.
        slot_pin = z[_N_NOMINAL:] * (candidate == 0)
        return jnp.concatenate([data, z[: len(REFIT_FIELDS)], slot_pin])

    # Start M_v from the mean offset of the unrefitted nominal model (DC gain 1/moment_unit).
    zero = jnp.zeros(n_params)
    nominal0, _ = _model(zero, 0, base, prior_sigma, ctx, ts, u_test)
    offset = jnp.sum((u_out - nominal0) * ctx.train) / jnp.sum(ctx.train)

    def fit_one(guess, candidate):
        z0 = guess.at[len(REFIT_FIELDS)].set(offset)
        solver = optx.LevenbergMarquardt(rtol=FIT_TOLERANCE, atol=FIT_TOLERANCE)
        solution = optx.least_squares(
            residuals, solver, z0, args=candidate, max_steps=FIT_MAX_STEPS, throw=False
        )
        z = solution.value
        prediction, phi = _model(z, candidate, base, prior_sigma, ctx, ts, u_test)
        innovations = _innovations(u_out - prediction, phi)
        converged = solution.result == optx.RESULTS.successful
        return z, prediction, innovations, phi, converged, solution.stats["num_steps"]

    fits = jax.vmap(fit_one)(guesses, candidates)
    return (nominal0,) + fits


# --------------------------------------------------------------------------------------
# Host side: contexts, evidence, localisation
# --------------------------------------------------------------------------------------


def _noise_pilot(u_out: np.ndarray) -> float:
    """White-noise σ [V] from second differences (robust to steps: median absolute value)."""
    second = np.diff(u_out, 2)
    return float(np.median(np.abs(second - np.median(second))) / 0.6745 / np.sqrt(6.0))


def _split(u_test: np.ndarray) -> int:
    """Index of the first held-out sample: the input change nearest to 1 − HELD_OUT_FRACTION
    of the record, after the first change (falls back to that fraction of the record)."""
    n = u_test.shape[0]
    changes = np.flatnonzero(np.diff(u_test) != 0) + 1
    target = int(round((1 - HELD_OUT_FRACTION) * n))
    usable = changes[(changes > (changes[0] if changes.size else 0)) & (changes < n - n // 10)]
    usable = usable[usable >= n // 2]
    if usable.size:
        return int(usable[np.argmin(np.abs(usable - target))])
    return target


def _context(data: StepData, nominal: NominalDevice) -> tuple[StepContext, dict]:
    base = nominal.params
    ts, u_out = np.asarray(data.t), np.asarray(data.u_out)
    n = ts.shape[0]
    split = _split(np.asarray(data.u_test))
    train = (np.arange(n) < split).astype(np.float64)
    gain = float(base.pickoff_gain * base.amplifier_gain * base.pendulum_length)
    stiffness = float(loop_stiffness(base))
    moment_unit = stiffness / gain
    period = float(time_constant(base))
    sigma = max(_noise_pilot(u_out), 1e-12 * max(np.max(np.abs(u_out)), 1.0))
    host = {
        "sigma_pilot": sigma,
        "duration": float(ts[-1] - ts[0]),
        "peak": float(np.max(np.abs(u_out[:split]))),
        "moment_unit": moment_unit,
        "lag_unit": 0.03 * period,
        "gain": float(base.pickoff_gain * base.amplifier_gain),
        "dt": float(data.sample_period),
        "split": split,
    }
    ctx = StepContext(
        sigma_ref=jnp.asarray(sigma),
        duration=jnp.asarray(host["duration"]),
        peak=jnp.asarray(host["peak"]),
        moment_unit=jnp.asarray(moment_unit),
        lag_unit=jnp.asarray(host["lag_unit"]),
        train=jnp.asarray(train),
        test=jnp.asarray(1 - train),
    )
    return ctx, host


def _guesses(effects, context_host) -> np.ndarray:
    """Starting points, one row per candidate (nominal first): zeros but the effect slot."""
    guesses = np.zeros((1 + len(effects), _N_NOMINAL + _slot_size(effects)))
    for i, effect in enumerate(effects, start=1):
        guesses[i, _N_NOMINAL : _N_NOMINAL + effect.n_params] = effect.initial_guess(context_host)
    return guesses


def _prior_sigma(nominal: NominalDevice) -> np.ndarray:
    return np.array([nominal.uncertainty.get(f, 0.0) for f in REFIT_FIELDS])


def _localise(data: StepData, residual: np.ndarray, sigma: float, host: dict) -> dict:
    """Where the nominal refit's residual lies: per input segment (transient vs steady
    state), in frequency against the white-noise floor, and its whiteness."""
    u = np.asarray(data.u_test)
    n = u.shape[0]
    dt = host["dt"]
    edges = np.concatenate([[0], np.flatnonzero(np.diff(u) != 0) + 1, [n]])
    segments = []
    transient_sq, transient_n, steady_sq, steady_n = 0.0, 0, 0.0, 0
    for start, stop in zip(edges[:-1], edges[1:], strict=True):
        cut = start + max(1, int(TRANSIENT_FRACTION * (stop - start)))
        r_t, r_s = residual[start:cut], residual[cut:stop]
        transient_sq += float(np.sum(r_t**2))
        transient_n += r_t.size
        steady_sq += float(np.sum(r_s**2))
        steady_n += r_s.size
        segments.append(
            {
                "t_start_s": float(data.t[start]),
                "u_test_V": float(u[start]),
                "held_out": bool(start >= host["split"]),
                "rms_transient_V": float(np.sqrt(np.mean(r_t**2))),
                "rms_steady_V": float(np.sqrt(np.mean(r_s**2))) if r_s.size else None,
            }
        )
    # Welch periodogram (Hann, 50 % overlap) against the white floor 2σ²dt [V²/Hz].
    length = int(min(256, 2 ** np.floor(np.log2(max(n // 4, 16)))))
    window = np.hanning(length)
    hop = length // 2
    frames = [residual[i : i + length] for i in range(0, n - length + 1, hop)]
    spectra = [np.abs(np.fft.rfft((f - f.mean()) * window)) ** 2 for f in frames]
    psd = 2 * dt * np.mean(spectra, axis=0) / np.sum(window**2)
    freqs = np.fft.rfftfreq(length, dt)
    floor = 2 * sigma**2 * dt
    above = psd[1:] > 4 * floor
    band = freqs[1:][above]
    return {
        "time": {
            "rms_transient_V": float(np.sqrt(transient_sq / max(transient_n, 1))),
            "rms_steady_V": float(np.sqrt(steady_sq / max(steady_n, 1))),
            "transient_fraction_of_segment": TRANSIENT_FRACTION,
        },
        "conditions": segments,
        "frequency": {
            "noise_floor_V2_per_Hz": floor,
            "peak_excess_Hz": float(freqs[1:][np.argmax(psd[1:] / floor)]),
            "peak_excess_ratio": float(np.max(psd[1:]) / floor),
            "fraction_of_bins_above_4x_floor": float(np.mean(above)),
            "band_above_4x_floor_Hz": [float(band.min()), float(band.max())] if band.size else None,
            "frequency_Hz": freqs.tolist(),
            "psd_V2_per_Hz": psd.tolist(),
        },
        "whiteness": ljung_box(residual),
        "noise_sigma_pilot_V": sigma,
    }


def _postprocess(data, nominal, host, effects, outputs) -> DiagnosisResult:
    before_refit, zs, predictions, innovations, phis, converged, steps = (
        np.asarray(o) for o in outputs
    )
    split = host["split"]
    n_train = split
    u_out = np.asarray(data.u_out)
    prior_sigma = _prior_sigma(nominal)
    names = ["nominal"] + [e.name for e in effects]
    fits = []
    for i, name in enumerate(names):
        w = innovations[i]
        rss = float(np.sum(w[:split] ** 2))
        phi = float(phis[i])
        log_like = (
            -0.5 * n_train * np.log(rss / n_train)
            + 0.5 * np.log(max(1 - phi**2, 1e-300))
            - 0.5 * float(np.sum(zs[i, : len(REFIT_FIELDS)] ** 2))
        )
        params = {}
        if i:
            slot = zs[i, _N_NOMINAL : _N_NOMINAL + effects[i - 1].n_params]
            params = effects[i - 1].physical(slot, host)
        fits.append(
            CandidateFit(
                effect=name,
                n_effect_params=0 if i == 0 else effects[i - 1].n_params,
                log_likelihood=float(log_like),
                n_train=n_train,
                held_out_ms=float(np.mean(w[split:] ** 2)),
                held_out_errors=w[split:],
                train_ms=rss / n_train,
                params=params,
                converged=bool(converged[i]),
            )
        )
    verdict, ranking, tied = rank_candidates(fits[0], fits[1:])
    floor = min(f.train_ms for f in fits)
    by_name = {f.effect: f for f in fits}
    for entry in ranking:
        g = held_out_gap(fits[0].held_out_errors, by_name[entry["effect"]].held_out_errors, floor)
        entry["gap_shrink"] = g["shrink"]
    chosen = verdict if verdict in by_name else (tied[0] if tied else "nominal")
    after = by_name[chosen].held_out_errors if verdict != "none" else fits[0].held_out_errors
    gap = held_out_gap(fits[0].held_out_errors, after, floor)
    gap["unit"] = "V"
    gap["model_after"] = chosen if verdict != "none" else "nominal"

    # Refit: the nominal parameters' shifts, and how much of the gap to the unrefitted
    # nominal model the refit closed (over the whole record).
    parameters = {}
    for j, field in enumerate(REFIT_FIELDS):
        if prior_sigma[j] == 0:
            continue
        value0 = float(getattr(nominal.params, field))
        value = value0 * float(np.exp(prior_sigma[j] * zs[0, j]))
        parameters[field] = {
            "nominal": value0,
            "refitted": value,
            "shift_relative": value / value0 - 1,
            "shift_sigma": float(zs[0, j]),
        }
    residual_nominal = u_out - predictions[0]
    rms_unrefitted = float(np.sqrt(np.mean((u_out - before_refit) ** 2)))
    rms_refitted = float(np.sqrt(np.mean(residual_nominal**2)))
    refit = {
        "parameters": parameters,
        "external_moment_Nm": {
            "nominal": float(nominal.params.external_moment),
            "refitted": float(
                nominal.params.external_moment + zs[0, len(REFIT_FIELDS)] * host["moment_unit"]
            ),
        },
        "rms_before_refit_V": rms_unrefitted,
        "rms_after_refit_V": rms_refitted,
        "gap_closed_by_refit": 1 - rms_refitted / rms_unrefitted if rms_unrefitted > 0 else 0.0,
        "converged": bool(converged[0]),
    }
    # Per estimated quantity: the scale factor K_a implied by each refit.
    chosen_index = names.index(chosen)
    scale_factors = {}
    for label, index in (("nominal_refit", 0), ("with_effect", chosen_index)):
        device = _refitted_device(nominal.params, jnp.asarray(zs[index]), jnp.asarray(prior_sigma))
        scale_factors[label] = float(scale_factor(device))
    scale_factors["prior"] = float(scale_factor(nominal.params))
    refit["scale_factor_V_per_mps2"] = scale_factors
    refit["scale_factor_shift_by_effect"] = (
        scale_factors["with_effect"] / scale_factors["nominal_refit"] - 1
    )
    # A gap the refit closes, with nothing missing afterwards, is a parameter error.
    noise_floor = float(np.sqrt(floor))
    refit["parameter_error"] = bool(
        verdict == "none" and rms_unrefitted > 3 * noise_floor and rms_refitted < 1.5 * noise_floor
    )
    sigma = float(np.sqrt(floor))
    where = _localise(data, residual_nominal, sigma, host)
    traces = {
        "t": np.asarray(data.t),
        "u_test": np.asarray(data.u_test),
        "measured": u_out,
        "nominal_unrefitted": before_refit,
        "nominal": predictions[0],
        "best": predictions[chosen_index],
        "best_name": chosen,
        "residual_before": residual_nominal,
        "residual_after": innovations[chosen_index] if verdict != "none" else residual_nominal,
        "split": split,
    }
    return DiagnosisResult(
        kind="step",
        verdict=verdict,
        tied=tied,
        ranking=ranking,
        gap=gap,
        where=where,
        refit=refit,
        traces=traces,
    )


def diagnose_step(datasets: list[StepData], nominal: NominalDevice) -> list[DiagnosisResult]:
    """Diagnose step records against a nominal device (SPEC.md §5, `step` kind).

    Records of one length are fitted together: one compilation, the batch vmapped and
    sharded across devices (`accel_jax.sweep`), every candidate model of a record vmapped.
    Each record is fitted on its first ~2/3 (up to an input change) and judged on the rest.

    **Arguments:**

    - `datasets`: validated `StepData` records (e.g. from `read_csv`).
    - `nominal`: the nominal device and its prior (`NominalDevice`).

    **Returns:** one `DiagnosisResult` per record, in order. Float64 (needs x64 enabled;
    a `ValueError` otherwise).
    """
    if not jax.config.jax_enable_x64:
        raise ValueError(
            "diagnose needs float64: call jax.config.update('jax_enable_x64', True) first "
            "(the evidence compares log-likelihoods of ~1e4 to within ~1)."
        )
    results: list[DiagnosisResult | None] = [None] * len(datasets)
    by_length: dict[int, list[int]] = {}
    for i, data in enumerate(datasets):
        by_length.setdefault(len(data.t), []).append(i)
    base = nominal.params
    prior_sigma = jnp.asarray(_prior_sigma(nominal))
    for _, indices in by_length.items():
        contexts, hosts = zip(*(_context(datasets[i], nominal) for i in indices), strict=True)
        effects = _effects()
        batch = lambda *xs: jnp.stack([jnp.asarray(x) for x in xs])  # noqa: E731
        ctx = jax.tree_util.tree_map(batch, *contexts)
        ts = batch(*(datasets[i].t for i in indices))
        u_test = batch(*(datasets[i].u_test for i in indices))
        u_out = batch(*(datasets[i].u_out for i in indices))
        guesses = jnp.asarray(np.stack([_guesses(effects, h) for h in hosts]))
        outputs = sweep(
            _fit_record,
            base,
            prior_sigma,
            ctx,
            ts,
            u_test,
            u_out,
            guesses,
            jnp.arange(1 + len(effects)),
            in_axes=(None, None, 0, 0, 0, 0, 0, None),
            chunk_size=even_chunk_size(len(indices), BATCH_CHUNK),
            desc="diagnose step",
        )
        outputs = [np.asarray(o) for o in outputs]
        for j, i in enumerate(indices):
            record_outputs = [o[j] for o in outputs]
            results[i] = _postprocess(datasets[i], nominal, hosts[j], effects, record_outputs)
    return results
