"""The IEEE Std 952 / 1554 noise terms of an Allan deviation, with parametric-bootstrap
confidence intervals: `fit_allan_terms` and its result `AllanTerms`.

A rate record x (e.g. accelerometer output [u], u = g or m/s²) sampled every Δ has the
Allan variance of the standard five-term model

    σ²(τ) = 3Q²/τ² + N²/τ + (2 ln 2/π) B² + K²τ/3 + R²τ²/2,

Q quantisation [u·s], N white rate noise (velocity/angle random walk) [u·√s = u/√Hz], B
bias instability [u], K rate random walk [u/√s], R rate ramp [u/s]; linear in the squared
coefficients c = (Q², N², B², K², R²) ≥ 0. B is defined by the two-sided PSD of the rate,
S(f) = B²/(2π|f|) (one-sided B²/(π f)): with σ²(τ) = 2∫₀^∞ G(f) sin⁴(πfτ)/(πfτ)² df for
the one-sided G, G = h/f gives 2 ln 2·h, hence (2 ln 2/π) B²; likewise IEEE's N² is the
two-sided white level (one-sided 2N², σ² = N²/τ).

Why not least squares with intervals from its covariance: the ADEVs at different τ are
strongly correlated (the same samples) and their variances depend on the model (σ̂²(τ) is
close to σ²(τ)·χ²_ν/ν, ν the equivalent degrees of freedom, EDF, a few tens at the longest
τ), so such intervals are far too narrow and terms the data barely touch get named. Here

1. the point estimate is non-negative least squares on σ̂²(τ) at the octave τ's (IEEE's
   plot), weighted by the model-implied variance and iterated (the quasi-likelihood of a
   Gamma-like, identity-link model): var σ̂²(τ) ≈ 2 s² (+ the ramp's cross term,
   `_variance`), s = Σ_i σ_i²(τ)/√ν_i(τ), σ_i² each term's share of the current fit and
   ν_i Greenhall's EDF of the overlapping ADEV for its power law
   (`allantools.edf_greenhall`: white PM for Q, white FM for N, flicker FM for B,
   random-walk FM for K and R);
2. the intervals are a parametric bootstrap-t. c̃ is the weighted least squares at the
   converged weights with every term free in sign (a near-linear estimator, with no
   boundary at zero for an absent term to pile up on) and se its standard errors at those
   weights (they scale with the terms, so the pivot T_k = (c̃_k − c_k)/se_k hardly
   depends on the unknown c). `n_bootstrap` = B records of the same length are simulated
   from the fitted terms, their ADEV computed and refitted the same way, and the k-th
   smallest and largest pivots t_lo, t_hi, k = ⌊(B + 1)(1 − confidence)/2⌋, give
   c_k ∈ [c̃_k − t_hi se_k, c̃_k − t_lo se_k] (clipped at 0, then square-rooted).

The simulators (`_simulate`), each exact for its term's column of `_design`: Q, the first
difference of white noise of standard deviation Q, over Δ (the rate of a white
angle/velocity quantisation error: 3Q²/τ²); N, white noise of standard deviation N/√Δ
(N²/τ); B, flicker noise by FFT shaping of white noise to S(f) = B²/(2π|f|) on every bin
of a record of ≥ 2N samples (Timmer & König), an N-sample part kept: its expected ADEV is
`_sampled_flicker`, → √(2 ln 2/π)·B for τ ≫ Δ (σ² 19 % above at τ = Δ, 3 % at 4Δ,
~0.1 % below at the longest octave); K, a random walk of increments K√Δ
(K²τ/3 + K²Δ²/(6τ)); R, the ramp R·t (R²τ²/2). The fit uses these exact sampled-process
columns, which differ from the IEEE formula only at τ of a few Δ (so a flicker's excess
there is not mistaken for N or Q); `_design` without Δ is the formula itself.

What the intervals assume: the five-term model holds. A flicker whose high-frequency
shape differs from the band-limited 1/f above (a roll-off, aliasing) is indistinguishable
from a change of N and Q by a fraction of B's share of σ² at τ ≈ Δ; where N is very
precise that can exceed N's interval.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Sequence
from typing import cast

import jax
import numpy as np

from .allan import _allan_deviation, allan_deviation
from .allan_intervals import octave_cluster_sizes
from .record import _sample_interval, _validate_record

TERM_NAMES = ("Q", "N", "B", "K", "R")
"""The IEEE Std 952 terms, in order of the power of τ (−2 … +2 in σ²)."""

TERM_UNITS = {"Q": "u·s", "N": "u·√s", "B": "u", "K": "u/√s", "R": "u/s"}
"""Each term's unit, u being the record's unit (N in u·√s is u/√Hz)."""

_FLICKER = 2 * math.log(2) / math.pi
# Power-law exponent α of S_y(f) ∝ f^α whose Greenhall EDF weights each term (the ramp,
# deterministic, takes random-walk FM's: its σ̂² varies only through the other terms).
_ALPHA = {"Q": 2, "N": 0, "B": -1, "K": -2, "R": -2}
_MIN_SIZES_OVER_TERMS = 2  # octaves beyond the number of terms fitted
_MIN_BOOTSTRAP = 50
_CHUNK_SAMPLES = 4_000_000  # samples per simulated batch (32 MB of float64)


def minimum_samples(n_terms: int = 5) -> int:
    """The shortest record `fit_allan_terms` fits `n_terms` terms to: its octave τ's must
    number `_MIN_SIZES_OVER_TERMS` more than the terms (1,024 samples for all five)."""
    return 16 * 2 ** (n_terms + _MIN_SIZES_OVER_TERMS - 1)


def _flicker_size(n: int) -> int:
    """Length of the FFT record the flicker simulator draws (≥ 2n, the record a part)."""
    from scipy import fft

    return cast(int, fft.next_fast_len(2 * n, real=True))  # pyright reads None from its placeholder


def _sampled_flicker(taus: np.ndarray, dt: float, n: int) -> np.ndarray:
    """Exact Allan variance per B² of the simulated (sampled, band-limited) flicker at
    τ = mΔ: Σ over the FFT's bins of S(f) |H_m(f)|²/2 df, S(f) = 1/(2π|f|) two-sided and
    |H_m|² = 4 sin⁴(π f τ)/(m² sin²(π f Δ)) the squared gain of the difference of two
    consecutive m-sample means. → 2 ln 2/π for τ ≫ Δ (+19 % at τ = Δ, +3 % at 4Δ; ~−0.1 %
    at m = N/16, the FFT record's lowest frequency 1/(2NΔ) being missing below)."""
    size = _flicker_size(n)
    f = np.fft.rfftfreq(size, dt)[1:]
    both = np.full(f.size, 2.0)  # ±f, the Nyquist bin once
    if size % 2 == 0:
        both[-1] = 1.0
    weight = both / (2 * np.pi * f) / (size * dt) / 2 * 4 / np.sin(np.pi * f * dt) ** 2
    m = taus.reshape(-1, 1) / dt
    return (np.sin(np.pi * f * taus.reshape(-1, 1)) ** 4 / m**2) @ weight


def _design(
    terms, taus, sample_interval: float | None = None, n_samples: int | None = None
) -> np.ndarray:
    """σ²(τ) of each term per unit squared coefficient, shape (len(taus), len(terms)).

    Without `sample_interval`: the IEEE Std 952 formula. With it (and the record's length
    `n_samples`), the exact Allan variance of the simulated sampled processes: the same for
    Q, N and R, K²(τ/3 + Δ²/(6τ)) for the sampled random walk and the band-limited flicker
    `_sampled_flicker` for B, both → the formula for τ ≫ Δ."""
    taus = np.asarray(taus, np.float64)
    dt = sample_interval

    def flicker():
        if dt is None:
            return np.full_like(taus, _FLICKER)
        if n_samples is None:
            raise ValueError("the sampled flicker's variance needs the record's n_samples.")
        return _sampled_flicker(taus, dt, n_samples)

    columns = {
        "Q": lambda: 3 / taus**2,
        "N": lambda: 1 / taus,
        "B": flicker,
        "K": lambda: taus / 3 if dt is None else taus / 3 + dt**2 / (6 * taus),
        "R": lambda: taus**2 / 2,
    }
    return np.stack([columns[t]() for t in terms], axis=1)


@dataclasses.dataclass(frozen=True)
class AllanTerms:
    """The IEEE Std 952 noise terms fitted to a record's Allan deviation (`fit_allan_terms`).

    **Fields:**

    - `taus` [s], `deviation` the measured overlapping ADEV σ̂(τ) [u], `model_deviation`
      the fitted model's σ(τ) [u] (arrays over the octave τ's);
    - `terms`: {name: {"value", "lower", "upper", "supported", "unit"}} for each fitted
      term ("Q", "N", "B", "K", "R"). A supported term (its lower confidence bound > 0) has
      `value` (the point estimate) and the interval [`lower`, `upper`]; an unsupported one
      has `value` and `lower` None and only the upper bound `upper` (the interval is
      [0, upper]). Coefficients, not their squares, in the `unit` given (u the record's);
    - `fit_coefficients`: {name: coefficient} of the non-negative fit behind
      `model_deviation`, every term, supported or not (the curve's parameters; quote
      `terms`, not these);
    - `confidence`, `n_bootstrap`, `n_samples`, `sample_interval` [s], `method` (how the
      estimate and the intervals were made).

    `deviation_at(taus)` is the fitted model's σ(τ) at any τ (to draw over the measured).
    """

    taus: np.ndarray
    deviation: np.ndarray
    model_deviation: np.ndarray
    terms: dict
    fit_coefficients: dict
    confidence: float
    n_bootstrap: int
    n_samples: int
    sample_interval: float
    method: str

    def deviation_at(self, taus) -> np.ndarray:
        """The fitted model's Allan deviation σ(τ) [u] at `taus` [s] (any shape, > 0)."""
        taus = np.asarray(taus, dtype=np.float64)
        names = tuple(self.fit_coefficients)
        c = np.array([self.fit_coefficients[t] ** 2 for t in names])
        design = _design(names, taus.reshape(-1), self.sample_interval, self.n_samples)
        return np.sqrt(design @ c).reshape(taus.shape)


# --------------------------------------------------------------------------------------
# The fit


def _edf_table(terms, sizes, n):
    """Greenhall's EDF of the overlapping ADEV, shape (len(terms), len(sizes))."""
    import allantools

    def edf(alpha, m):
        return float(allantools.edf_greenhall(alpha=alpha, d=2, m=m, N=n, overlapping=True))

    table = {a: [edf(a, m) for m in sizes] for a in {_ALPHA[t] for t in terms}}
    return np.array([table[_ALPHA[t]] for t in terms])


def _variance(design, c, root_edf, ramp):
    """The model-implied var σ̂²(τ) ≈ 2 s² + 4 σ_R² s/√ν_R, s = Σ_{i≠R} σ_i²(τ)/√ν_i(τ): each
    random term's χ²-like share, their cross terms at the geometric mean of their EDFs, and
    the deterministic ramp's cross term with them (no variance of its own)."""
    share = design * c
    if ramp is None:
        return 2 * (share / root_edf.T).sum(axis=1) ** 2
    random = np.delete(share, ramp, axis=1) / np.delete(root_edf, ramp, axis=0).T
    s = random.sum(axis=1)
    return 2 * s**2 + 4 * share[:, ramp] * s / root_edf[ramp]


def _nnls(a, b):
    from scipy.optimize import nnls

    scale = np.linalg.norm(a, axis=0)
    scale[scale == 0] = 1.0
    x, _ = nnls(a / scale, b, maxiter=50 * a.shape[1])
    return x / scale


def _fit(avar, design, root_edf, ramp=None, *, max_iter=100, rtol=1e-10):
    """Iteratively reweighted non-negative least squares of σ̂²(τ) = X c, weights
    1/var σ̂²(τ) from the current fit (`_variance`).

    Returns (c ≥ 0 the point estimate, c̃ the sign-free weighted least squares at the final
    weights, se the standard errors of c̃ at those weights)."""
    # Start: weights from the measurement itself, at the least EDF of the terms.
    var = 2 * avar**2 / root_edf.min(axis=0) ** 2
    model = None
    c = np.zeros(design.shape[1])  # replaced by the first iteration (max_iter ≥ 1)
    for _ in range(max_iter):
        w = 1 / np.sqrt(var)
        c = _nnls(design * w[:, None], avar * w)
        new = design @ c
        # Floor: an iterate far below the measurement must not weigh a τ without bound.
        var = np.maximum(_variance(design, c, root_edf, ramp), (1e-6 * avar) ** 2)
        if model is not None and np.all(np.abs(new - model) <= rtol * np.abs(model)):
            break
        model = new
    w = 1 / np.sqrt(var)
    a, b = design * w[:, None], avar * w
    scale = np.linalg.norm(a, axis=0)
    free = np.linalg.lstsq(a / scale, b, rcond=None)[0] / scale
    cov = np.linalg.pinv((a / scale).T @ (a / scale)) / np.outer(scale, scale)
    return c, free, np.sqrt(np.diag(cov))


# --------------------------------------------------------------------------------------
# The simulators and the batched ADEV


def _simulate(coefficients, n, dt, rng, batch):
    """`batch` records of `n` samples from the terms {name: coefficient} (module docstring)."""
    from scipy import fft

    x = np.zeros((batch, n))
    q = coefficients.get("Q", 0.0)
    if q > 0:
        x += np.diff(rng.standard_normal((batch, n + 1)), axis=1) * (q / dt)
    white = coefficients.get("N", 0.0)
    if white > 0:
        x += rng.standard_normal((batch, n)) * (white / math.sqrt(dt))
    b = coefficients.get("B", 0.0)
    if b > 0:
        size = _flicker_size(n)
        f = np.fft.rfftfreq(size, dt)
        amplitude = np.zeros_like(f)
        # E|X_k|² = L S(f_k)/Δ makes irfft's output have the two-sided PSD S on its bins.
        amplitude[1:] = np.sqrt(size * b**2 / (2 * np.pi * f[1:]) / dt)
        spectrum = rng.standard_normal((batch, f.size)) + 1j * rng.standard_normal((batch, f.size))
        spectrum *= amplitude / math.sqrt(2)
        if size % 2 == 0:  # the Nyquist bin is real
            spectrum[:, -1] = spectrum[:, -1].real * math.sqrt(2)
        # (cast: pyright reads SciPy's uarray-dispatched transforms as returning a tuple)
        x += cast(np.ndarray, fft.irfft(spectrum, n=size, axis=1))[:, :n]
    k = coefficients.get("K", 0.0)
    if k > 0:
        x += np.cumsum(rng.standard_normal((batch, n)), axis=1) * (k * math.sqrt(dt))
    r = coefficients.get("R", 0.0)
    if r > 0:
        x += r * dt * np.arange(n)
    return x


def _batched_avar(records, dt, sizes):
    """σ̂²(τ) of each row of `records`: `allan_deviation`'s jitted kernel, mapped over the
    rows (`lax.map`). Vmapped, the same kernel took twice as long (a batch of 15 records of
    1.3e5 samples, 13 octaves: 0.16 s against 0.08 s on one core of the 2-core CPU, three
    medians of 5) with the same values to round-off (the bootstrap's interval ends of the
    1.3e5-sample benchmark record moved by at most 7e-14 relative): the rows' cumulative
    sums and reductions run one record at a time, in cache."""
    with jax.enable_x64(True):
        return np.asarray(_avar_rows(records, dt, tuple(sizes)), np.float64)


@functools.partial(jax.jit, static_argnums=(1, 2))
def _avar_rows(records, dt, sizes):
    return jax.lax.map(lambda x: _allan_deviation(x, dt, sizes)[1] ** 2, records)


def _order_statistic(n_bootstrap, confidence):
    """k of the bootstrap-t's ends (the k-th smallest and largest of B pivots)."""
    return max(1, math.floor((n_bootstrap + 1) * (1 - confidence) / 2 + 1e-9))


# --------------------------------------------------------------------------------------
# The public function


def fit_allan_terms(
    record,
    sample_interval: float,
    *,
    confidence: float = 0.95,
    n_bootstrap: int = 199,
    seed: int = 0,
    terms: Sequence[str] = TERM_NAMES,
) -> AllanTerms:
    """Fit the IEEE Std 952 / 1554 noise terms to a rate record's Allan deviation, with
    parametric-bootstrap confidence intervals (the method: this module's docstring).

    σ²(τ) = 3Q²/τ² + N²/τ + (2 ln 2/π) B² + K²τ/3 + R²τ²/2 at the octave τ = mΔ,
    m = 1, 2, 4, … while the record holds 8 clusters of 2m samples; the point estimate is
    the iteratively weighted non-negative least squares, the intervals a bootstrap-t.

    **Rule for a term:** a term is *supported* when the lower bound of its interval is
    > 0, i.e. its squared coefficient is significantly positive (one-sided level
    (1 − confidence)/2); it is then reported with its value and interval. A term the data
    do not support is reported as not supported, with only an upper bound (value and
    lower None): it is not reported as a number. The value and the interval are those of
    the sign-free weighted fit c̃ (the bootstrap-t's own estimate, so the value lies in
    its interval); the drawn curve `model_deviation` and `fit_coefficients` are the
    non-negative fit's, which differ from c̃ only where another term sits at zero. An
    upper bound of 0 means the whole interval of c̃ lies below zero.

    **Arguments:** `record` x (N samples of a rate, any unit u); `sample_interval` Δ [s];
    `confidence` of the two-sided intervals, in (0, 1); `n_bootstrap` simulated records
    (≥ 50 and ≥ 2/(1 − confidence) − 1; with (n_bootstrap + 1)(1 − confidence)/2 an
    integer, as for 199 at 95 %, the interval's nominal level is exact); `seed` of the
    simulation (NumPy); `terms` the subset of ("Q", "N", "B", "K", "R") to fit (the
    others are taken as absent).

    **Returns:** an `AllanTerms`. Host-side NumPy, float64 whatever JAX's setting (restored
    after); the ADEVs by `allan_deviation`'s jitted kernel. About 2 s for 1e5 samples and
    200 bootstrap records on a CPU core, linear in both.

    **Raises:** `ValueError` for a non-finite, constant, non-1-D or too short record (fewer
    than len(terms) + 2 octave τ's), a non-positive Δ, an unknown or repeated term or the
    ramp alone, a confidence outside (0, 1) or too few bootstrap records.
    """
    return _fit_allan_terms(record, sample_interval, confidence, n_bootstrap, seed, terms, None)


class Stopped(Exception):
    """Raised by `_fit_allan_terms` when its `stop` event is set between bootstrap batches."""


def _fit_allan_terms(record, sample_interval, confidence, n_bootstrap, seed, terms, stop):
    """`fit_allan_terms`; `stop`: None, or a `threading.Event` checked before each batch of
    the bootstrap (`Stopped` raised once it is set), so that a caller that runs this on a
    background thread can end it within a batch (~0.3 s on 1.3e5 samples) when the user
    interrupts the work beside it."""
    name = "fit_allan_terms"
    with jax.enable_x64(True):  # float64 whatever the caller's setting (restored after)
        x = np.asarray(_validate_record(name, record), np.float64)
    _sample_interval(name, sample_interval)
    dt = float(sample_interval)
    terms = tuple(terms) if not isinstance(terms, str) else (terms,)
    unknown = [t for t in terms if t not in TERM_NAMES]
    if not terms or unknown or len(set(terms)) != len(terms):
        raise ValueError(f"{name}: terms must be distinct names among {TERM_NAMES}, got {terms!r}.")
    terms = tuple(t for t in TERM_NAMES if t in terms)  # canonical order
    if terms == ("R",):
        raise ValueError(
            f"{name}: terms must include a noise term (Q, N, B or K): the ramp alone is "
            "deterministic and its bootstrap has nothing to vary."
        )
    if not (isinstance(confidence, (int, float, np.floating)) and 0 < confidence < 1):
        raise ValueError(f"{name}: confidence must be in (0, 1), got {confidence}.")
    least = max(_MIN_BOOTSTRAP, math.ceil(2 / (1 - confidence) - 1))
    if not (
        isinstance(n_bootstrap, (int, np.integer))
        and not isinstance(n_bootstrap, bool)
        and n_bootstrap >= least
    ):
        raise ValueError(
            f"{name}: n_bootstrap must be an integer ≥ {least} (≥ 50, and ≥ 2/(1 − confidence)"
            f" − 1 for the interval's ends to exist), got {n_bootstrap!r}."
        )
    n_bootstrap = int(n_bootstrap)
    n = x.size
    sizes = tuple(octave_cluster_sizes(n))
    if len(sizes) < len(terms) + _MIN_SIZES_OVER_TERMS:
        need = minimum_samples(len(terms))
        raise ValueError(
            f"{name}: a record of {n} samples is too short: it gives {len(sizes)} octave τ's "
            f"and fitting {len(terms)} terms needs {len(terms) + _MIN_SIZES_OVER_TERMS} "
            f"(at least {need} samples)."
        )

    with jax.enable_x64(True):
        taus, deviation = allan_deviation(x, dt, sizes)
    taus, deviation = np.asarray(taus, np.float64), np.asarray(deviation, np.float64)
    design = _design(terms, taus, dt, n)
    root_edf = np.sqrt(_edf_table(terms, sizes, n))
    ramp = terms.index("R") if "R" in terms else None
    c, free, se = _fit(deviation**2, design, root_edf, ramp)
    fitted = {t: math.sqrt(v) for t, v in zip(terms, c, strict=True)}

    # Parametric bootstrap-t from the fitted terms.
    rng = np.random.default_rng(seed)
    batch = max(1, min(n_bootstrap, _CHUNK_SAMPLES // (2 * n)))
    pivots = []
    while len(pivots) < n_bootstrap:
        if stop is not None and stop.is_set():
            raise Stopped("fit_allan_terms: stopped by the caller")
        size = min(batch, n_bootstrap - len(pivots))
        records = _simulate(fitted, n, dt, rng, size)
        if size < batch:  # one compiled shape: pad the last batch with zero records
            records = np.concatenate([records, np.zeros((batch - size, n))])
        for avar in _batched_avar(records, dt, sizes)[:size]:
            _, free_b, se_b = _fit(avar, design, root_edf, ramp)
            pivots.append((free_b - c) / se_b)
    # The k-th smallest and largest pivots, k = ⌊(B + 1)α/2⌋: were the observed pivot and
    # the B simulated ones exchangeable, each end would be missed with probability
    # k/(B + 1) ≤ α/2 exactly, whatever B (an interpolated quantile misses more often).
    pivots = np.sort(np.array(pivots), axis=0)
    k = _order_statistic(n_bootstrap, confidence)
    t_lo, t_hi = pivots[k - 1], pivots[n_bootstrap - k]
    lower_c, upper_c = free - t_hi * se, free - t_lo * se

    report = {}
    for i, t in enumerate(terms):
        supported = bool(lower_c[i] > 0)
        report[t] = {
            # the sign-free estimate: the interval's own point, so value ∈ [lower, upper]
            "value": math.sqrt(free[i]) if supported else None,
            "lower": math.sqrt(lower_c[i]) if supported else None,
            "upper": math.sqrt(max(upper_c[i], 0.0)),
            "supported": supported,
            "unit": TERM_UNITS[t],
        }
    return AllanTerms(
        taus=taus,
        deviation=deviation,
        model_deviation=np.sqrt(design @ c),
        terms=report,
        fit_coefficients=fitted,
        confidence=float(confidence),
        n_bootstrap=n_bootstrap,
        n_samples=n,
        sample_interval=dt,
        method=(
            "IEEE Std 952 five-term model; non-negative least squares on the octave "
            "overlapping Allan variance, iteratively weighted by the model-implied variance "
            "(Greenhall EDF); intervals by a parametric bootstrap-t of each squared "
            "coefficient's sign-free weighted fit, order statistics k = "
            f"{k} of {n_bootstrap} simulated records; supported = lower bound > 0"
        ),
    )
