"""The noise kind's model and fit: white + coloured block + level filtered exactly (a Kalman
filter over the components' state space), the Whittle start on band-averaged
periodograms and the exact-likelihood polish, vmapped over records.

The spectra of the Whittle start come from `accel_jax._noise.models` (`spectrum`); the
filter `filter_terms` is a hand-unrolled fast path of `accel_jax._kalman.kalman_filter` on
the state space of `models`' white + exponential-cosine (or Gauss–Markov) + random walk,
checked against it in tests/test_noise_one_model.py."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ..._noise import _DIFFUSE
from ..._noise.models import (
    ExponentialCosine,
    RandomWalk,
    WhiteNoise,
    difference_parts,
)
from ..base import (
    effect_library,
)
from .effects import AbstractNoiseEffect, NoiseComponents

WHITTLE_STEPS = 128
POLISH_STEPS = 64
"""BFGS step budgets of the Whittle start and of the exact-likelihood polish."""

FIT_TOLERANCE = 1e-6
"""rtol = atol of the BFGS fits (on O(1) scaled parameters; the objective is −ln L / n)."""


WHITTLE_BANDS = 64
"""The Whittle start uses the periodogram averaged over this many frequency bands (the
lowest bins one by one, then log-spaced): a start needs the right basin, not the last digit,
and every start of every candidate of every record evaluates it (8 × 4 per record)."""


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
    covariance v(1 − ρ²) I (the transition F and its noise Q are
    `accel_jax._noise.ExponentialCosine.discrete_state_space`'s; a Gauss–Markov noise at θ =
    0), observation x_k = ℓ_k + s₁,k + σ_w w_k. Prior: ℓ diffuse (variance `diffuse`),
    (s₁, s₂) stationary, v I (the model's P0, taken as v itself: read from P0's diagonal,
    the Hessian of the likelihood, the intervals' information, sums its terms in another
    order, ~10⁻¹⁵ apart). The covariance update is the standard form (P⁺ = P − K S Kᵀ),
    written out for the six distinct entries.

    **Arguments:** `white` σ_w²; `parts` (`NoiseComponents`); `record` x (n,), centred;
    `diffuse` the level's prior variance.

    **Returns:** (innovations ν_k, their variances S_k, log-likelihood terms), each (n,).
    jit/vmap/grad-safe.
    """
    v, rho, theta, walk = parts.variance, parts.decay, parts.rotation, parts.walk
    # The block's exact discrete form, from the per-sample parameters (no log of ρ: the
    # nominal candidate's ρ = 0 stays finite, its derivatives too).
    transition, refresh, _, _, _ = ExponentialCosine.discrete_state_space(v, rho, theta)
    a11, a21 = transition[0, 0], transition[1, 0]  # F = [[a11, −a21], [a21, a11]]
    refresh = refresh[0, 0]
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


def spectrum(z, candidate, omega):
    """The spectral density per sample of the differenced record under candidate
    `candidate` at z: (2 − 2 cos ω)(σ_w² + S_c(ω)) + qΔ, S_c the coloured block's
    exponential-cosine spectrum (a Gauss–Markov one at θ = 0), every piece from
    `accel_jax._noise.models` (the one definition of the noise spectra)."""
    white, parts = _components(z, candidate)
    block = ExponentialCosine.discrete_spectrum(omega, parts.variance, parts.decay, parts.rotation)
    coloured = WhiteNoise.discrete_spectrum(omega, white) + block
    walk = RandomWalk.discrete_difference_spectrum(omega, parts.walk)
    stationary, walk = difference_parts(omega, coloured, walk)
    return stationary + walk


def _whittle(z, args):
    """Whittle −ln L per frequency of the differenced record, on band averages, with the
    spectrum `spectrum`."""
    periodogram, omega, counts, candidate = args
    f = spectrum(z, candidate, omega)
    return jnp.sum(counts * (jnp.log(f) + periodogram / f)) / jnp.sum(counts)


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
# Intervals of the fitted model: the observed information at the maximum
# --------------------------------------------------------------------------------------

INTERVAL_LEVEL = 0.95
"""Two-sided level of the reported intervals of a fitted noise model."""

_INTERVAL_Z = 1.959963984540054  # the standard normal's 97.5 % point

_SYMBOLS = {
    "white_sigma_g": ("σ_w", "g"),
    "sigma_g": ("σ", "g"),
    "correlation_time_s": ("τ_c", "s"),
    "rate_per_s": ("1/τ_c", "1/s"),
    "decay_rate_per_s": ("α", "1/s"),
    "angular_frequency_rad_per_s": ("β", "rad/s"),
    "period_s": ("2π/β", "s"),
    "intensity_g2_per_s": ("q", "g²/s"),
    "walk_over_record_g": ("√(q T_rec)", "g"),
}
"""How each parameter of a noise model is named for a reader (symbol, unit)."""


@jax.jit
def _information(z, record, weight, candidate, diffuse):
    """The observed information −∂² ln L/∂z² of the training log-likelihood at z."""
    hessian = jax.hessian(_negative_log_likelihood)(z, (record, weight, candidate, diffuse))
    return hessian * jnp.sum(weight)


def model_intervals(z, record, split, candidate, effect, context) -> dict:
    """The fitted model's parameters with `INTERVAL_LEVEL` intervals, for a Kalman filter.

    The covariance of the fitted z (ln σ_w and the effect's own parameters) is the inverse
    of the observed information of the training log-likelihood (the exact Kalman one the
    fit maximised); it is carried to each physical parameter p by the delta method on
    ln p (numerical derivatives of the effect's `physical`), so an interval of a positive
    quantity stays positive: p·exp(±z₀.₉₇₅ sd(ln p)). A parameter at a bound or a flat
    likelihood (information not positive definite) gets its value without an interval and
    a note.

    **Arguments:** `z` the fitted parameters (nominal layout: [ln σ_w, slot]); `record` the
    normalised record; `split` its training length; `candidate` 0 (white) or the effect's
    index; `effect` the `AbstractNoiseEffect` (None for white); `context` (`scale`, `dt`,
    `duration`) as for `physical`.
    """
    z = np.asarray(z, dtype=np.float64)
    n = record.shape[0]
    index = np.arange(n)
    weight = ((index < split) & (index > 0)).astype(np.float64)
    x = np.asarray(record, dtype=np.float64)
    diffuse = _DIFFUSE * float(np.sum(x[:split] ** 2)) / split
    n_params = effect.n_params if effect is not None else 0
    used = list(range(1 + n_params))
    information = np.asarray(
        _information(jnp.asarray(z), jnp.asarray(x), jnp.asarray(weight), candidate, diffuse)
    )[np.ix_(used, used)]

    def physical(values):
        full = z.copy()
        full[used] = values
        out = {}
        if effect is not None:
            out = effect.physical(full[1 : 1 + n_params], context)
            if "correlation_time_s" in out and out["correlation_time_s"] > 0:
                out["rate_per_s"] = 1 / out["correlation_time_s"]
        out["white_sigma_g"] = math.exp(float(full[0])) * context["scale"]
        return out

    centre = physical(z[used])
    names = [k for k in centre if k in _SYMBOLS]
    out = {
        "level": INTERVAL_LEVEL,
        "method": "maximum likelihood (exact Kalman filter, training part); intervals from "
        "the observed information, delta method on ln p",
        "parameters": {},
    }
    eigenvalues = np.linalg.eigvalsh(0.5 * (information + information.T))
    covariance = None
    if np.all(np.isfinite(eigenvalues)) and eigenvalues.min() > 1e-9 * max(eigenvalues.max(), 1):
        covariance = np.linalg.inv(information)
    else:
        out["note"] = (
            "no intervals: the likelihood is flat or the fit sits at a bound (observed "
            "information not positive definite)"
        )
    jacobian = np.zeros((len(names), len(used)))
    if covariance is not None:
        step = 1e-5
        for j in range(len(used)):
            up, down = z[used].copy(), z[used].copy()
            up[j] += step
            down[j] -= step
            hi, lo = physical(up), physical(down)
            for i, name in enumerate(names):
                if centre[name] > 0 and hi[name] > 0 and lo[name] > 0:
                    jacobian[i, j] = (math.log(hi[name]) - math.log(lo[name])) / (2 * step)
                else:
                    jacobian[i, j] = np.nan
    for i, name in enumerate(names):
        value = float(centre[name])
        entry = {"value": value, "symbol": _SYMBOLS[name][0], "unit": _SYMBOLS[name][1]}
        if covariance is not None and np.all(np.isfinite(jacobian[i])) and value > 0:
            sd = math.sqrt(max(float(jacobian[i] @ covariance @ jacobian[i]), 0.0))
            entry.update(
                {
                    "low": value * math.exp(-_INTERVAL_Z * sd),
                    "high": value * math.exp(_INTERVAL_Z * sd),
                    "sd_log": sd,
                }
            )
        out["parameters"][name] = entry
    return out
