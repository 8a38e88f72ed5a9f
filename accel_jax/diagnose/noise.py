"""The `noise` kind: a static record, its nominal model (white noise) and its effects.

**Nominal model** (what a white-noise assumption means, SPEC.md §4): the indicated
acceleration of a static sensor is an unknown constant level plus white noise,

    a_out(t_k) = ℓ + σ_w w_k                                                          [g].

The level has a diffuse prior in every model (the record's mean is not known in advance),
so that all candidates are compared on the same terms, by the exact Gaussian likelihood of
the record conditional on its first sample, log p(x_2..x_N | x_1), as
`accel_jax._noise.log_likelihood` defines it.

**Effects** (each adds one process of `accel_jax._noise` to the white noise and is exactly
the nominal model when its amplitude is zero):

- `gauss_markov`: + first-order Gauss–Markov noise, R(τ) = σ² e^{−|τ|/τ_c};
- `exp_cosine`: + exponential-cosine noise, R(τ) = σ² e^{−α|τ|} cos βτ (the paper's
  "structured residual" model, Chernodarov et al. (16));
- `random_walk`: the level itself walks, ℓ_{k+1} = ℓ_k + √(qΔ) w_k (at q = 0 it is the
  nominal constant level, exactly).

An exponential-cosine noise at β = 0 is a Gauss–Markov noise, and a Gauss–Markov noise whose
τ_c outgrows the record looks like a random walk; those nested pairs are told apart by a
likelihood-ratio test when the evidence alone ties (`rank_candidates(nested=...)`).

**Fit**: exact maximum likelihood on the training part (the first `1 − HELD_OUT_FRACTION`
of the record): a Whittle (frequency-domain) fit of the differenced record gives the start,
then BFGS (optimistix) on the exact likelihood polishes it. The likelihood is the Kalman
filter of the state-space forms of `accel_jax._noise` (state: level, the two components of
the exponential-cosine rotation — a Gauss–Markov noise is its β = 0 case), written out for
this three-state model with a scalar observation so that a batch of records × candidates
runs as one fused loop (the generic `accel_jax._kalman.kalman_filter` gives the same
numbers — the tests check it against `accel_jax._noise.log_likelihood` — about ten times
slower). Parameters are scaled so that zero is reachable: the effect's standard deviation is
z·s₀ (s₀ the record's RMS), the random walk's increment RMS z·s₀.

**Held out**: the last `HELD_OUT_FRACTION` of the record. The filter with the training fit
runs over the whole record, and the one-step prediction errors (innovations) of the
held-out part are the held-out errors: the gap is the RMS innovation above the noise floor
(the innovation variance the best model leaves on the training part).

Float64 throughout (log-likelihoods of thousands of samples compared to within a unit).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .._data import DataError, NoiseData, NominalDevice
from .._noise import _DIFFUSE, initial_model
from .._sweep import even_chunk_size, sweep
from . import openworld
from .base import (
    NESTED_LEVEL,
    AbstractEffect,
    CandidateFit,
    DiagnosisResult,
    _resolve_nested,
    effect_library,
    held_out_gap,
    ljung_box,
    rank_candidates,
    register_effect,
    require_float64,
)

HELD_OUT_FRACTION = 1 / 3
"""The last third of the record is held out."""

WHITTLE_STEPS = 128
POLISH_STEPS = 64
"""BFGS step budgets of the Whittle start and of the exact-likelihood polish."""

FIT_TOLERANCE = 1e-6
"""rtol = atol of the BFGS fits (on O(1) scaled parameters; the objective is −ln L / n)."""

NESTED = {"exp_cosine": "gauss_markov", "gauss_markov": "random_walk"}
"""An exponential-cosine noise at β = 0 is a Gauss–Markov noise; a Gauss–Markov noise with
τ_c → ∞ (σ² ∝ τ_c) is a random walk."""

STARTS = 8
"""Whittle starts per candidate (the `initial_model` guess and a grid, see
`AbstractNoiseEffect.alternative_starts`)."""

WHITTLE_BANDS = 64
"""The Whittle start uses the periodogram averaged over this many frequency bands (the
lowest bins one by one, then log-spaced): a start needs the right basin, not the last digit,
and every start of every candidate of every record evaluates it (8 × 4 per record)."""

BATCH_CHUNK = 64
"""Records fitted per compiled call (a vmapped batch runs until its slowest fit stops)."""

_SLOT = 3  # the largest effect's parameter count (exp_cosine)


class NoiseComponents(eqx.Module):
    """The processes added to the white noise, in the record's normalised units (s₀ = 1).

    **Fields:** `variance` v of the coloured block; `decay` ρ = e^{−αΔ} of the block per
    sample; `rotation` θ = βΔ of the block per sample (0: Gauss–Markov); `walk` qΔ, the
    level's increment variance per sample.
    """

    variance: jax.Array
    decay: jax.Array
    rotation: jax.Array
    walk: jax.Array


class AbstractNoiseEffect(AbstractEffect):
    """An effect on a static record. One hook: `components(z)` gives the processes it adds
    (`NoiseComponents`; zero variance and zero walk at z = 0: the nominal model)."""

    kind = "noise"

    def components(self, z) -> NoiseComponents:
        zero = jnp.zeros_like(z[0])
        return NoiseComponents(zero, zero, zero, zero)

    def guess_from(self, model, scale, dt) -> np.ndarray:
        """A start z from `accel_jax._noise.initial_model`'s model of the record."""
        raise NotImplementedError

    def alternative_starts(self, guess: np.ndarray) -> np.ndarray:
        """Further starts for the Whittle fit, shape (STARTS − 1, n_params): the likelihood
        of a correlated noise can have several maxima (in τ_c, in β); the best Whittle fit
        of all starts goes on to the exact polish."""
        return np.repeat(guess[None, :], STARTS - 1, axis=0)

    @property
    def structure(self) -> str:
        """The `accel_jax._noise` structure of nominal + this effect."""
        return f"white+{self.name}"

    def initial_guess(self, context) -> np.ndarray:
        """z from `accel_jax._noise.initial_model` of the normalised training record
        (`context`: `initial_models` by effect name, `dt`)."""
        model = context["initial_models"][self.name]
        return self.guess_from(model.components[1], 1.0, context["dt"])


@register_effect
class GaussMarkovNoise(AbstractNoiseEffect):
    """+ Gauss–Markov noise: σ = s₀·z₀, τ_c = Δ·e^{−z₁}."""

    name = "gauss_markov"
    parameter_names = ("sigma_g", "correlation_time_s")
    description = "first-order Gauss–Markov (exponentially correlated) noise"

    def components(self, z):
        return NoiseComponents(z[0] ** 2, jnp.exp(-jnp.exp(z[1])), 0 * z[0], 0 * z[0])

    def guess_from(self, model, scale, dt):
        return np.array([float(model.sigma) / scale, math.log(dt / float(model.correlation_time))])

    def alternative_starts(self, guess):
        # τ_c from 1 to 300 samples.
        grid = np.log(1 / np.geomspace(1.0, 300.0, STARTS - 1))
        return np.stack([np.full(STARTS - 1, guess[0]), grid], axis=1)

    def physical(self, z, context):
        return {
            "sigma_g": abs(float(z[0])) * context["scale"],
            "correlation_time_s": context["dt"] / math.exp(float(z[1])),
        }


@register_effect
class ExpCosineNoise(AbstractNoiseEffect):
    """+ exponential-cosine noise: σ = s₀·z₀, α = e^{z₁}/Δ, β = z₂²/Δ."""

    name = "exp_cosine"
    parameter_names = ("sigma_g", "decay_rate_per_s", "angular_frequency_rad_per_s")
    description = "exponential-cosine (damped oscillatory) correlated noise"

    def components(self, z):
        return NoiseComponents(z[0] ** 2, jnp.exp(-jnp.exp(z[1])), z[2] ** 2, 0 * z[0])

    def guess_from(self, model, scale, dt):
        theta = min(float(model.angular_frequency) * dt, 0.9 * math.pi)
        return np.array(
            [float(model.sigma) / scale, math.log(float(model.decay_rate) * dt), math.sqrt(theta)]
        )

    def alternative_starts(self, guess):
        # Periods from 3 to 100 samples, two oscillations per decay time.
        theta = 2 * np.pi / np.geomspace(3.0, 100.0, STARTS - 1)
        return np.stack(
            [np.full(STARTS - 1, guess[0]), np.log(theta / (4 * np.pi)), np.sqrt(theta)], axis=1
        )

    def physical(self, z, context):
        dt = context["dt"]
        theta = float(z[2]) ** 2 % (2 * math.pi)
        theta = min(theta, 2 * math.pi - theta)  # cos θk is even and 2π-periodic in θ
        beta = theta / dt
        return {
            "sigma_g": abs(float(z[0])) * context["scale"],
            "decay_rate_per_s": math.exp(float(z[1])) / dt,
            "angular_frequency_rad_per_s": beta,
            "period_s": 2 * math.pi / beta if beta > 0 else float("inf"),
        }


@register_effect
class RandomWalkNoise(AbstractNoiseEffect):
    """+ random walk of the level: increment RMS per sample √(qΔ) = s₀·z₀."""

    name = "random_walk"
    parameter_names = ("intensity_g2_per_s",)
    description = "random walk of the level (bias instability growing without bound)"

    def components(self, z):
        zero = 0 * z[0]
        return NoiseComponents(zero, zero, zero, z[0] ** 2)

    def guess_from(self, model, scale, dt):
        return np.array([math.sqrt(float(model.intensity) * dt) / scale])

    def alternative_starts(self, guess):
        # Increment RMS from 1e-3 to 0.3 of the record's RMS per sample.
        return np.geomspace(1e-3, 0.3, STARTS - 1)[:, None]

    def physical(self, z, context):
        q = float(z[0]) ** 2 * context["scale"] ** 2 / context["dt"]
        return {
            "intensity_g2_per_s": q,
            "walk_over_record_g": math.sqrt(q * context["duration"]),
        }


# --------------------------------------------------------------------------------------
# The model: white + coloured block + level, filtered exactly
# --------------------------------------------------------------------------------------


def _effects() -> list[AbstractNoiseEffect]:
    return [cls() for cls in effect_library("noise").values()]


def _components(z, candidate) -> tuple[jax.Array, NoiseComponents]:
    """White variance and the added processes of candidate `candidate` (0: nominal,
    i: nominal + effect i − 1) at z = [ln σ_w, effect slot]."""
    white = jnp.exp(2 * z[0])
    zero = jnp.zeros_like(white)
    out = NoiseComponents(zero, zero, zero, zero)
    for i, effect in enumerate(_effects(), start=1):
        parts = effect.components(z[1 : 1 + effect.n_params])
        out = jax.tree_util.tree_map(lambda o, p, i=i: jnp.where(candidate == i, p, o), out, parts)
    return white, out


def filter_terms(white, parts: NoiseComponents, record, diffuse):
    """Exact Kalman filter of level + coloured block + white noise on a record.

    State (ℓ, s₁, s₂): ℓ_{k+1} = ℓ_k + √walk·w, (s₁, s₂)_{k+1} = ρ Rot(θ)(s₁, s₂)_k + noise of
    covariance v(1 − ρ²) I (`accel_jax._noise.ExponentialCosine`'s exact discrete form; a
    Gauss–Markov noise at θ = 0), observation x_k = ℓ_k + s₁,k + σ_w w_k. Prior: ℓ diffuse
    (variance `diffuse`), (s₁, s₂) stationary (v I). The covariance update is the standard
    form (P⁺ = P − K S Kᵀ), written out for the six distinct entries.

    **Arguments:** `white` σ_w²; `parts` (`NoiseComponents`); `record` x (n,), centred;
    `diffuse` the level's prior variance.

    **Returns:** (innovations ν_k, their variances S_k, log-likelihood terms), each (n,).
    jit/vmap/grad-safe.
    """
    v, rho, theta, walk = parts.variance, parts.decay, parts.rotation, parts.walk
    a11 = rho * jnp.cos(theta)
    a21 = rho * jnp.sin(theta)
    refresh = v * (1 - rho**2)
    log_2pi = math.log(2 * math.pi)

    def step(carry, x):
        ml, m1, m2, pll, pl1, pl2, p11, p12, p22 = carry
        nu = x - ml - m1
        s = pll + 2 * pl1 + p11 + white
        kl, k1, k2 = (pll + pl1) / s, (pl1 + p11) / s, (pl2 + p12) / s
        ml, m1, m2 = ml + kl * nu, m1 + k1 * nu, m2 + k2 * nu
        pll, pl1, pl2 = pll - kl * kl * s, pl1 - kl * k1 * s, pl2 - kl * k2 * s
        p11, p12, p22 = p11 - k1 * k1 * s, p12 - k1 * k2 * s, p22 - k2 * k2 * s
        # Predict: A = ρ [[cos θ, −sin θ], [sin θ, cos θ]] on (s₁, s₂).
        m1, m2 = a11 * m1 - a21 * m2, a21 * m1 + a11 * m2
        pl1, pl2 = a11 * pl1 - a21 * pl2, a21 * pl1 + a11 * pl2
        t11, t12 = a11 * p11 - a21 * p12, a11 * p12 - a21 * p22
        t21, t22 = a21 * p11 + a11 * p12, a21 * p12 + a11 * p22
        p11 = t11 * a11 - t12 * a21 + refresh
        p12 = t11 * a21 + t12 * a11
        p22 = t21 * a21 + t22 * a11 + refresh
        pll = pll + walk
        log_lik = -0.5 * (log_2pi + jnp.log(s) + nu**2 / s)
        return (ml, m1, m2, pll, pl1, pl2, p11, p12, p22), (nu, s, log_lik)

    zero = jnp.zeros_like(white + v)
    carry = (zero, zero, zero, zero + diffuse, zero, zero, zero + v, zero, zero + v)
    _, (nu, s, log_lik) = jax.lax.scan(step, carry, record)
    return nu, s, log_lik


def _bands(n_frequencies: int) -> tuple[np.ndarray, int]:
    """Band index of each periodogram bin (static): the first bins one by one, then
    log-spaced bands up to the Nyquist frequency."""
    single = min(16, n_frequencies)
    edges = np.unique(
        np.round(np.geomspace(single, n_frequencies, WHITTLE_BANDS - single + 1)).astype(int)
    )
    index = np.arange(n_frequencies)
    band = np.where(index < single, index, single + np.searchsorted(edges, index, side="right") - 1)
    _, band = np.unique(band, return_inverse=True)
    return band, int(band.max()) + 1


def _whittle(z, args):
    """Whittle −ln L per frequency of the differenced record, on band averages: its
    spectrum is (2 − 2 cos ω)(σ_w² + S_c(ω)) + qΔ, S_c = v/2 [P(ω − θ) + P(ω + θ)], P the
    Poisson kernel (1 − ρ²)/(1 − 2ρ cos x + ρ²) — the spectrum of R_k = v ρ^|k| cos kθ."""
    periodogram, omega, counts, candidate = args
    white, parts = _components(z, candidate)
    rho = parts.decay

    def poisson(x):
        return (1 - rho**2) / (1 - 2 * rho * jnp.cos(x) + rho**2)

    theta = parts.rotation
    colored = 0.5 * parts.variance * (poisson(omega - theta) + poisson(omega + theta))
    spectrum = (2 - 2 * jnp.cos(omega)) * (white + colored) + parts.walk
    return jnp.sum(counts * (jnp.log(spectrum) + periodogram / spectrum)) / jnp.sum(counts)


def _negative_log_likelihood(z, args):
    record, weight, candidate, diffuse = args
    white, parts = _components(z, candidate)
    _, _, log_lik = filter_terms(white, parts, record, diffuse)
    return -jnp.sum(weight * log_lik) / jnp.sum(weight)


def _fit_record(record, split_mask, guesses, candidates, band, band_count):
    """Fit every candidate (vmapped) to one normalised, centred record: Whittle start on
    the training part, exact-likelihood polish, then the filter over the whole record."""
    n = record.shape[0]
    train = split_mask
    n_train = jnp.sum(train)
    # Conditional on the first sample: the likelihood terms of samples 1..n_train − 1.
    weight = train * (jnp.arange(n) > 0)
    diffuse = _DIFFUSE * jnp.sum(train * record**2) / n_train
    # Periodogram of the training part's differences (the level drops out), Hann-tapered:
    # differencing spans the spectrum over decades (≈ 0 at ω → 0), and the leakage of an
    # untapered finite record would swamp its low-frequency end. Zero-padded to n − 1.
    index = jnp.arange(n - 1)
    m = n_train - 1
    taper = jnp.where(index < m, 0.5 - 0.5 * jnp.cos(2 * jnp.pi * (index + 0.5) / m), 0.0)
    diff = jnp.diff(record) * taper
    fourier = jnp.fft.rfft(diff)
    periodogram = (jnp.abs(fourier) ** 2 / jnp.sum(taper**2))[1:]
    omega = (2 * jnp.pi * jnp.arange(fourier.shape[0]) / (n - 1))[1:]
    # The band index enters as an argument: computed on the host and embedded as a
    # constant, a million-sample record's index made XLA spend seconds constant-folding
    # (and print warnings about it).
    n_bands = band_count.shape[0]
    counts = jax.ops.segment_sum(jnp.ones_like(omega), band, n_bands)
    periodogram = jax.ops.segment_sum(periodogram, band, n_bands) / counts
    omega = jax.ops.segment_sum(omega, band, n_bands) / counts

    def whittle_fit(guess, candidate):
        start = optx.minimise(
            _whittle,
            optx.BFGS(rtol=FIT_TOLERANCE, atol=FIT_TOLERANCE),
            guess,
            args=(periodogram, omega, counts, candidate),
            max_steps=WHITTLE_STEPS,
            throw=False,
        )
        value = _whittle(start.value, (periodogram, omega, counts, candidate))
        ok = jnp.all(jnp.isfinite(start.value)) & jnp.isfinite(value)
        return jnp.where(ok, start.value, guess), jnp.where(ok, value, jnp.inf)

    def fit_one(guesses, candidate):
        starts, values = jax.vmap(whittle_fit, in_axes=(0, None))(guesses, candidate)
        z0 = starts[jnp.argmin(values)]
        args = (record, weight, candidate, diffuse)
        polish = optx.minimise(
            _negative_log_likelihood,
            optx.BFGS(rtol=FIT_TOLERANCE, atol=FIT_TOLERANCE),
            z0,
            args=args,
            max_steps=POLISH_STEPS,
            throw=False,
        )
        z = polish.value
        white, parts = _components(z, candidate)
        nu, s, log_lik = filter_terms(white, parts, record, diffuse)
        converged = polish.result == optx.RESULTS.successful
        return z, nu, s, jnp.sum(weight * log_lik), converged, polish.stats["num_steps"]

    return jax.vmap(fit_one)(guesses, candidates)


# --------------------------------------------------------------------------------------
# Host side: context, evidence, localisation
# --------------------------------------------------------------------------------------


def _context(data: NoiseData, effects) -> dict:
    x = np.asarray(data.a_out, dtype=np.float64)
    n = x.size
    split = int(round((1 - HELD_OUT_FRACTION) * n))
    train = x[:split]
    if np.ptp(train) == 0:
        raise DataError(
            f"noise record: a_out is constant ({float(train[0])!r} g) over the training part "
            f"(first {split} samples); no noise to diagnose (a disconnected or saturated channel?)."
        )
    level = float(np.mean(train))
    scale = float(np.std(train))
    dt = float(data.sample_period)
    normalised = (x - level) / scale
    initial = {}
    for effect in effects:
        try:
            initial[effect.name] = initial_model(effect.structure, normalised[:split], dt)
        except ValueError as error:
            raise DataError(f"noise record: {error}") from None
    host = {"initial_models": initial, "dt": dt}
    guesses = np.zeros((1 + len(effects), STARTS, 1 + _SLOT))  # nominal: σ_w = s₀ (z = 0)
    for i, effect in enumerate(effects, start=1):
        guess = effect.initial_guess(host)
        guesses[i, :, 0] = math.log(float(initial[effect.name].components[0].sigma))
        guesses[i, 0, 1 : 1 + effect.n_params] = guess
        guesses[i, 1:, 1 : 1 + effect.n_params] = effect.alternative_starts(guess)
    return {
        "normalised": normalised,
        "split": split,
        "level": level,
        "scale": scale,
        "dt": dt,
        "duration": float(data.t[-1] - data.t[0]),
        "guesses": guesses,
    }


def _welch(x: np.ndarray, dt: float):
    n = x.size
    length = int(min(512, 2 ** np.floor(np.log2(max(n // 4, 16)))))
    window = np.hanning(length)
    hop = length // 2
    frames = [x[i : i + length] for i in range(0, n - length + 1, hop)]
    spectra = [np.abs(np.fft.rfft((f - f.mean()) * window)) ** 2 for f in frames]
    psd = 2 * dt * np.mean(spectra, axis=0) / np.sum(window**2)
    return np.fft.rfftfreq(length, dt), psd


def _localise(residual: np.ndarray, innovations: np.ndarray, sigma: float, host: dict) -> dict:
    """Where the nominal model's residual departs from white noise: its spectrum against the
    white floor (by frequency band), its autocorrelation (Ljung–Box), and its level and
    spread over segments of the record (a random walk wanders, a stationary noise not)."""
    dt = host["dt"]
    freqs, psd = _welch(residual, dt)
    floor = 2 * sigma**2 * dt
    f, p = freqs[1:], psd[1:]
    edges = np.geomspace(f[0], f[-1], 9)
    bands = []
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        inside = (f >= lo) & (f <= hi)
        if np.any(inside):
            bands.append(
                {
                    "band_Hz": [float(lo), float(hi)],
                    "psd_over_floor": float(np.mean(p[inside]) / floor),
                }
            )
    above = p > 2 * floor
    segments = []
    n = residual.size
    for k in range(8):
        part = residual[k * n // 8 : (k + 1) * n // 8]
        segments.append(
            {
                "t_start_s": float(k * n // 8 * dt),
                "mean_g": float(np.mean(part)),
                "rms_g": float(np.sqrt(np.mean(part**2))),
                "held_out": bool(k * n // 8 >= host["split"]),
            }
        )
    whiteness = ljung_box(innovations, lags=20)
    return {
        "frequency": {
            "noise_floor_g2_per_Hz": floor,
            "bands": bands,
            "peak_excess_Hz": float(f[np.argmax(p / floor)]),
            "peak_excess_ratio": float(np.max(p) / floor),
            "fraction_of_bins_above_2x_floor": float(np.mean(above)),
            "frequency_Hz": freqs.tolist(),
            "psd_g2_per_Hz": psd.tolist(),
        },
        "whiteness": whiteness,
        "time": {"segments": segments},
        "noise_sigma_g": sigma,
    }


def _postprocess(data: NoiseData, host: dict, effects, outputs) -> DiagnosisResult:
    zs, nus, ss, log_liks, converged, steps = (np.asarray(o) for o in outputs)
    split, scale, dt = host["split"], host["scale"], host["dt"]
    n = nus.shape[1]
    names = ["nominal"] + [e.name for e in effects]
    context = {"scale": scale, "dt": dt, "duration": host["duration"]}
    fits = []
    # Log-likelihoods in the record's unit: the normalisation by s₀ shifts every model by
    # the same −(n_terms) ln s₀.
    unit_shift = -(split - 1) * math.log(scale)
    for i, name in enumerate(names):
        innovation = nus[i] * scale
        params = {}
        if i:
            params = effects[i - 1].physical(zs[i, 1 : 1 + effects[i - 1].n_params], context)
        params["white_sigma_g"] = math.exp(float(zs[i, 0])) * scale
        fits.append(
            CandidateFit(
                effect=name,
                n_effect_params=0 if i == 0 else effects[i - 1].n_params,
                log_likelihood=float(log_liks[i]) + unit_shift,
                n_train=split,
                held_out_ms=float(np.mean(innovation[split:] ** 2)),
                held_out_errors=innovation[split:],
                train_ms=float(np.mean(innovation[1:split] ** 2)),
                params=params,
                converged=bool(converged[i]),
            )
        )
    _, ranking, _ = rank_candidates(fits[0], fits[1:], nested=NESTED)
    by_name = {f.effect: f for f in fits}
    # Open world: a model explains the record when its held-out one-step errors, each
    # scaled by the variance the model predicts for it, are white with unit variance (to
    # 3 standard errors), and no periodic line of its training errors continues into the
    # held-out ones. The line test runs on each model's own standardised one-step errors,
    # whose null is white: on the raw record a slow Gauss–Markov wander alone would pass
    # for a low-frequency line (a τ = 50 s record at 1 Hz did: a 0.0011 Hz "line" that
    # predicted over 20 % of the held-out part).
    n_test = n - split
    assessed = {}
    for i, name in enumerate(names):
        predicted = ss[i, split:] * scale**2
        scaled = by_name[name].held_out_errors / np.sqrt(predicted)
        test = openworld.whiteness(scaled)
        ratio = float(np.mean(scaled**2))
        # The predicted variance comes from the fit to the training part: both parts'
        # sampling errors count (2/n each for a variance), not the held-out part's alone.
        spread = math.sqrt(2 / max(n_test, 1) + 2 / max(split, 1))
        consistent = abs(ratio - 1) <= 3 * spread
        standardised = nus[i] / np.sqrt(np.maximum(ss[i], np.finfo(float).tiny))
        line = openworld.predictability(
            standardised[1:],
            split - 1,
            dt,
            np.zeros(0, int),
            np.zeros(0),
            1,
            tests=("periodic",),
            line_z=openworld.LINE_Z,
        )
        assessed[name] = {
            "floor": float(np.mean(predicted)),
            "whiteness": test,
            "variance_ratio": ratio,
            "predictable": line,
            "explains": bool(test["white"] and consistent and not line["deterministic"]),
        }
    for entry in ranking:
        own = assessed[entry["effect"]]
        before = openworld.excess(fits[0].held_out_ms, own["floor"])
        after = openworld.excess(by_name[entry["effect"]].held_out_ms, own["floor"])
        entry.update(
            {
                "stochastic": True,
                "explains": own["explains"],
                # A fit that stopped short of its maximum only understates its evidence
                # (a lower bound), as in the step kind: it stays credible. (Whether the
                # exp-cosine fit of a near-undamped line reaches its tolerance within the
                # step limit depended on the batch it ran in.)
                "plausible": bool(np.isfinite(entry["evidence"])),
                "one_step_whiteness": own["whiteness"],
                "variance_ratio": own["variance_ratio"],
                "deterministic_misfit": own["predictable"]["deterministic"],
                "explained_fraction": openworld.explained_fraction(before, after),
            }
        )
    nominal_status = {
        "explains": assessed["nominal"]["explains"],
        "white": assessed["nominal"]["whiteness"]["white"],
        "plausible": bool(converged[0]),
    }
    decision = openworld.decide(
        nominal_status,
        ranking,
        resolve_tie=lambda a, b: _resolve_nested(a, b, fits[1:], NESTED, NESTED_LEVEL),
    )
    verdict, tied = decision["verdict"], decision["tied"]
    shown = decision["chosen"] or decision["best_partial"]
    chosen = shown or "nominal"
    # The noise floor is the shown model's own predicted innovation variance on the
    # held-out part (the filter's S_k): what remains above it is what the model did not
    # expect. (A floor estimated on the training part would add the sampling mismatch of
    # two segments' variances, as large as the excess being measured.)
    floor = assessed[chosen]["floor"]
    for entry in ranking:
        g = held_out_gap(fits[0].held_out_errors, by_name[entry["effect"]].held_out_errors, floor)
        entry["gap_shrink"] = g["shrink"]
        entry["fit_steps"] = int(steps[names.index(entry["effect"])])
    after = by_name[chosen].held_out_errors
    gap = held_out_gap(fits[0].held_out_errors, after, floor)
    gap["unit"] = "g"
    gap["model_after"] = chosen
    gap["held_out"] = f"the last {n - split} of {n} samples (one-step prediction errors)"
    gap["metric"] = (
        "held-out RMS one-step prediction error in excess of the chosen model's predicted "
        "innovation variance"
    )
    fraction = next((e["explained_fraction"] for e in ranking if e["effect"] == shown), 0.0)
    remaining = gap["after"]
    remaining_gap = {
        "g": remaining,
        "noise_floor_g": math.sqrt(floor),
        "over_floor": remaining / math.sqrt(floor) if floor > 0 else float("inf"),
        "model": chosen,
        "whiteness_p_value": assessed[chosen]["whiteness"]["p_value"],
    }
    line = assessed[chosen]["predictable"]
    if line["deterministic"]:
        # A line is a gap the RMS hardly shows: its amplitude, in g, beside the RMS gap.
        remaining_gap["periodic_line"] = {
            "frequency_Hz": line["frequency_Hz"],
            "rms_g": line["periodic_rms"] * math.sqrt(floor),
            "z": line["periodic_z"],
        }
    predictable = assessed[chosen]["predictable"]
    reason = _reason(decision, assessed, ranking, predictable, remaining, floor, chosen)

    white_sigma = fits[0].params["white_sigma_g"]
    x = np.asarray(data.a_out)
    residual = x - host["level"]
    refit = {
        "parameters": {},
        "nominal_fit": {"white_sigma_g": white_sigma, "level_g": host["level"]},
        "model": "a_out = level + σ_w w (white noise about a constant level; no prior)",
        "parameter_error": False,
        "converged": bool(converged[0]),
        "description": (
            f"white noise σ_w = {white_sigma:.4g} g about the level {host['level']:.9g} g "
            "(fitted on the training part)"
        ),
    }
    where = _localise(residual, nus[0], white_sigma, host)
    chosen_index = names.index(chosen)
    traces = {
        "t": np.asarray(data.t),
        "measured": x,
        "level": host["level"],
        "innovations_before": nus[0] * scale,
        "innovations_after": nus[chosen_index] * scale,
        "best_name": chosen,
        "split": split,
    }
    where["predictability"] = predictable
    return DiagnosisResult(
        kind="noise",
        verdict=verdict,
        tied=tied,
        ranking=ranking,
        gap=gap,
        where=where,
        refit=refit,
        traces=traces,
        notes=list(getattr(data, "notes", ())),
        explained_fraction=fraction,
        remaining_gap=remaining_gap,
        reason=reason,
    )


def _reason(decision, assessed, ranking, predictable, remaining, floor, chosen) -> str:
    verdict = decision["verdict"]
    sigma = math.sqrt(floor)
    entry = {e["effect"]: e for e in ranking}
    if verdict == "none":
        return (
            "the held-out record is white noise about its level (Ljung–Box p = "
            f"{assessed['nominal']['whiteness']['p_value']:.2g}) and no effect is significant."
        )
    if verdict == "cannot_tell":
        a, b = decision["tied"]
        return (
            f"{a} and {b} both whiten the held-out record and their evidence differs by "
            f"{abs(entry[a]['evidence'] - entry[b]['evidence']):.1f} (< 6 on the 2 ln B scale)."
        )
    if verdict != "unexplained":
        return (
            f"with {verdict} the held-out one-step prediction errors are white (Ljung–Box p = "
            f"{assessed[verdict]['whiteness']['p_value']:.2g}) at the variance it predicts; "
            f"evidence 2 ln B = {entry[verdict]['evidence']:.1f} over white noise."
        )
    parts = []
    if predictable["deterministic"]:
        parts.append(
            f"a periodic line at {predictable['frequency_Hz']:.4g} Hz continues from the "
            f"training part into the held-out one-step errors of {chosen} (projection "
            f"{predictable['periodic_z']:.1f} standard errors, {predictable['periodic']:.1%} "
            "of their mean square): deterministic, not one of the library's noises"
        )
    elif abs(predictable["periodic_z"]) >= openworld.LINE_Z and predictable["frequency_Hz"]:
        # A line of the training part whose continuation is anti-correlated (or far off)
        # with the held-out part: a real spectral line whose phase or frequency wanders.
        parts.append(
            f"a spectral line at {predictable['frequency_Hz']:.4g} Hz in the training part "
            f"does not carry its phase into the held-out part (projection "
            f"{predictable['periodic_z']:.1f} standard errors): a wandering line"
        )
    if decision["best_partial"]:
        best = decision["best_partial"]
        own = assessed[best]
        if not own["whiteness"]["white"]:
            p_value = own["whiteness"]["p_value"]
            short = f"its one-step errors are not white (Ljung–Box p = {p_value:.2g})"
        elif own["predictable"]["deterministic"]:
            short = "it leaves the line"
        else:
            short = (
                f"its one-step errors are {math.sqrt(own['variance_ratio']):.3g}× the size it "
                "predicts"
            )
        parts.append(
            f"the best library effect, {best}, explains {entry[best]['explained_fraction']:.0%} "
            f"of the excess, but {short}; {remaining:.3g} g above its {sigma:.3g} g floor "
            "remains"
        )
    elif not any(e["significant"] for e in ranking):
        nominal = assessed["nominal"]
        p_value = nominal["whiteness"]["p_value"]
        if nominal["predictable"]["deterministic"]:
            why = "the line is not one of the library's noises"
        elif nominal["whiteness"]["white"]:
            why = (
                f"the held-out record is white (Ljung–Box p = {p_value:.2g}) but its variance "
                f"is {nominal['variance_ratio']:.3g}× the training part's"
            )
        else:
            why = (
                "the record is not white noise (Ljung–Box p = "
                f"{nominal['whiteness']['p_value']:.2g})"
            )
        parts.append(why + " and no library effect is significant")
    else:
        parts.append(
            "no library noise leaves white one-step prediction errors (best: "
            f"{chosen}, Ljung–Box p = {assessed[chosen]['whiteness']['p_value']:.2g})"
        )
    return "; ".join(parts) + "."


def diagnose_noise(
    datasets: list[NoiseData], nominal: NominalDevice | None = None
) -> list[DiagnosisResult]:
    """Diagnose static noise records (SPEC.md §5, `noise` kind).

    Records of one length are fitted together (one compilation, every candidate of every
    record vmapped, in chunks of `BATCH_CHUNK` records): Whittle start and exact maximum
    likelihood on the first 2/3 of each record, evidence (2 ln B, BIC scale) against white
    noise, the held-out gap on the last third, and the localisation of the white-noise
    residual in frequency, lag and time.

    **Arguments:**

    - `datasets`: validated `NoiseData` records (e.g. from `read_csv`).
    - `nominal`: ignored (the servo device has no parameter in this kind's nominal model);
        accepted for the common `diagnose` interface.

    **Returns:** one `DiagnosisResult` per record, in order. Float64 (needs x64 enabled;
    a `ValueError` otherwise).
    """
    require_float64("log-likelihoods of thousands of samples are compared to within a unit")
    del nominal
    effects = _effects()
    hosts = [_context(data, effects) for data in datasets]
    results: list[DiagnosisResult | None] = [None] * len(datasets)
    groups: dict[tuple[int, int], list[int]] = {}
    for i, host in enumerate(hosts):
        groups.setdefault((host["normalised"].size, host["split"]), []).append(i)
    candidates = jnp.arange(1 + len(effects))
    for (n, split), indices in groups.items():
        records = jnp.asarray(np.stack([hosts[i]["normalised"] for i in indices]))
        guesses = jnp.asarray(np.stack([hosts[i]["guesses"] for i in indices]))
        mask = jnp.asarray((np.arange(n) < split).astype(np.float64))
        band, n_bands = _bands((n - 1) // 2)
        outputs = sweep(
            _fit_record,
            records,
            mask,
            guesses,
            candidates,
            jnp.asarray(band.astype(np.int32)),
            jnp.zeros(n_bands),
            in_axes=(0, None, 0, None, None, None),
            chunk_size=even_chunk_size(len(indices), BATCH_CHUNK),
            desc="diagnose noise",
        )
        outputs = [np.asarray(o) for o in outputs]
        for j, i in enumerate(indices):
            results[i] = _postprocess(datasets[i], hosts[i], effects, [o[j] for o in outputs])
    return results
