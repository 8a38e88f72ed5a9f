"""The spectral model of a real sensor's static record and its Whittle likelihood.

A static record x_k (k = 0..n−1, every Δ seconds) of a real sensor is modelled as

    x_k = ℓ_k + Σ_lines A cos(2π f k Δ + φ) + a e^{−kΔ/τ_s} + h * (w + g + e + c + u)_k + p_k

with a level ℓ that may walk (random walk of increment variance qΔ per sample), periodic
lines, a start-up transient, and the sensor's output low-pass h (the bandlimit) applied to
the white noise w, a Gauss–Markov noise g, an exponential-cosine noise e, a flicker
(1/f, bias-instability) noise c and a high-frequency noise u (a spectrum that rises above a
corner towards the Nyquist frequency: a servo loop's noise gain, a converter's shaped
noise), plus a white floor p after the filter: the quantisation
noise q²/12 of the output's ADC grid, when one is found, plus (`filter_floor`) a fitted
white variance p_f, the noise a signal chain adds after its low-pass (an ADC's or an
amplifier's own), found whether or not the record lies on a grid. Each extension is
exactly the nominal model (white noise about a constant level) at zero.

The stochastic part is fitted by the Whittle likelihood of the first difference
y_k = x_k − x_{k−1} (the difference removes the level and makes the random walk white),
whose spectral density per sample, with λ(ω) = |1 − e^{−iω}|² = 2 − 2 cos ω, is

    f_y(ω) = λ(ω) [H(ω) (σ_w² + f_g(ω) + f_e(ω) + f_c(ω) + f_u(ω)) + p] + H(ω) qΔ,

- Gauss–Markov (σ_g, ρ = e^{−Δ/τ_c}): f_g = σ_g² (1 − ρ²) / |1 − ρ e^{−iω}|²;
- exponential-cosine (σ_e, ρ = e^{−αΔ}, θ = βΔ): f_e = σ_e²/2 [P(ω − θ) + P(ω + θ)],
  P(u) = (1 − ρ²)/(1 − 2ρ cos u + ρ²) (the exact spectrum of R_k = σ_e² ρ^|k| cos kθ);
- flicker: f_c = B²/|ω|, the exact 1/f spectrum (no sum-of-Gauss–Markov approximation is
  needed in the frequency domain). B is the IEEE Std 952 bias-instability coefficient: the
  two-sided rate PSD is S(f) = B²/(2π|f|), so f_c(ω) = S(ω/2πΔ)/Δ = B²/|ω|, and the Allan
  deviation's floor is √(2 ln 2/π)·B = 0.664 B;
- high-frequency noise (σ_h, corner f_h): f_u = σ_h² (1 − H₂(ω; f_h)), white noise through
  a second-order Butterworth high-pass, H₂ the low-pass gain below;
- bandlimit: a Butterworth low-pass (bilinear transform) of order N = 2 (`bandlimit`), 1, 3
  or 4 (`BUTTERWORTH_ORDERS`) and corner f_b, H(ω) = 1/(1 + (tan(ω/2)/tan(π f_b Δ))^{2N}) —
  exactly 1 at f_b = the Nyquist frequency; or another shape of the signal chain
  (`OTHER_LOW_PASSES`, `chain_filters`): a Bessel low-pass of order 2–4 (−3 dB at f_b), a
  moving average of M samples (H = (sin(Mω/2)/(M sin(ω/2)))², its corner set by M), a
  decimating average of K stages and ratio R (a CIC decimator: H = ρ_0 + 2 Σ ρ_j cos jω,
  its folded images included, set by K and R).

Each of these spectra (and λ, H and the assembly of f_y) is defined once, in `models`
(`WhiteNoise`, `GaussMarkov`, `ExponentialCosine`, `RandomWalk`, `Flicker`,
`ButterworthLowPass` and `chain_filters`' shapes, `difference_parts`); `_parts` calls them
with this module's parameterisation, and `component_models` gives the models of a
parameter vector. The lines and the transient are terms of the mean, not of this
spectrum: `mean_models`
(`PeriodicLine`, `StartupTransient`), regressed out of the record before the fit
(`sensor_model`).

The Whittle log-likelihood of the periodogram I_j of y at ω_j = 2πj/m is
−Σ_j [ln f_y(ω_j) + I_j/f_y(ω_j)]; records longer than `FULL_RESOLUTION` bins use it on
geometric bands of bins (ratio `BAND_RATIO`), which makes one evaluation cost the same for
10⁴ and 10⁶ samples. Float64.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .._solvers import STALL_WINDOW, StallEndingMinimiser
from . import chain_filters
from .periodogram import (  # the periodogram's own module; its names kept here
    BAND_RATIO,
    FULL_RESOLUTION,
    MID_GRID,
    TAPER,
    Periodogram,
    periodogram,
)
from .models import (
    ExponentialCosine,
    Flicker,
    Frequencies,
    GaussMarkov,
    HighFrequencyNoise,
    NoiseSum,
    RandomWalk,
    WhiteNoise,
    _frequencies,
    difference_parts,
)

COMPONENTS = (
    "gauss_markov",
    "exp_cosine",
    "random_walk",
    "flicker",
    "bandlimit",
    "filter_floor",
    "high_frequency_noise",
)
"""The stochastic extensions, in the order of their slots in the parameter vector.
`filter_floor` (the fitted white variance after the low-pass) is part of the bandlimit's
signal chain: the selection adds it only with a low-pass (without one it is white noise,
the nominal's own)."""

BUTTERWORTH_ORDERS = {
    "bandlimit": 2,
    "bandlimit_order1": 1,
    "bandlimit_order3": 3,
    "bandlimit_order4": 4,
}
"""The Butterworth low-pass of each order (the mask's slot 8 carries N): order 2
(`bandlimit`), 1, 3 or 4. A first-order one differs from a Gauss–Markov process over white
noise only near the Nyquist frequency (its bilinear zero there), so the record may not
tell the two apart (the exchange says so)."""

OTHER_LOW_PASSES = {
    **{f"bandlimit_bessel{n}": chain_filters.BESSEL_CODE + n for n in chain_filters.BESSEL_ORDERS},
    **{
        f"bandlimit_taps{m}": chain_filters.MOVING_AVERAGE_CODE + m
        for m in range(2, chain_filters.MAX_TAPS + 1)
    },
    **{
        f"bandlimit_decimation{k}x{r}": chain_filters.DECIMATION_CODE + 100 * k + r
        for k in chain_filters.DECIMATION_STAGES
        for r in range(2, chain_filters.MAX_RATIO + 1)
    },
}
"""The signal chain's other low-pass shapes (`chain_filters`; slot 8 carries the shape's
code): a Bessel low-pass of order 2–4, a moving average of M samples, and a decimating
average of K stages and ratio R."""

LOW_PASS_ORDERS = {**BUTTERWORTH_ORDERS, **OTHER_LOW_PASSES}
"""Every low-pass the selection tries in the `bandlimit` slot, by name: its code (the
Butterworth order N, or `chain_filters`' code of another shape)."""


def effect_name(name: str) -> str:
    """A component's name as the selection reports it: a low-pass of any order is
    `bandlimit`."""
    return "bandlimit" if name in LOW_PASS_ORDERS else name


def low_pass(names) -> str | None:
    """The low-pass of `names` (a key of `LOW_PASS_ORDERS`), or None."""
    return next((n for n in names if n in LOW_PASS_ORDERS), None)

N_PARAMS = 12
"""z = [ln σ_w², ln σ_g², ln τ_c/Δ, ln σ_e², ln αΔ, ln θ, ln qΔ, ln B², logit(f_b/f_N), ln p_f,
ln σ_h², logit(f_h/f_N)]."""

SLOTS = {
    "gauss_markov": (1, 2),
    "exp_cosine": (3, 4, 5),
    "random_walk": (6,),
    "flicker": (7,),
    "bandlimit": (8,),
    "filter_floor": (9,),
    "high_frequency_noise": (10, 11),
    **{name: (8,) for name in LOW_PASS_ORDERS if name != "bandlimit"},
}

MAX_QUALITY = 300.0
"""The exponential-cosine noise's decay per sample is αΔ = e^{z₄} + θ/`MAX_QUALITY`: a
resonance sharper than β/α = 300 is a periodic line (the `sinusoid` effect), and the
banded likelihood could not resolve it."""

STEPS = 128
TOLERANCE = 1e-8

STALL_NATS = 1e-3
"""A Whittle fit ends as at its step limit (`_solvers.StallEndingMinimiser`) once its
log-likelihood has risen by less than this over its last `_solvers.STALL_WINDOW` (10)
accepted steps: a parameter the record does not identify (an absent flicker's level, an
exponential-cosine β → 0) keeps the step test of `TOLERANCE` from firing after the
likelihood has settled (14 of 21 single-start fits of a 20,000-sample record ran all
`STEPS`). Going on at that rate to the limit would add less than 0.013 to ln L, against an
evidence bar of 10 in 2 ln B. Measured on the 2-core CPU, warm, one process:
`select_sensor_noise` of the tests' composite record (line, quantisation, low-pass,
flicker; 20,000 samples) 23.5 → 17.7 s, and of a Gauss–Markov record with a line (8,000
samples) 3.8 → 2.8 s, the same effects and every step's evidence equal to 1e-4 (one run
each)."""


def _mask(names) -> np.ndarray:
    mask = np.zeros(N_PARAMS)
    mask[0] = 1.0
    for name in names:
        for i in SLOTS[name]:
            mask[i] = LOW_PASS_ORDERS.get(name, 1.0)  # a low-pass's slot: its order
    return mask


def _parts(z, mask, omega, floor):
    """(stationary part λ(H·coloured + p), random-walk part H·qΔ) of f_y at |ω| ≤ π, each
    component's spectrum and the low-pass's gain from `models` (the one definition);
    `omega` ω or its `Frequencies`; p = `floor` + the fitted p_f where `filter_floor` is
    on. A component the mask leaves off is not evaluated (`_if_on`)."""
    on = mask > 0
    floor = floor + jnp.where(on[9], jnp.exp(z[9]), 0.0)
    omega = _frequencies(omega)
    zero, one = jnp.zeros_like(omega.omega), jnp.ones_like(omega.omega)

    def gauss_markov():
        return GaussMarkov.discrete_spectrum(omega, jnp.exp(z[1]), jnp.exp(-jnp.exp(-z[2])))

    def exp_cosine():
        theta = jnp.exp(z[5])
        rho_e = jnp.exp(-(jnp.exp(z[4]) + theta / MAX_QUALITY))
        return ExponentialCosine.discrete_spectrum(omega, jnp.exp(z[3]), rho_e, theta)

    def flicker():
        return Flicker.discrete_spectrum(omega, jnp.exp(z[7]))

    def high_frequency_noise():
        rise = jax.nn.sigmoid(z[11]) * (math.pi / 2)  # π f_h Δ ∈ (0, π/2)
        return HighFrequencyNoise.discrete_spectrum(omega, jnp.exp(z[10]), rise)

    def low_pass():
        corner = jax.nn.sigmoid(z[8]) * (math.pi / 2)  # π f_b Δ ∈ (0, π/2)
        # (off, evaluated only under a vmapped mask: a finite gain and gradient, unused)
        code = jnp.where(on[8], mask[8], 2.0)
        return chain_filters.low_pass_gain(omega, corner, code)

    coloured = WhiteNoise.discrete_spectrum(omega, jnp.exp(z[0]))
    coloured = coloured + _if_on(on[1], gauss_markov, zero) + _if_on(on[3], exp_cosine, zero)
    coloured = coloured + _if_on(on[7], flicker, zero)
    coloured = coloured + _if_on(on[10], high_frequency_noise, zero)
    gain = _if_on(on[8], low_pass, one)
    walk = jnp.where(on[6], RandomWalk.discrete_difference_spectrum(omega, jnp.exp(z[6])), 0.0)
    return difference_parts(omega, coloured, walk, gain, floor)


def _if_on(on, spectrum, off):
    """`spectrum()` where the (traced) slot `on` is switched on, else `off`: a `lax.cond`,
    so that a fit's value and gradient skip the components its structure leaves out (the
    mask is an argument of one compiled fit for every structure). With `jnp.where` every
    component's spectrum and its gradient were computed on every frequency and then
    discarded: on the correction's grid of 16,385 frequencies that gradient cost more than
    its Fourier transforms. Measured on the 2-core CPU, one core, the Whittle
    log-likelihood's value and gradient on section 7's 130,000-sample record (1,880 bands,
    a grid of 32,768): 1.64–1.68 → 1.25–1.43 ms for structures of one or two components
    (1.65 → 1.61 ms with three), equal to 1e-12 relative in value. Under `vmap` with a
    batched mask, a select of both, as before."""
    return jax.lax.cond(on, spectrum, lambda: off)


def component_models(z, mask, sample_interval):
    """The noise of parameters z (the slots `mask` switches on) as `models`' modules: a
    `NoiseSum` of white noise and the stochastic components (Δ = `sample_interval`), the
    low-pass (`chain_filters.low_pass`: a `ButterworthLowPass`, `BesselLowPass` or
    `MovingAverage`; None when off) and the fitted white noise after it (`WhiteNoise`,
    None when `filter_floor` is off). Its difference spectrum, low-passed, plus the white
    noise after the filter and the floor is `spectrum`."""
    on = np.asarray(mask) > 0
    z = np.asarray(z, np.float64)
    parts: list = [WhiteNoise(math.exp(0.5 * z[0]))]
    if on[1]:
        parts.append(GaussMarkov(math.exp(0.5 * z[1]), math.exp(z[2]) * sample_interval))
    if on[3]:
        theta = math.exp(z[5])
        rate = (math.exp(z[4]) + theta / MAX_QUALITY) / sample_interval
        parts.append(ExponentialCosine(math.exp(0.5 * z[3]), rate, theta / sample_interval))
    if on[6]:
        parts.append(RandomWalk(math.exp(z[6]) / sample_interval))
    if on[7]:
        parts.append(Flicker(math.exp(0.5 * z[7])))
    if on[10]:
        rise = 1 / (1 + math.exp(-z[11])) / 2  # f_h Δ
        parts.append(HighFrequencyNoise(math.exp(0.5 * z[10]), rise / sample_interval))
    noise = parts[0] if len(parts) == 1 else NoiseSum(tuple(parts))
    low_pass = None
    if on[8]:
        corner = 1 / (1 + math.exp(-z[8])) / 2  # f_b Δ
        low_pass = chain_filters.low_pass(float(np.asarray(mask)[8]), corner / sample_interval)
    after = WhiteNoise(math.exp(0.5 * z[9])) if on[9] else None
    return noise, low_pass, after


def spectrum(z, mask, omega, floor):
    """f_y(ω) of the differenced record (module docstring) at parameters z with the slots
    that `mask` switches on; `floor` the post-filter white variance p."""
    stationary, walk = _parts(z, mask, omega, floor)
    return stationary + walk


compiled_spectrum = jax.jit(spectrum)
"""`spectrum` compiled, for callers outside a compiled fit (the transient test's and the
arbiter's autocovariances). Run eagerly, op by op, an evaluation took 4 times as long, and
the low-pass's `lax.switch` was traced and compiled anew at every call (0.19 s each; 6.2 s
of a 1.3e5-sample `accel-jax noise` run)."""


def expected_periodogram(z, mask, gram, floor):
    """E I_j of the model for the tapered periodogram: the debiased Whittle likelihood's
    f̄ (Sykulski et al., Biometrika 2019), Σ_h c(h) γ_y(h) e^{−iω_j h} with c the taper's
    normalised autocorrelation (1 − |h|/m untapered), computed as f_y(ω_j) −
    Σ_h (1 − c(h)) γ_y(h) e^{−iω_j h}. The correction matters where f_y is small next to
    the record's variance over m: at the lowest frequencies of a differenced record
    (untapered white noise: exactly 2σ² cos ω/m, far above λσ² there) and beyond a steep
    low-pass, where the periodogram is leakage. γ_y comes from f_y on a grid of `gram.grid`
    points, the power of two ≥ 2m (every lag of the record; f̄ interpolated to the Fourier
    frequencies) for records up to 2^14 differences, else at most 2^15 (`_grid`: the
    correction's lags truncated where the taper leaves them little weight).
    The random walk's part of y is white and needs none."""
    stationary, walk = _parts(z, mask, gram.bin_frequencies, floor)
    size = gram.grid
    # f_y is even in ω, so its values at ω_k = 2πk/size, k ≤ size/2 (`gram.grid_frequencies`),
    # define it on the whole circular grid: γ_y is their inverse real FFT, and the
    # correction (a real, even sequence's transform) the real part of a real FFT (half the
    # spectrum evaluations and half the transform work of full complex FFTs; equal to
    # round-off).
    on_grid, _ = _parts(z, mask, gram.grid_frequencies, floor)
    gamma = jnp.fft.irfft(on_grid, size)
    correction = -jnp.real(jnp.fft.rfft(gram.lag_weight * gamma))
    d = jnp.interp(gram.bins, gram.grid_frequencies.omega, correction)
    per_bin = stationary + walk + d
    if gram.bins.shape == gram.omega.shape:  # full resolution
        return per_bin
    return jax.ops.segment_sum(per_bin, gram.band, gram.omega.shape[0]) / gram.count


def whittle(z, mask, gram: Periodogram, floor):
    """The Whittle log-likelihood of the (banded) periodogram."""
    return jnp.sum(_whittle_terms(z, mask, gram, floor))


def _whittle_terms(z, mask, gram: Periodogram, floor):
    f = expected_periodogram(z, mask, gram, floor)
    return -gram.count * (jnp.log(f) + gram.power / f)


@eqx.filter_jit
def whittle_terms(z, mask, gram: Periodogram, floor):
    """The Whittle log-likelihood's terms, one per periodogram entry (their sum is
    `whittle`): for paired comparisons of two models on the same bins."""
    return _whittle_terms(z, mask, gram, floor)


@eqx.filter_jit
def deviance_terms(z, mask, gram: Periodogram, floor):
    """Per entry: r = I/f and the Whittle deviance r − ln r − 1 (its mean is Euler's γ =
    0.5772 per bin and its variance π²/6 − 1 under the model, for single bins)."""
    r = gram.power / expected_periodogram(z, mask, gram, floor)
    return r, r - jnp.log(r) - 1


N_STARTS = 4
"""Starts per structure, fitted in one compiled call (one compilation for every structure
of a record: the structure is the `mask` argument)."""


@eqx.filter_jit
def _fit_all(z0s, repeated, mask, gram, floor):
    """The fit from each start of `z0s`, one after another (`lax.map`): each stops at its own
    step count, where a vmapped batch ran every start until the slowest stopped (BFGS takes
    from a few to the full `STEPS` here), and a start that repeats an earlier one
    (`repeated`: fewer distinct starts than `N_STARTS`) is not fitted again (log-likelihood
    −inf). The same fits to round-off; measured on the 2-core CPU, `analyse_static_record`
    of a 16,000-sample record 146 → 115 s (one run each, the machine busy), its results
    within 1.3e-6 relative."""

    def one(args):
        z0, skip = args
        return jax.lax.cond(
            skip,
            lambda: (z0, jnp.asarray(-jnp.inf, z0.dtype), jnp.asarray(False)),
            lambda: _fit(z0, mask, gram, floor),
        )

    return jax.lax.map(one, (z0s, repeated))


def _free(mask):
    """The slots a fit moves: those `mask` switches on, less the corner of a moving or
    decimating average (its M, or K and R, in the code, set its gain)."""
    free = mask > 0
    return free.at[8].set(free[8] & (mask[8] < chain_filters.MOVING_AVERAGE_CODE))


def _fit(z0, mask, gram, floor):
    n = jnp.sum(gram.count)
    free = _free(mask)

    def loss(z, _):
        z = jnp.where(free, z, z0)
        return -whittle(z, mask, gram, floor) / n

    solver = StallEndingMinimiser(
        optx.BFGS(rtol=TOLERANCE, atol=TOLERANCE), STALL_WINDOW, 0.0, STALL_NATS / n
    )
    sol = optx.minimise(loss, solver, z0, max_steps=STEPS, throw=False)
    z = jnp.where(free, sol.value, z0)
    return z, whittle(z, mask, gram, floor), sol.result == optx.RESULTS.successful


@eqx.filter_jit
def log_likelihood(z, mask, gram, floor):
    """`whittle`, jitted."""
    return whittle(z, mask, gram, floor)


@eqx.filter_jit
def information(z, mask, gram, floor):
    """The observed information −∂² ln L/∂z² (for the intervals of the final model)."""
    return -jax.hessian(lambda u: whittle(u, mask, gram, floor))(z)


def starts(names, variance: float, new=None) -> list[np.ndarray]:
    """Starting points for a structure: the record's variance for the white slot and a
    small grid over the time scale of each correlated component in `new` (default: all
    of `names`; the Whittle likelihood can have several maxima in τ_c, β or the corner)."""
    base = np.zeros(N_PARAMS)
    base[0] = math.log(variance)
    base[1] = math.log(0.5 * variance)
    base[2] = math.log(10.0)
    base[3] = math.log(0.5 * variance)
    base[4] = math.log(0.05)
    base[5] = math.log(0.3)
    base[6] = math.log(1e-3 * variance)
    base[7] = math.log(0.1 * variance)
    base[8] = 1.0
    base[9] = math.log(0.1 * variance)
    base[10] = math.log(variance)
    base[11] = 0.0
    out = [base]
    grids = {
        "gauss_markov": [(2, math.log(t)) for t in (2.0, 50.0, 500.0)],
        "exp_cosine": [
            (slot, value)
            for theta in (0.05, 1.0, 2.5)
            for slot, value in ((5, math.log(theta)), (4, math.log(theta / 6)))
        ],
        "bandlimit": [(8, v) for v in (-2.0, 0.0, 3.0)],
        "filter_floor": [(9, math.log(v * variance)) for v in (0.01, 0.5)],
        "high_frequency_noise": [(11, v) for v in (-1.0, 1.0, 3.0)],
        "random_walk": [(6, math.log(v * variance)) for v in (1e-5, 1e-1)],
        "flicker": [(7, math.log(v * variance)) for v in (1e-3, 1.0)],
    }
    for name in names if new is None else new:
        if name == "exp_cosine":
            pairs = grids[name]
            for k in range(0, len(pairs), 2):
                z = base.copy()
                for slot, value in pairs[k : k + 2]:
                    z[slot] = value
                out.append(z)
            continue
        if name in OTHER_LOW_PASSES and OTHER_LOW_PASSES[name] >= chain_filters.MOVING_AVERAGE_CODE:
            continue  # a moving or decimating average: no corner to search (its code sets it)
        for slot, value in grids[effect_name(name)]:
            z = base.copy()
            z[slot] = value
            out.append(z)
    return out


def fit_structure(
    names, gram: Periodogram, floor: float, variance: float, parent=None, parent_names=()
):
    """Maximum Whittle likelihood of the structure `names` (a subset of `COMPONENTS` on top
    of white noise): the best of `starts`, `N_STARTS` of them fitted in one compiled call
    (`_fit_all`). With `parent` (the fit of the structure `parent_names` ⊂ `names`), every
    start also carries the parent's optimum in the parent's slots, so the extended fit
    starts where the nested one ended (and cannot end below it but by a failed search).

    Returns (z, log-likelihood, converged)."""
    mask = jnp.asarray(_mask(names))
    new = [n for n in names if n not in parent_names] if parent is not None else None
    candidates = starts(names, variance, new)
    if parent is not None:
        inherited = _mask(parent_names) > 0
        candidates = [np.where(inherited, np.asarray(parent), c) for c in candidates]
    candidates = (candidates * N_STARTS)[:N_STARTS]
    repeated = [any(np.array_equal(c, b) for b in candidates[:i]) for i, c in enumerate(candidates)]
    z, log_lik, ok = (
        np.asarray(a)
        for a in _fit_all(
            jnp.asarray(np.stack(candidates)),
            jnp.asarray(repeated),
            mask,
            gram,
            jnp.asarray(floor),
        )
    )
    log_lik = np.where(np.isfinite(log_lik), log_lik, -np.inf)
    i = int(np.argmax(log_lik))
    return z[i], float(log_lik[i]), bool(ok[i])
