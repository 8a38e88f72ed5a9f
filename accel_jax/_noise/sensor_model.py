"""The sensor-noise selection's candidate models and how they are judged.

A candidate (`_Model`) is a set of named stochastic effects (fitted by the Whittle
likelihood of `accel_jax._noise.spectral`), periodic lines (`mean_models.PeriodicLine`s,
`_fit_line`, each found by a golden-section search around a periodogram peak) and a
start-up transient a e^{−t/τ} (`mean_models.StartupTransient`), fitted to a record
(`_Record`) on its training part (the first 2/3) and scored on the whole record. Here:
the fits (`_evaluate`; `_evaluate_many` runs several on threads, one per core), the
evidence of a larger model against a smaller one (`_evidence`: 2 Δ ln L − k ln J, k from
`PARAMETER_COUNT`), the paired held-out check (`_held_out_z`), the transient's exact
time-domain likelihood ratio (`_transient_test`: Durbin–Levinson on the record's first
differences), the held-out excess deviance and the explained fraction, the model's
variogram (for the level-shift test) and its fitted values in physical units
(`_physical`). `accel_jax._noise.sensor` drives the selection.

Float64, NumPy on the host; one jitted, vmapped Whittle fit per record length.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._runtime import thread_map
from . import chain_filters, spectral
from .mean_models import PeriodicLine, StartupTransient

HELD_OUT_FRACTION = 1 / 3


HELD_OUT_Z = 2.0
"""An addition is refused when the held-out part prefers the model without it at this
paired z (`_held_out_z`)."""


EULER_GAMMA = 0.5772156649015329


DEVIANCE_VARIANCE = math.pi**2 / 6 - 1


PARAMETER_COUNT = {
    "gauss_markov": 2,
    "exp_cosine": 3,
    "random_walk": 1,
    "flicker": 1,
    **{name: 1 for name in spectral.LOW_PASS_ORDERS},  # the corner, or a moving average's M
    "filter_floor": 1,
    "high_frequency_noise": 2,
    "sinusoid": 3,
    "startup_transient": 2,
}


def _line_design(t, f):
    return np.stack([*PeriodicLine.basis(t, f), np.ones_like(t)], 1)


LINE_BLOCK = 32
"""Samples per block of the demodulated record in the line's frequency search."""


def _fit_line(r: np.ndarray, t: np.ndarray, f0: float, width: float) -> PeriodicLine:
    """A sinusoid at the frequency near f0 (±width) that best fits r: the frequency that
    maximises the periodogram |Σ r_k e^{−i2πf t_k}|² (a grid, then golden-section search),
    evaluated on the record demodulated at f0 and summed over blocks of `LINE_BLOCK`
    samples (the residual frequency |f − f0| ≤ width turns the phase by at most
    2π·width·`LINE_BLOCK`Δ within a block: ~1 % of a turn for a record of 300 blocks and
    more); then cos, sin and a constant by least squares at that frequency."""
    r = r - np.mean(r)
    usable = r.size // LINE_BLOCK * LINE_BLOCK
    z = (r[:usable] * np.exp(-2j * np.pi * f0 * t[:usable])).reshape(-1, LINE_BLOCK)
    centre = t[:usable].reshape(-1, LINE_BLOCK).mean(1)
    offsets = np.arange(LINE_BLOCK) * (t[1] - t[0]) if r.size > 1 else np.zeros(1)
    offsets = offsets - offsets.mean()

    def power(delta):
        inner = np.exp(-2j * np.pi * delta * offsets)  # the phase within a block, exactly
        blocks = z @ inner
        return float(np.abs(np.sum(blocks * np.exp(-2j * np.pi * delta * centre))) ** 2)

    grid = np.linspace(-width, width, 41)
    values = [power(d) for d in grid]
    i = int(np.argmax(values))
    lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)]
    golden = (math.sqrt(5) - 1) / 2
    c, d = hi - golden * (hi - lo), lo + golden * (hi - lo)
    pc, pd = power(c), power(d)
    for _ in range(40):  # each step keeps one of the two inner points and its power
        if pc > pd:
            hi, d, pd = d, c, pc
            c = hi - golden * (hi - lo)
            pc = power(c)
        else:
            lo, c, pc = c, d, pd
            d = lo + golden * (hi - lo)
            pd = power(d)
    f = f0 + 0.5 * (lo + hi)
    design = _line_design(t, f)
    coef, *_ = np.linalg.lstsq(design, r, rcond=None)
    return PeriodicLine(float(f), float(coef[0]), float(coef[1]))


def _mean_key(lines: tuple, transient: StartupTransient | None) -> str:
    """The deterministic terms as a key of the fits' and periodograms' caches: the exact
    reprs of their parameters."""
    key: list[tuple[float, ...]] = [
        (float(line.frequency), float(line.cosine), float(line.sine)) for line in lines
    ]
    if transient is not None:
        key.append((float(transient.amplitude), float(transient.time_constant)))
    return repr(key)


@dataclasses.dataclass
class _Model:
    names: tuple
    lines: tuple  # of `PeriodicLine`s
    transient: StartupTransient | None
    z: np.ndarray
    train: float
    held: float
    held_terms: np.ndarray
    converged: bool


class _Record:
    """A record under selection: its training and held-out parts, the periodograms of its
    residuals (by lines and transient) and `fits`, the fitted models by content (the
    record's samples and Δ, the model's structure, lines, transient and start), which the
    passes of one `select_sensor_noise` call share: a second forward selection of the
    same record (in the order of the evidence alone, or after a step is taken out and put
    back) refits nothing it fitted before."""

    def __init__(self, x, dt, fits: dict | None = None):
        self.x = x
        self.dt = dt
        self.fits = {} if fits is None else fits
        self.key = (hashlib.sha1(np.ascontiguousarray(x, np.float64).tobytes()).digest(), dt)
        self.n = x.size
        self.split = int(round((1 - HELD_OUT_FRACTION) * self.n))
        self.t = np.arange(self.n) * dt
        self.variance = float(np.var(np.diff(x[: self.split]))) / 2
        self._grams = {}

    def residual(self, lines, transient):
        r = self.x - np.mean(self.x[: self.split])
        for line in lines:
            r = r - line.signal(self.t)
        if transient is not None:  # (self.t starts at 0: the record's first sample)
            r = r - transient.signal(self.t)
        return r

    def grams(self, lines, transient):
        key = _mean_key(lines, transient)
        if key not in self._grams:
            r = self.residual(lines, transient)
            self._grams[key] = (
                spectral.periodogram(r[: self.split]),
                spectral.periodogram(r[self.split :]),
            )
        return self._grams[key]


def _evaluate(record, floor, names, lines, transient, parent=None) -> _Model:
    parent_z, parent_names = (parent.z, parent.names) if parent is not None else (None, ())
    start = None if parent_z is None else (np.asarray(parent_z).tobytes(), tuple(parent_names))
    key = (record.key, floor, tuple(names), _mean_key(lines, transient), start)
    if key not in record.fits:  # the same fit again (a deterministic XLA call): reused
        record.fits[key] = _fit(record, floor, names, lines, transient, parent_z, parent_names)
    return record.fits[key]


def _fit(record, floor, names, lines, transient, parent_z, parent_names) -> _Model:
    train, held = record.grams(lines, transient)
    z, log_lik, ok = spectral.fit_structure(
        list(names), train, floor, record.variance, parent_z, parent_names
    )
    mask = jnp.asarray(spectral._mask(names))
    terms = np.asarray(spectral.whittle_terms(jnp.asarray(z), mask, held, jnp.asarray(floor)))
    held_lik = float(np.sum(terms))
    return _Model(tuple(names), tuple(lines), transient, z, log_lik, held_lik, terms, ok)


def _evaluate_many(record, floor, specs: list) -> list:
    """`_evaluate` of each spec (names, lines, transient, parent), in order. Independent
    fits run on as many threads as the process has cores (`thread_map`): a fit is one XLA
    call that runs on one core and releases the GIL (the first forward step of a
    10⁶-sample record 3.3 s → 1.9 s on the 2-core machine). The same fits, the same
    results, in either case."""
    return thread_map(lambda spec: _evaluate(record, floor, *spec), specs)


def _evidence(model: _Model, smaller: _Model, k: int, log_j: float) -> float:
    """2 ln B of `model` over `smaller` (nested): 2 Δ ln L on the whole record (the
    training part's likelihood at the parameters fitted there plus the held-out part's at
    the same parameters: the held-out part only confirms, and an addition that fits the
    training part's noise loses its gain there) − k ln J, J the whole record's bins."""
    score = 2 * ((model.train + model.held) - (smaller.train + smaller.held)) - k * log_j
    # a fit that failed (a non-finite likelihood) is no evidence, and must not scramble
    # the ranking (NaN compares false with everything)
    return score if math.isfinite(score) else -math.inf


def _held_out_z(model: _Model, smaller: _Model) -> float:
    """The held-out check of an addition: a paired z of the held-out log-likelihood gain
    over its entries, Σ d_j / √(Σ d_j²) with d_j each periodogram entry's change (Vuong's
    statistic with the spread taken about zero, not about the mean: never larger in size,
    so the check is conservative). The addition is refused when the held-out part prefers
    the smaller model significantly (z < −`HELD_OUT_Z`). Not a demand that the held-out
    part gain: an effect whose evidence lies at the lowest frequencies (flicker, a random
    walk) has its gain in a few bins that the held-out part, a third of the record, does
    not even resolve, and its held-out gain then scatters about zero."""
    d = model.held_terms - smaller.held_terms
    scale = float(np.sqrt(np.sum(d * d)))
    if not np.isfinite(scale):
        return -math.inf
    return float(np.sum(d)) / scale if scale > 0 else 0.0


TRANSIENT_WINDOW = 1 << 12
"""The start-up transient is tested on at most `TRANSIENT_WINDOW` first differences at each
of its scales (`_transient_scales`), time constants up to a quarter of that window."""


TRANSIENT_TAUS = 24

TRANSIENT_SCALE_STEP = 16
TRANSIENT_MAX_SCALE = 256
"""The transient's scales: block means of 1, 16, … samples (`TRANSIENT_SCALE_STEP`), the
last the block that makes the window cover the training part, at most
`TRANSIENT_MAX_SCALE` samples (time constants up to 2^18 samples: 22 min at 200 Hz)."""


def _transient_scales(n: int) -> list[int]:
    """The block lengths m at which `_transient_test` looks for a transient in n samples:
    1, then ×`TRANSIENT_SCALE_STEP` until `TRANSIENT_WINDOW` blocks cover the n samples
    (the last the shortest block that does), at most `TRANSIENT_MAX_SCALE`. A thermal
    warm-up of a minute in a 200 Hz record needs a window of ~50,000 samples; Durbin–
    Levinson on that many costs O(n²), on 4,096 block means of 13 samples it does not."""
    scales = [1]
    while scales[-1] * TRANSIENT_WINDOW < n and scales[-1] < TRANSIENT_MAX_SCALE:
        covering = -(-n // TRANSIENT_WINDOW)
        scales.append(min(scales[-1] * TRANSIENT_SCALE_STEP, covering, TRANSIENT_MAX_SCALE))
    return scales


def _transient_grid(n: int, dt: float, m: int) -> np.ndarray:
    """The time constants `_transient_test` tries on n samples at block length m: from 2
    blocks to a quarter of the window of differences, `TRANSIENT_TAUS` of them."""
    size = min(TRANSIENT_WINDOW + 1, n // m) - 1
    return np.geomspace(2 * m * dt, max(size * m * dt / 4, 3 * m * dt), TRANSIENT_TAUS)


def _transient_tau_limit(n: int, dt: float) -> float:
    """The longest time constant `_transient_test` tries on n samples (its last scale's)."""
    return float(_transient_grid(n, dt, _transient_scales(n)[-1])[-1])


@functools.lru_cache(maxsize=4)
def _aliasing(size: int, block: int) -> tuple[np.ndarray, np.ndarray | None]:
    """The frequencies `_differenced_autocovariance` evaluates f_y at (the m = `block`
    frequencies ν_k folded onto [0, π], for each ω of its grid of 8·size) and the weights
    sin⁴(ω/2) / sin⁴(ν_k/2) of their sum (None for m = 1); fixed by (size, block)."""
    grid = 8 * size
    m = block
    w = 2 * np.pi * np.arange(grid) / grid
    nu = (w[:, None] + 2 * np.pi * np.arange(m)) / m  # in [0, 2π)
    folded = np.minimum(nu, 2 * np.pi - nu).ravel()
    if m == 1:
        folded.setflags(write=False)
        return folded, None
    below = np.sin(nu / 2) ** 4
    ratio = np.sin(w / 2)[:, None] ** 4 / np.where(below > 0, below, 1.0)
    ratio[0, 0] = float(m) ** 4
    folded.setflags(write=False)  # shared by every call of the same (size, block)
    ratio.setflags(write=False)
    return folded, ratio


def _differenced_autocovariance(
    model: _Model,
    floor: float,
    size: int,
    block: int = 1,
    spectrum=spectral.compiled_spectrum,
) -> np.ndarray:
    """γ(h), h = 0..size−1, of the differenced block means ȳ_j = x̄_j − x̄_{j−1} of the
    model's record x over blocks of `block` samples (`block` = 1: y = Δx): the inverse
    Fourier transform of its spectral density on a grid of 8·size. From f_y, the
    differenced record's density (`spectral.spectrum`), by the boxcar's response
    |H(ν)|² = sin²(mν/2) / (m² sin²(ν/2)) and the aliasing of the m frequencies
    ν_k = (ω + 2πk)/m onto ω:

        f_ȳ(ω) = sin⁴(ω/2)/m³ · Σ_k f_y(ν_k) / sin⁴(ν_k/2)   (the k = 0 term at ω = 0: m f_y(0))

    (f_x = f_y / (4 sin²(ν/2)), f_x̄(ω) = Σ_k f_x(ν_k) |H(ν_k)|² / m, f_ȳ = 4 sin²(ω/2) f_x̄.
    Checked against the time-domain sum over γ_y in tests/test_noise_sensor.py.)
    `spectrum`: f_y's function (`spectral.compiled_spectrum`, or another of the same
    arguments)."""
    grid = 8 * size
    m = block
    folded, ratio = _aliasing(size, block)
    z, mask = jnp.asarray(model.z), jnp.asarray(spectral._mask(model.names))
    f = _in_chunks(lambda omega: spectrum(z, mask, omega, floor), folded).reshape(grid, m)
    if ratio is not None:
        f = np.sum(ratio * f, axis=1, keepdims=True) / float(m) ** 3
    return np.real(np.fft.ifft(f[:, 0]))[:size]


SPECTRUM_CHUNK = 1 << 15
"""`_differenced_autocovariance` evaluates f_y on `SPECTRUM_CHUNK` frequencies at a time
(the last chunk padded): one compiled shape for every window and block length, where a
program per length (5 on a 1.3e5-sample record, ~0.2 s each) was compiled in every new
process. f_y is elementwise in ω: the same values."""


def _in_chunks(fn, omega: np.ndarray) -> np.ndarray:
    """`fn(omega)` of an elementwise `fn`, on `SPECTRUM_CHUNK` entries of ω at a time."""
    pad = -omega.size % SPECTRUM_CHUNK
    padded = np.concatenate([omega, np.full(pad, omega[-1])]) if pad else omega
    parts = [
        np.asarray(fn(padded[i : i + SPECTRUM_CHUNK]))
        for i in range(0, padded.size, SPECTRUM_CHUNK)
    ]
    return np.concatenate(parts)[: omega.size]


def _innovations(
    gamma: np.ndarray, vectors: np.ndarray, block: int = 256
) -> tuple[np.ndarray, np.ndarray]:
    """The one-step prediction errors of the columns of `vectors` under the stationary
    autocovariance γ (the Durbin–Levinson recursion: each sample predicted from all the
    earlier ones of the window) and their variances D_k; Σ_k e_k e'_k/D_k is then the exact
    Gaussian inner product uᵀ C⁻¹ v. Where D_k reaches 0 (γ not positive definite beyond
    k samples) the first k are returned.

    The recursion gives the predictor of each sample; the errors of `block` samples at a
    time are then one matrix product (their predictors as rows) instead of a product per
    sample: the transient test's window of 4,096 samples and 26 columns in 0.14 s instead
    of 0.42 s on the 2-core CPU (one core, median of 5), equal to round-off."""
    size = gamma.size
    out = np.empty_like(vectors)
    variance = np.empty(size)
    rows = np.zeros((block, size))  # row k − start: e_k = rows[k − start] · vectors
    start = 0

    def flush(stop):  # the errors of samples start..stop−1
        out[start:stop] = rows[: stop - start, :stop] @ vectors[:stop]
        rows[:] = 0.0

    phi = np.zeros(0)
    d = float(gamma[0])
    rows[0, 0] = 1.0
    variance[0] = d
    for k in range(1, size):
        if k - start == block:
            flush(k)
            start = k
        kappa = (gamma[k] - phi @ gamma[k - 1 : 0 : -1]) / d if k > 1 else gamma[1] / d
        phi = np.concatenate([phi - kappa * phi[::-1], [kappa]])
        d = d * (1 - kappa * kappa)
        if not d > 0:
            flush(k)
            return out[:k], variance[:k]
        rows[k - start, :k] = -phi[::-1]
        rows[k - start, k] = 1.0
        variance[k] = d
    flush(size)
    return out, variance


def _transient_test(r: np.ndarray, dt: float, model: _Model, floor: float) -> dict:
    """The start-up transient a e^{−t/τ} that best explains the start of r, and its
    evidence 2 ln Λ against `model`'s noise, by generalised least squares in the time
    domain: on the first `TRANSIENT_WINDOW` first differences y of r's block means at each
    scale of `_transient_scales` (the difference takes the level out and makes a random
    walk stationary; block means of m samples let the window reach slow warm-ups), the
    exact Gaussian likelihood ratio of y − a Δh_τ − b against y − b under the model's
    autocovariance of y (Durbin–Levinson; b, a constant rate of the level, is a nuisance:
    a linear drift is not a transient), 2 ln Λ = (Δhᵀ C⁻¹ y)² / (Δhᵀ C⁻¹ Δh) with b
    projected out of both, maximised over a geometric grid of τ from 2 blocks to a
    quarter of the window, and over the scales.

    The spectral (Whittle) likelihood cannot judge a transient: its taper gives the first
    samples of the record, where the transient lives, almost no weight. Returns
    {"evidence": 2 ln Λ, "transient": the `StartupTransient`}."""
    found = [_transient_test_at(r, dt, model, floor, m) for m in _transient_scales(r.size)]
    return max(found, key=lambda f: f["evidence"])


def _transient_templates(size: int, m: int, dt: float, taus: np.ndarray) -> np.ndarray:
    """The first differences of the block means (m samples) of e^{−t/τ}, one column per τ
    of `taus`, `size` rows: a block's mean is its first sample's value times the mean of
    e^{−i dt/τ}, i < m (exactly 1 for m = 1)."""
    spread = -np.expm1(-m * dt / taus) / (m * -np.expm1(-dt / taus))
    starts = np.arange(size + 1) * m * dt
    return np.diff(StartupTransient(1.0, taus).signal(starts[:, None]) * spread, axis=0)


def _differenced_block_means(r: np.ndarray, m: int, blocks: int) -> np.ndarray:
    """The first differences of the means of the first `blocks` blocks of m samples of r."""
    return np.diff(r[: blocks * m].reshape(blocks, m).mean(axis=1))


def _drift_profiled(gram: np.ndarray) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """From the C⁻¹ inner products `gram` of the columns (y, 1, templates…): y's quadratic
    form with the level's drift (a constant mean of y) profiled out, and each template's
    cross product with y, its energy and its 2 ln Λ, the drift projected out of both (a
    ramp is not a transient)."""
    drift = gram[1, 1]
    quad = gram[0, 0] - gram[0, 1] ** 2 / drift
    cross = gram[2:, 0] - gram[2:, 1] * gram[1, 0] / drift
    energy = np.diag(gram)[2:] - gram[2:, 1] ** 2 / drift
    z2 = np.where(energy > 0, cross**2 / np.where(energy > 0, energy, 1.0), 0.0)
    return float(quad), cross, energy, z2


def _transient_test_at(r: np.ndarray, dt: float, model: _Model, floor: float, m: int) -> dict:
    """`_transient_test` on the block means of r over blocks of m samples."""
    y = _differenced_block_means(r, m, min(TRANSIENT_WINDOW + 1, r.size // m))
    size = y.size
    taus = _transient_grid(r.size, dt, m)
    templates = _transient_templates(size, m, dt, taus)
    gamma = _differenced_autocovariance(model, floor, size, m)
    columns = np.concatenate([y[:, None], np.ones((size, 1)), templates], axis=1)
    e, d = _innovations(gamma, columns)
    weighted = e / d[:, None]
    gram = weighted.T @ e  # the C⁻¹ inner products of every pair of columns
    _, cross, energy, z2 = _drift_profiled(gram)
    i = int(np.argmax(z2))
    amplitude = float(cross[i] / energy[i]) if energy[i] > 0 else 0.0
    return {"evidence": float(z2[i]), "transient": StartupTransient(amplitude, float(taus[i]))}


def _held_out_deviance(record, floor, model: _Model) -> dict:
    r = record.residual(model.lines, model.transient)[record.split :]
    gram = spectral.periodogram(r, banded=False)
    mask = jnp.asarray(spectral._mask(model.names))
    _, dev = spectral.deviance_terms(jnp.asarray(model.z), mask, gram, jnp.asarray(floor))
    dev = np.asarray(dev)
    excess = float(np.sum(dev) - EULER_GAMMA * dev.size)
    return {
        "excess_deviance": excess,
        "z": excess / math.sqrt(DEVIANCE_VARIANCE * dev.size),
        "bins": int(dev.size),
    }


def _standardised_peak(record, floor, model: _Model):
    """The largest standardised periodogram ordinate I/f of the training residual (full
    resolution): where a line would be."""
    r = record.residual(model.lines, model.transient)[: record.split]
    gram = spectral.periodogram(r, banded=False)
    mask = jnp.asarray(spectral._mask(model.names))
    ratio, _ = spectral.deviance_terms(jnp.asarray(model.z), mask, gram, jnp.asarray(floor))
    ratio = np.array(ratio)
    # Not the lowest bins: a drift there is a line's impostor.
    ratio[:2] = 0
    j = int(np.argmax(ratio))
    m = r.size - 1
    return float(np.asarray(gram.omega)[j] / (2 * np.pi * record.dt)), 1 / (m * record.dt)


def _physical(model: _Model, dt: float, floor: float, n_train: int | None = None) -> dict:
    z = model.z
    out: dict[str, Any] = {"white_sigma": math.sqrt(math.exp(z[0]))}
    if "gauss_markov" in model.names:
        out["gauss_markov"] = {
            "sigma": math.sqrt(math.exp(z[1])),
            "correlation_time_s": math.exp(z[2]) * dt,
        }
    if "exp_cosine" in model.names:
        out["exp_cosine"] = {
            "sigma": math.sqrt(math.exp(z[3])),
            "decay_rate_per_s": math.exp(z[4]) / dt,
            "angular_frequency_rad_per_s": math.exp(z[5]) / dt,
        }
    if "random_walk" in model.names:
        out["random_walk"] = {"intensity_per_s": math.exp(z[6]) / dt}
    if "flicker" in model.names:
        b = math.sqrt(math.exp(z[7]))
        out["flicker"] = {
            "bias_instability_B": b,
            "allan_floor": b * math.sqrt(2 * math.log(2) / math.pi),
        }
    if "high_frequency_noise" in model.names:
        rise = float(jax.nn.sigmoid(z[11])) * math.pi / 2
        out["high_frequency_noise"] = {
            "sigma": math.sqrt(math.exp(z[10])),
            "corner_Hz": rise / (math.pi * dt),
        }
    order_name = spectral.low_pass(model.names)
    if order_name is not None:
        shape, n = chain_filters.code_kind(spectral.LOW_PASS_ORDERS[order_name])
        if shape == "moving_average":  # its −3 dB point is set by M
            out["bandlimit"] = {
                "corner_Hz": chain_filters.moving_average_corner(n) / dt,
                "order": None,
                "shape": shape,
                "taps": n,
            }
        elif shape == "decimating_average":  # K and R set its gain and −3 dB point
            stages, ratio = divmod(n, 100)
            out["bandlimit"] = {
                "corner_Hz": chain_filters.decimation_corner(stages, ratio) / dt,
                "order": stages,
                "shape": shape,
                "ratio": ratio,
            }
        else:
            corner = float(jax.nn.sigmoid(z[8])) * math.pi / 2
            out["bandlimit"] = {"corner_Hz": corner / (math.pi * dt), "order": n, "shape": shape}
        if "filter_floor" in model.names:  # the white noise after the filter, fitted
            out["bandlimit"]["white_after_filter_sigma"] = math.sqrt(math.exp(z[9]))
    if model.lines:
        out["sinusoid"] = [line.to_dict() for line in model.lines]
    if model.transient is not None:
        out["startup_transient"] = model.transient.to_dict()
        if n_train is not None:  # at the longest τ tried, a bound, not an estimate: said
            limit = _transient_tau_limit(n_train, dt)
            at_limit = float(model.transient.time_constant) >= limit * (1 - 1e-9)
            out["startup_transient"]["time_constant_at_limit"] = at_limit
    # the white variance after the filter: the output grid's (or a negligible floor) and
    # the fitted `filter_floor`
    out["post_filter_floor_variance"] = floor + (
        math.exp(z[9]) if "filter_floor" in model.names else 0.0
    )
    return out


def _explained(dev: dict, nominal: dict) -> float:
    """The share of the nominal model's held-out excess deviance that a model removes."""
    if not nominal["excess_deviance"] > 0:
        return 0.0
    return min(max(1 - dev["excess_deviance"] / nominal["excess_deviance"], 0.0), 1.0)


def _variogram(model: _Model, floor: float, size: int) -> np.ndarray:
    """V(h) = ½ E (x_{t+h} − x_t)², h = 0..size−1, of the model (defined for a random walk
    and flicker too): ½ Σ_{i,j=1}^{h} γ_y(i − j) of the differenced record's γ_y."""
    g = _differenced_autocovariance(model, floor, size)
    h = np.arange(size, dtype=np.float64)
    tau = np.arange(1, size, dtype=np.float64)
    s1 = np.concatenate([[0.0, 0.0], np.cumsum(g[1:])[: size - 2]])
    s2 = np.concatenate([[0.0, 0.0], np.cumsum(tau * g[1:])[: size - 2]])
    return 0.5 * (h * g[0] + 2 * (h * s1 - s2))


def _parameters(model: _Model) -> int:
    k = sum(PARAMETER_COUNT[n] for n in model.names)
    k += PARAMETER_COUNT["sinusoid"] * len(model.lines)
    return k + (PARAMETER_COUNT["startup_transient"] if model.transient is not None else 0)


def _named(model: _Model) -> list:
    """The model's effects by name (a low-pass of any order as `bandlimit`)."""
    names = [spectral.effect_name(n) for n in model.names]
    if model.lines:
        names.append("sinusoid")
    if model.transient is not None:
        names.append("startup_transient")
    return names
