"""Identification of the INS sensor-error models in flight, from the filter's own running
estimates, with the change of model structure inside the filter (docs/models.md §4, the
paper's section 1 and its Fig. 2); and the innovation-based adaptive filter it is compared
with.

The filter runs on the single-channel INS with each sensor's error in a two-state block,
the exponential-cosine model (16) R(τ) = σ² e^{−α|τ|} cos βτ realised as the damped rotation
ds = (−αI + βJ) s dt + σ√(2α) dW (J = [[0, −1], [1, 0]]; its first component is the error).
β = 0 is the first-order Gauss–Markov model (7) (the second component is then a decoupled
copy the observation never sees), so a change of structure is a change of β, and the
state vector [ΔV, δ, a₁, a₂, ω₁, ω₂] keeps its shape: the whole flight is one `lax.scan`.

`identify_in_flight` runs the filter block by block (`retune_every` steps). After each block:

1. The filtered estimates of Δa and Δω, taken every `decimation` steps, fill a sliding
   window (the last `window` of them); its sample autocovariance R̂_k (11) is computed over
   `max_lag` lags by FFT.
2. Shrinkage: the filtered mean x̂ is a conditional mean, so its autocovariance is lower
   than the sensor error's: by the law of total covariance, Cov(x_{t+k}, x_t) =
   Cov(x̂_{t+k}, x̂_t) + (Φ_s(kΔ) P_s)₀₀ with P_s the filter's covariance of the sensor block
   and Φ_s its transition (a future state is correlated with today's error through the
   dynamics only; e_{t+k} is orthogonal to x̂_t). The window's mean P_s, carried by the
   current model, is added to R̂ (`correct_shrinkage`). Without it the loop feeds on
   estimates that shrink as the filter trusts its model more, and collapses its own
   process noise.
3. Both structures are fitted by the paper's rules (`structure_candidates`): Gauss–Markov by
   rule (15) on the corrected R̂ (lags while r_j > e⁻¹); exponential-cosine by (19)–(21),
   its β and α from the estimates' own R̂ (whose zero crossing the correction would move),
   its σ² from the corrected R̂_0. Each structure is fitted from the estimates of the filter
   that runs it, corrected with that filter's model (`own_filter_candidates`): the current
   structure from the main filter, the other from the filter beside it with that sensor
   alone in the other structure. (Fitted from the main filter's estimates, whose shape
   follows the main filter's model, the other structure's candidate was biased — a gyro
   drift with 1/α = 14,400 s fitted at 961 s — and the Gauss–Markov accelerometer took
   exponential-cosine at the drift's frequency on 7 of 16 logs of a strongly oscillating
   drift, against 0 of 16 so.)
4. Structure: beside the main filter run three more, one for each other combination of
   the two sensors' structures (each sensor in its other structure takes its latest fit of
   that structure). Over the window, each combination's velocity log-likelihood less
   (½ ln n + ln B) per exponential-cosine sensor (n the observations counted: the BIC
   price of β; B the log's retunes, at each of which the test is made again: without it a
   Gauss–Markov drift ended exponential-cosine on 7 of 64 logs) is compared, and both
   sensors take the best combination's structures — the test the batch selection
   (`select_noise_model`) makes, on the observations the filter has rather than on a
   sensor record. The two are chosen together: an oscillating model of one sensor must
   not win by absorbing the other's misfit (tested one sensor at a time, on a log whose
   drift holds βτ_c = 3 against a 0.01 m/s reference, the drift switched on 5 of 16 logs
   from the ×10 start; jointly on 11 of 16). Blocks count once both alternatives have been
   fitted, and the test waits for `min_window` of them. (A test on the estimates' own
   autocorrelation was tried first and rejected: their shape follows the filter's model,
   and it switched a Gauss–Markov accelerometer to exponential-cosine on about half the
   logs of a filter started with too slow a model.)
5. Guards: no retune before `min_window` samples are in the window or when a rule fails;
   σ and α move by at most `max_change` per retune; 1/α is capped at the window's span over
   `min_correlation_times` (`cap_correlation_time`; otherwise such a retune is refused).
6. The discrete model is rebuilt (Van Loan, as `INSNoiseChannel`) and the filter goes on
   with its state and covariance.

`adaptation="sage_husa"` is the baseline the paper argues against: the model structure and
parameters stay as started and the process covariance follows the innovations alone, the
simplified Sage–Husa estimator Q_k = (1 − d_k) Q_{k−1} + d_k K_k ν_k² K_kᵀ, d_k = (1 − b)/
(1 − b^{k+1}), b = 1 − 1/`fading_window` (the form without P_k − Φ P_{k−1} Φᵀ, which keeps
Q positive semi-definite). `adaptation="none"` is the filter with the models it is given.

What velocity aiding can observe: ΔV' = −gδ + Δa, so the velocity record sees Δa and the
tilt δ only through −gδ + Δa; they separate through δ's slow Schuler dynamics (period
2π√(R/g) ≈ 84 min), so a sensor error's slow part is shared with tilt and is shrunk most
(`tests/test_kalman_online.py` and the noise study give the steady-state variance each
sensor error keeps).

float64 throughout (gyro variances ~1e-15 rad²/s² beside g).
"""

from __future__ import annotations

from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike

from ._checks import require_float64
from ._kalman import _matmul, _symmetrise
from ._kalman_ins import EARTH_RADIUS
from ._kalman_sensor import (
    SensorErrorModel,
    _window_autocovariance,
    online_channel,
    structure_candidates,
)
from ._params import _concrete
from ._static import STANDARD_GRAVITY


class OnlineIdentification(eqx.Module):
    """Settings of `identify_in_flight` (steps and samples are counts at the filter's rate).

    - `adaptation`: "identify" (the paper's loop), "sage_husa" (the innovation-based
      baseline) or "none" (the filter with the models it is given).
    - `retune_every`: steps per block; the models are re-identified after each.
    - `decimation`: the estimates enter the autocovariance every `decimation` steps.
    - `window`: samples (decimated) in the sliding window.
    - `max_lag`: lags (decimated) of the autocovariance.
    - `min_window`: samples (decimated) in the window before the first retune.
    - `min_correlation_times`: the window must span this many correlation times 1/α̂.
    - `max_change`: σ and α change by at most this factor per retune.
    - `correct_shrinkage`: add the filter's propagated covariance to the estimates'
      autocovariance (law of total covariance).
    - `choose_structure`: run the joint log-likelihood structure test (three more filters)
      and let
      it switch between Gauss–Markov and exponential-cosine (otherwise each sensor keeps
      the structure it starts with).
    - `fading_window`: Sage–Husa's memory N (b = 1 − 1/N), in steps.
    - `cap_correlation_time`: a fitted 1/α longer than the window's span over
      `min_correlation_times` is capped there (else the retune is refused).
    - `own_filter_candidates`: fit each structure from the estimates of the filter that
      runs it (with the structure test; otherwise both from the main filter's).
    """

    adaptation: Literal["identify", "sage_husa", "none"] = eqx.field(static=True, default="identify")
    retune_every: int = eqx.field(static=True, default=1800)
    decimation: int = eqx.field(static=True, default=30)
    window: int = eqx.field(static=True, default=2880)
    max_lag: int = eqx.field(static=True, default=480)
    min_window: int = eqx.field(static=True, default=720)
    min_correlation_times: float = eqx.field(static=True, default=10.0)
    max_change: float = eqx.field(static=True, default=10.0)
    correct_shrinkage: bool = eqx.field(static=True, default=True)
    choose_structure: bool = eqx.field(static=True, default=True)
    fading_window: float = eqx.field(static=True, default=3600.0)
    cap_correlation_time: bool = eqx.field(static=True, default=True)
    own_filter_candidates: bool = eqx.field(static=True, default=True)

    def __check_init__(self):
        if self.adaptation not in ("identify", "sage_husa", "none"):
            raise ValueError(
                "OnlineIdentification.adaptation must be 'identify', 'sage_husa' or 'none', "
                f"got {self.adaptation!r}."
            )
        for name in ("retune_every", "decimation", "window", "max_lag", "min_window"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"OnlineIdentification.{name} must be ≥ 1, got {getattr(self, name)!r}.")
        if self.retune_every % self.decimation:
            raise ValueError(
                f"OnlineIdentification: retune_every ({self.retune_every}) must be a multiple "
                f"of decimation ({self.decimation})."
            )
        if 2 * (self.max_lag + 1) > self.window:
            raise ValueError(
                f"OnlineIdentification: the window ({self.window} samples) must hold at least "
                f"2 (max_lag + 1) = {2 * (self.max_lag + 1)} samples."
            )
        if not (self.max_change > 1 and self.fading_window >= 1 and self.min_correlation_times > 0):
            raise ValueError(
                "OnlineIdentification: max_change must be > 1, fading_window ≥ 1 and "
                "min_correlation_times > 0."
            )


class OnlineRun(eqx.Module):
    """The in-flight filter over T steps in B blocks.

    **Fields:**

    - `kinematic_means`: [ΔV̂, δ̂] filtered, shape (T, 2).
    - `kinematic_covariances`: their filtered covariance, shape (T, 2, 2).
    - `innovations`, `innovation_variances`: ν_k and S_k, shape (T,).
    - `sensor_estimates`: the filtered Δâ, Δω̂ every `decimation` steps (the series the
      loop identifies from), shape (T / decimation, 2).
    - `sensor_covariances`: the filter's covariance of each sensor's two-state block at
      the same steps, shape (T / decimation, 2, 2, 2) (the shrinkage correction's P_s).
    - `models`: (σ, α, β) of [accelerometer, gyro] in force during each block, shape
      (B, 2, 3) (block 0: the starting models).
    - `alternative_models`: (σ, α, β) of each sensor's other structure during each block,
      the candidate the structure test weighs (with the test; else the placeholder it
      starts with), shape (B, 2, 3).
    - `retuned`: whether the models were re-identified after each block, shape (B, 2).
    - `structure_statistic`: after each block, per sensor, the best penalised window
      log-likelihood of the combinations with that sensor exponential-cosine less the best
      of those with it Gauss–Markov, shape (B, 2) (> 0: exponential-cosine chosen; NaN
      before the test has enough blocks or without it).
    """

    kinematic_means: Array
    kinematic_covariances: Array
    innovations: Array
    innovation_variances: Array
    sensor_estimates: Array
    sensor_covariances: Array
    models: Array
    alternative_models: Array
    retuned: Array
    structure_statistic: Array


def _limit(new, current, span, settings: OnlineIdentification):
    """The guards on one retune: σ and α move by at most `max_change`, 1/α is capped at
    span / `min_correlation_times` (or the retune refused); returns (model, ok)."""
    limit = settings.max_change
    sigma = jnp.clip(new.sigma, current.sigma / limit, current.sigma * limit)
    alpha = jnp.clip(new.decay_rate, current.decay_rate / limit, current.decay_rate * limit)
    ok = jnp.ones((), bool)
    if settings.cap_correlation_time:
        # The window tells correlation times up to span / min_correlation_times: a longer
        # fit (often the current model's own, carried in by the shrinkage correction) is
        # capped there rather than refused.
        alpha = jnp.maximum(alpha, settings.min_correlation_times / span)
    else:
        ok = span * new.decay_rate >= settings.min_correlation_times
    return SensorErrorModel(sigma, alpha, new.angular_frequency), ok


def _corrected(model, x_window, p_window, count, settings, lag_time):
    """The window's autocovariance with the shrinkage correction under `model` (the model
    the filter that made the estimates ran), and the estimates' own (the shape)."""
    R, _ = _window_autocovariance(x_window, count, settings.max_lag)
    shape = R
    if settings.correct_shrinkage:
        mask = jnp.arange(x_window.shape[0]) >= x_window.shape[0] - count
        p_mean = jnp.sum(jnp.where(mask[:, None, None], p_window, 0.0), axis=0) / count
        lags = jnp.arange(settings.max_lag + 1, dtype=R.dtype) * lag_time
        R = R + jax.vmap(lambda tau: (model.transition(tau) @ p_mean)[0, 0])(lags)
    return R, shape


def _retune(current, alternative, use_ec, windows, count, settings, lag_time, own):
    """One sensor's re-identification after a block: (model, alternative, retuned,
    alternative retuned). The structure `use_ec` is decided by the caller (the
    log-likelihood test); the model takes that structure's fit, the alternative the
    other's. `windows`: ((x, P) of the main filter, (x, P) of the filter that runs this
    sensor in its other structure): each structure is fitted from the estimates of the
    filter that runs it, corrected with that filter's model, when `own` (the settings'
    `own_filter_candidates` with the structure test); otherwise both from the main filter."""
    (x_main, p_main), (x_alt, p_alt) = windows
    R, shape = _corrected(current, x_main, p_main, count, settings, lag_time)
    gm, ec, gm_ok, ec_ok = structure_candidates(R, lag_time, shape)
    if own:
        R_alt, shape_alt = _corrected(alternative, x_alt, p_alt, count, settings, lag_time)
        gm_a, ec_a, gm_a_ok, ec_a_ok = structure_candidates(R_alt, lag_time, shape_alt)
        cur_ec = current.angular_frequency > 0
        # The current structure's fit from the main filter, the other's from its own.
        ec = jax.tree.map(lambda a, m: jnp.where(cur_ec, m, a), ec_a, ec)
        gm = jax.tree.map(lambda a, m: jnp.where(cur_ec, a, m), gm_a, gm)
        ec_ok = jnp.where(cur_ec, ec_ok, ec_a_ok)
        gm_ok = jnp.where(cur_ec, gm_a_ok, gm_ok)
    span = count * lag_time
    enough = count >= settings.min_window

    def pick(flag, base):
        new = jax.tree.map(lambda e, g: jnp.where(flag, e, g), ec, gm)
        new, ok = _limit(new, base, span, settings)
        ok = ok & enough & jnp.where(flag, ec_ok, gm_ok)
        return jax.tree.map(lambda n, c: jnp.where(ok, n, c), new, base), ok

    # The guards compare each structure's fit with the last model of that structure: the
    # current model's when it keeps its structure, the alternative's when it changes.
    switched = use_ec != (current.angular_frequency > 0)
    base = jax.tree.map(lambda a, c: jnp.where(switched, a, c), alternative, current)
    other = jax.tree.map(lambda c, a: jnp.where(switched, c, a), current, alternative)
    model, ok = pick(use_ec, base)
    alternative, alternative_ok = pick(~use_ec, other)
    return model, alternative, ok, alternative_ok


def _check_log(observations, settings: OnlineIdentification):
    z = jnp.asarray(observations, float)
    if z.ndim != 1:
        raise ValueError(f"identify_in_flight: observations must be 1-D (T,), got shape {z.shape}.")
    if z.shape[0] < settings.retune_every or z.shape[0] % settings.retune_every:
        raise ValueError(
            f"identify_in_flight: the log's length ({z.shape[0]} steps) must be a positive "
            f"multiple of retune_every ({settings.retune_every}); trim or pad the log."
        )
    concrete = _concrete(z)
    if concrete is not None and not np.all(np.isfinite(concrete)):
        raise ValueError(
            f"identify_in_flight: observation {int(np.argmax(~np.isfinite(concrete)))} is not "
            "finite; the log must be finite."
        )
    return z


def identify_in_flight(
    observations: ArrayLike,
    accel: SensorErrorModel,
    gyro: SensorErrorModel,
    *,
    velocity_noise,
    settings: OnlineIdentification = OnlineIdentification(),
    sample_interval: float = 1.0,
    initial_covariance: ArrayLike | None = None,
    gravity=STANDARD_GRAVITY,
    radius=EARTH_RADIUS,
) -> OnlineRun:
    """Filter a velocity log with the six-state INS channel and re-identify its sensor
    models in flight (see the module docstring), as one `lax.scan`; jit/vmap-safe (vmap over
    Monte Carlo logs).

    **Arguments:**

    - `observations`: z_k = ΔV_k + v_k [m/s], shape (T,), T a multiple of
      `settings.retune_every`.
    - `accel`, `gyro`: the starting `SensorErrorModel`s [m/s², rad/s].
    - `velocity_noise`: σ_v [m/s].
    - `settings`: `OnlineIdentification`.
    - `sample_interval`: Δ [s].
    - `initial_covariance`: the prior (6 × 6) at the first observation; default diag(0.1²,
      1e-4², sensors at their stationary σ²), the prior of `ins_initial_covariance`.

    **Returns:** `OnlineRun`. float64 required (a `ValueError` otherwise); models built
    in float32 are widened.
    """
    require_float64(
        "identify_in_flight",
        "the tilt's variance, ~1e-8 rad², sits beside the velocity's ~1e-2 m²/s² in one "
        "covariance",
    )
    z = _check_log(observations, settings)
    # Models built before x64 was on hold float32 leaves: widen them (the scan's carry
    # holds the models, and its types must not change).
    accel, gyro = (jax.tree.map(lambda v: jnp.asarray(v, jnp.float64), m) for m in (accel, gyro))
    dt = float(sample_interval)
    block, dec = settings.retune_every, settings.decimation
    n_blocks = z.shape[0] // block
    per_block = block // dec
    n_dec = n_blocks * per_block
    lag_time = dec * dt
    size = settings.window
    if initial_covariance is None:
        p0 = jnp.diag(
            jnp.stack(
                [
                    jnp.asarray(0.01),
                    jnp.asarray(1e-8),
                    accel.sigma**2,
                    accel.sigma**2,
                    gyro.sigma**2,
                    gyro.sigma**2,
                ]
            ).astype(float)
        )
    else:
        p0 = jnp.asarray(initial_covariance, float)
        if p0.shape != (6, 6):
            raise ValueError(f"identify_in_flight: initial_covariance must be 6 × 6, got {p0.shape}.")
    r = jnp.asarray(velocity_noise, float) ** 2
    fade = 1.0 - 1.0 / settings.fading_window

    def model_of(accel, gyro):
        return online_channel(accel, gyro, velocity_noise, dt, gravity=gravity, radius=radius)

    identify = settings.adaptation == "identify"
    test = identify and settings.choose_structure
    # Filters run side by side: the main one, and (with the structure test) one for each
    # other combination of the two sensors' structures — accelerometer in its other
    # structure, gyro in its other, both — for the joint log-likelihood comparison.
    n_filters = 4 if test else 1
    window_blocks = max(1, (size * dec) // block)
    min_blocks = max(1, -(-(settings.min_window * dec) // block))
    log_2pi = jnp.log(2 * jnp.pi)
    # Filter f runs sensor i in its other structure where bit i of f is set; combination
    # c (bit i set: sensor i exponential-cosine) is run by filter c XOR (the current
    # structures' bits). Row c: which sensors are exponential-cosine in combination c.
    combos = jnp.array([[False, False], [True, False], [False, True], [True, True]])

    def update_predict(mean, cov, z_k, transition, process):
        innovation = z_k - mean[0]
        s = cov[0, 0] + r
        gain = cov[:, 0] / s
        mean = mean + gain * innovation
        # Joseph's form (I − K H) P (I − K H)ᵀ + K r Kᵀ with H = e₀ᵀ, as two rank-one
        # updates (the products with I − K H touch one row and one column).
        left = cov - jnp.outer(gain, cov[0])
        cov = _symmetrise(left - jnp.outer(left[:, 0], gain) + r * jnp.outer(gain, gain))
        log_lik = -0.5 * (log_2pi + jnp.log(s) + innovation**2 / s)
        new_mean = _matmul(transition, mean[:, None])[:, 0]
        new_cov = _symmetrise(_matmul(_matmul(transition, cov), transition.T) + process)
        return new_mean, new_cov, (mean, cov, innovation, s, gain, log_lik)

    def step(carry, z_k, transitions, processes):
        means, covs, q, k, log_lik_sum, _ = carry
        if settings.adaptation == "sage_husa":
            processes = processes.at[0].set(q)
        means, covs, (mean, cov, innovation, s, gain, log_lik) = jax.vmap(
            update_predict, in_axes=(0, 0, None, 0, 0)
        )(means, covs, z_k, transitions, processes)
        if settings.adaptation == "sage_husa":
            d = (1 - fade) / (1 - fade ** (k + 1))
            q = (1 - d) * q + d * innovation[0] ** 2 * jnp.outer(gain[0], gain[0])
            # The filter predicted with the previous Q; the next step uses the new one.
        # The filtered sensor blocks of every filter (the loop reads them at the last step
        # of each decimation interval), and one packed row of the main filter's outputs.
        blocks = jnp.stack([cov[:, 2:4, 2:4], cov[:, 4:6, 4:6]], axis=1)
        sensors = (mean[:, jnp.array([2, 4])], blocks)
        row = jnp.concatenate([mean[0, :2], cov[0, :2, :2].ravel(), innovation[:1], s[:1]])
        return (means, covs, q, k + 1, log_lik_sum + log_lik, sensors), row

    def interval(carry, z_interval, transitions, processes):
        """`dec` filter steps; the filtered sensor blocks at the last of them."""
        carry, rows = jax.lax.scan(
            lambda c, zk: step(c, zk, transitions, processes), carry, z_interval
        )
        return carry, (rows, carry[5])

    def sensor(models, i):
        return jax.tree.map(lambda v: v[i], models)

    def stack(a, g):
        return jax.tree.map(lambda x, y: jnp.stack([x, y]), a, g)

    def outer(carry, b):
        means, covs, q, k, models, alternatives, valid, x_buf, p_buf, l_buf, v_buf = carry
        accel_m, gyro_m = sensor(models, 0), sensor(models, 1)
        pairs = [(accel_m, gyro_m)]
        if test:
            accel_a, gyro_a = sensor(alternatives, 0), sensor(alternatives, 1)
            pairs += [(accel_a, gyro_m), (accel_m, gyro_a), (accel_a, gyro_a)]
        discrete = [model_of(*pair) for pair in pairs]
        transitions = jnp.stack([m.transition for m in discrete])
        processes = jnp.stack([m.process_covariance for m in discrete])
        z_block = jax.lax.dynamic_slice_in_dim(z, b * block, block).reshape(per_block, dec)
        sensors0 = (jnp.zeros((n_filters, 2)), jnp.zeros((n_filters, 2, 2, 2)))
        (means, covs, q, k, log_lik_sum, _), (rows, (sensor_mean, sensor_cov)) = jax.lax.scan(
            lambda c, zi: interval(c, zi, transitions, processes),
            (means, covs, q, k, jnp.zeros(n_filters), sensors0),
            z_block,
        )
        rows = rows.reshape(block, rows.shape[-1])
        at = size + b * per_block
        x_buf = jax.lax.dynamic_update_slice_in_dim(x_buf, sensor_mean, at, 0)
        p_buf = jax.lax.dynamic_update_slice_in_dim(p_buf, sensor_cov, at, 0)
        params, other = (
            jnp.stack([m.sigma, m.decay_rate, m.angular_frequency], axis=-1)
            for m in (models, alternatives)
        )
        retuned = jnp.zeros(2, bool)
        statistic = jnp.full(2, jnp.nan)
        if identify:
            end = size + (b + 1) * per_block
            count = jnp.minimum((b + 1) * per_block, size).astype(float)
            if test:
                block_ll = log_lik_sum  # (4,), by filter
                is_ec = models.angular_frequency > 0
                # By combination: combination c was run by filter c XOR is_ec.
                code = jnp.sum(jnp.where(is_ec, jnp.array([1, 2]), 0))
                l_buf = l_buf.at[window_blocks + b].set(block_ll[jnp.arange(4) ^ code])
                v_buf = v_buf.at[window_blocks + b].set(jnp.all(valid))
                lls = jax.lax.dynamic_slice_in_dim(l_buf, b + 1, window_blocks)
                counted = jax.lax.dynamic_slice_in_dim(v_buf, b + 1, window_blocks)
                n_valid = jnp.sum(counted)
                total = jnp.sum(jnp.where(counted[:, None], lls, 0.0), axis=0)  # (4,)
                # BIC's price of each β, plus ln B for making the test at each of the log's
                # B retunes (the likelihood ratio's tail falls as e^{−c}: B tests at c + ln B
                # share the false-switch rate of one at c). The two sensors are chosen
                # together: an oscillating model of one sensor must not win by absorbing the
                # other's misfit (seen with separate tests: the Gauss–Markov accelerometer
                # taken as exponential-cosine while the gyro drift was still Gauss–Markov).
                price = 0.5 * jnp.log(jnp.maximum(n_valid, 1) * block) + jnp.log(n_blocks)
                score = total - price * jnp.sum(combos, axis=1)
                best = jnp.argmax(score)
                decided = n_valid >= min_blocks
                # Per sensor: the best score with it exponential-cosine over the best with
                # it Gauss–Markov (> 0: exponential-cosine chosen).
                margin = jnp.stack(
                    [
                        jnp.max(jnp.where(combos[:, i], score, -jnp.inf))
                        - jnp.max(jnp.where(combos[:, i], -jnp.inf, score))
                        for i in range(2)
                    ]
                )
                statistic = jnp.where(decided, margin, jnp.nan)
                use_ec = jnp.where(decided, combos[best], is_ec)
            else:
                use_ec = models.angular_frequency > 0
            new_models, new_alternatives, alt_ok, oks = [], [], [], []
            for i in range(2):
                # The main filter's estimates, and those of the filter that runs sensor i
                # alone in its other structure (filter 1 + i; the main one without the test).
                windows = tuple(
                    (
                        jax.lax.dynamic_slice_in_dim(x_buf[:, f, i], end - size, size),
                        jax.lax.dynamic_slice_in_dim(p_buf[:, f, i], end - size, size),
                    )
                    for f in (0, 1 + i if test else 0)
                )
                m, alt, ok, aok = _retune(
                    sensor(models, i),
                    sensor(alternatives, i),
                    use_ec[i],
                    windows,
                    count,
                    settings,
                    lag_time,
                    settings.own_filter_candidates and test,
                )
                new_models.append(m)
                new_alternatives.append(alt)
                oks.append(ok)
                alt_ok.append(aok)
            models, alternatives = stack(*new_models), stack(*new_alternatives)
            retuned = jnp.stack(oks)
            valid = valid | jnp.stack(alt_ok)
        return (means, covs, q, k, models, alternatives, valid, x_buf, p_buf, l_buf, v_buf), (
            rows,
            (params, other),
            retuned,
            statistic,
        )

    models = stack(accel, gyro)
    # The other structure of each sensor, before it is first identified: a placeholder
    # (βτ_c = 1) whose log-likelihood is not counted (`valid` is False until then).
    alternatives = stack(
        *(
            SensorErrorModel(m.sigma, m.decay_rate, jnp.where(m.angular_frequency > 0, 0.0, m.decay_rate))
            for m in (accel, gyro)
        )
    )
    q0 = model_of(accel, gyro).process_covariance
    # Buffers front-padded by one window, so every window is one dynamic slice.
    x_buf = jnp.zeros((size + n_dec, n_filters, 2))
    p_buf = jnp.zeros((size + n_dec, n_filters, 2, 2, 2))
    l_buf = jnp.zeros((window_blocks + n_blocks, 4))
    v_buf = jnp.zeros((window_blocks + n_blocks,), bool)
    carry = (
        jnp.zeros((n_filters, 6)),
        jnp.broadcast_to(p0, (n_filters, 6, 6)),
        q0,
        jnp.zeros((), float),
        models,
        alternatives,
        jnp.zeros(2, bool),
        x_buf,
        p_buf,
        l_buf,
        v_buf,
    )
    final, (steps, (params, other), retuned, statistic) = jax.lax.scan(
        outer, carry, jnp.arange(n_blocks)
    )
    steps = steps.reshape(-1, steps.shape[-1])
    kin_mean, kin_cov = steps[:, :2], steps[:, 2:6].reshape(-1, 2, 2)
    innovation, s = steps[:, 6], steps[:, 7]
    return OnlineRun(
        kinematic_means=kin_mean,
        kinematic_covariances=kin_cov,
        innovations=innovation,
        innovation_variances=s,
        sensor_estimates=final[7][size:, 0],
        sensor_covariances=final[8][size:, 0],
        models=params,
        alternative_models=other,
        retuned=retuned,
        structure_statistic=statistic,
    )
