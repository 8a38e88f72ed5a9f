"""Effects real sensors show in a static record, found by forward selection.

`select_sensor_noise` starts from the nominal model (white noise about a constant level)
and adds, one at a time, the effect whose evidence is largest, while it is significant:

- stochastic (fitted by the Whittle likelihood of `accel_jax._noise.spectral`):
  `gauss_markov`, `exp_cosine`, `random_walk`, `flicker` (bias instability, exact 1/f
  spectrum), `bandlimit` (the sensor's output low-pass, 2nd-order Butterworth);
- deterministic: `sinusoid` (a periodic line; added again for each further line, up to
  `MAX_LINES`) and `startup_transient` (a warm-up a e^{−t/τ} at the start of the record);
- `quantization`: the output lies on an ADC grid of step q (found from the values, not
  from the spectrum: the grid's white noise q²/12 is indistinguishable from white noise
  there). It is named when the grid noise is at least `QUANTIZATION_SHARE` of the white
  variance; a finer grid is reported as the record's resolution only.

**Evidence** of an addition: 2 ln B ≈ 2 Δ ln L − k ln J (k the effect's parameter count,
J the record's periodogram bins), Δ ln L the whole record's Whittle likelihood gain with
the parameters fitted on the training part (the first 2/3) alone: the held-out part (the
last third) adds its gain at those parameters, so an addition that fitted the training
part's noise loses there. It is added when that is at least `EVIDENCE` and the **held-out
check** does not refuse it: the held-out part must not prefer the model without it
significantly (a paired z over its periodogram entries below −`HELD_OUT_Z`; requiring a
held-out gain outright refused flicker and random walks, whose evidence lies in the few
lowest bins a third of the record does not resolve). A start-up transient's 2 Δ ln L is
instead its exact time-domain likelihood ratio against the current noise model
(`_transient_test`: the spectral likelihood's taper gives the record's first samples
almost no weight), and it has no held-out check (it lies in the training part). A
transient that clears the bar is added before any noise component, whatever their
evidence: its decay's power lies in the lowest bins, which a random walk or flicker
fitted first takes for its own (should the backward check remove it, the selection runs
again in the order of the evidence alone).
**Backward check** (`_backward`): once nothing more is added, each effect is judged again
(by the same evidence) against the final model without it and the weakest below
`EVIDENCE` is removed, until every one stands (an effect added early can lose its evidence
once a later one is in). **Exchange** (`_exchanges`): each named Gauss–Markov, random walk,
flicker or exponential-cosine process is tried against the first three in its place; one
better by `EVIDENCE` replaces it,
one within `EVIDENCE` either way is reported as a tie (the record cannot tell them apart).
**Explained fraction** after each step: the share of the
nominal model's excess Whittle deviance on the held-out part, Σ (r − ln r − 1) − γJ with
r = I/f (zero in expectation for the right model), that the model removes. What the final
model leaves is **unexplained** when its held-out excess deviance stands more than
`UNEXPLAINED_Z` standard errors (√((π²/6 − 1) J)) above zero, when impulsive events
(`_bursts`) or a linear drift no named effect makes (`_drift`) are found, or when the
level shifts (`_level_shift`: a step in the level, which the periodogram takes for a
random walk, found in the time domain against the final model's own wander), when the
output sits on a rail (`detect_saturation`: a range limit that clips the record), when the
residual's values are far from Gaussian (`_non_gaussian`), or when its spectrum changes
between the record's halves (`_spectral_change`: a line that moves, a vibration that
starts or stops). A shift
is taken out of the record and the selection run again on what is left (up to
`MAX_LEVEL_SHIFTS`), so that no effect of the library takes the credit for it.

Float64, host-driven (NumPy); the fits are one jitted, vmapped Whittle fit per record
length (`accel_jax._noise.spectral`).
"""

from __future__ import annotations

import dataclasses
import math
import os
import statistics
from concurrent.futures import ThreadPoolExecutor

import jax
import jax.numpy as jnp
import numpy as np

from . import spectral
from .record import _sample_interval, _validate_record

EVIDENCE = 10.0
"""2 ln B an effect needs to be added ("strong" on the Kass–Raftery scale)."""

MAX_LINES = 4
MAX_STEPS = 8
QUANTIZATION_SHARE = 0.01
"""The grid's noise q²/12 must be at least this share of the record's short-term variance
(half the variance of its first difference) to be named."""

UNEXPLAINED_Z = 4.0
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
    "bandlimit": 1,
    "sinusoid": 3,
    "startup_transient": 2,
}


@dataclasses.dataclass(frozen=True)
class SensorNoiseSelection:
    """What `select_sensor_noise` found.

    **Fields:** `effects` the named effects in the order added (`quantization` last when
    named); `unexplained` whether the final model leaves a significant held-out misfit;
    `steps` one dict per forward step (the model, its 2 ln B, held-out gain and the
    explained fraction; the steps of effects the backward check removed are left out, and
    the last step's fraction and z are the final model's); `parameters` the final model's
    physical parameters by effect; `held_out` the final model's held-out deviance test
    (with `removed`: the effects the backward check took out and their 2 ln B then;
    `exchanged`: the low-frequency effects the exchange replaced, and by what — their
    steps then name the substitute, with `replaced` the effect whose evidence they show;
    `ties`: each named low-frequency effect another fits as well, within the bar;
    `bursts`: impulsive events; `non_gaussian`: the residual's skewness and excess
    kurtosis and their z (`_non_gaussian`; `significant` makes the record unexplained);
    `spectral_change`: the residual's spectrum compared between the record's halves, the
    band that changes most and its p (`_spectral_change`; `significant` makes the record
    unexplained);
    `drift`, `drifting`: the level's linear drift and whether it is one no named effect
    makes; `level_shifts`: the steps in the level found and taken
    out (time, size, their z, the held-out z and effects with the step still in),
    `level_shift_test`: the last test (None for records under 32 samples), and
    `more_level_shifts` when one more stood than `MAX_LEVEL_SHIFTS`; `saturation`: the
    rails the record's values pile up on, `detect_saturation`);
    `quantization` the grid found (or None); `verdict` the effects joined by '+' ('none'
    when nothing is named and nothing is left, 'unexplained' alone when nothing is named
    but the misfit stays).
    """

    effects: tuple
    unexplained: bool
    steps: list
    parameters: dict
    held_out: dict
    quantization: dict | None
    sample_interval: float
    n_samples: int

    @property
    def verdict(self) -> str:
        names = list(self.effects)
        if self.unexplained:
            names.append("unexplained")
        return "+".join(names) if names else "none"


# --------------------------------------------------------------------------------------
# Quantisation grid
# --------------------------------------------------------------------------------------


def detect_quantization(x: np.ndarray) -> dict | None:
    """The ADC grid the values lie on: the smallest spacing q₀ of the distinct values,
    accepted when every distinct value sits within q₀/10 of a multiple of it from the
    lowest, and refined by least squares of the values on their grid indices. None when the
    values are continuous (more than half of them distinct) or fit no grid."""
    x = np.asarray(x, np.float64)
    u = np.unique(x)
    if u.size < 3 or u.size > x.size // 2:
        return None
    scale = max(float(np.max(np.abs(u))), 1e-300)
    gaps = np.diff(u)
    gaps = gaps[gaps > 1e-12 * scale]
    if gaps.size == 0:
        return None
    q0 = float(np.min(gaps))
    k = np.round((u - u[0]) / q0)
    if np.max(np.abs(u - u[0] - k * q0)) > 0.1 * q0:
        return None
    design = np.stack([np.ones_like(k), k], axis=1)
    (offset, q), *_ = np.linalg.lstsq(design, u, rcond=None)
    misfit = float(np.max(np.abs(design @ np.array([offset, q]) - u)))
    return {"step": float(q), "offset": float(offset), "levels": int(u.size), "misfit": misfit}


SATURATION_MIN = 5
"""Samples at an extreme of the record that, piled there, make it a rail."""


def detect_saturation(x: np.ndarray, grid: dict | None = None) -> list:
    """Rails: an extreme of the record (its largest or its smallest value) holding a pile of
    samples that no unimodal noise puts there: the range limit of an ADC or of the sensor's
    electronics, outside the library (clipping flattens the record's distribution, cuts its
    variance and biases every fitted parameter). Continuous values (`grid` None): the
    extreme value repeated at least `SATURATION_MIN` times (continuous noise repeats no
    value). On an output grid (`detect_quantization`, judged from 4 levels on): the extreme
    level holds at least `SATURATION_MIN` samples and more than twice the level next inside
    it — a unimodal noise's tail falls outward, a rail gathers the whole tail beyond it. (On
    a coarse grid a rail close to the mean is not seen: its pile is then no larger than a
    level's share.) Returns one entry per side found: {"side": "high" | "low", "level",
    "count", "fraction", "inner_count" (None for continuous values)}."""
    x = np.asarray(x, np.float64)
    if x.ndim != 1 or x.size == 0 or not np.all(np.isfinite(x)):
        raise ValueError(
            "detect_saturation: the record must be a non-empty 1-D array of finite values"
        )
    found = []
    for side, sign in (("high", 1.0), ("low", -1.0)):
        y = sign * x
        top = float(np.max(y))
        if grid is None:
            count = int(np.sum(y == top))
            inner = None
        else:
            q = grid["step"]
            if grid["levels"] < 4 or not q > 0:
                continue
            count = int(np.sum(y > top - q / 2))
            inner = int(np.sum((y > top - 1.5 * q) & (y <= top - q / 2)))
        if count >= SATURATION_MIN and count > 2 * (inner or 0):
            found.append(
                {
                    "side": side,
                    "level": sign * top,
                    "count": count,
                    "fraction": count / x.size,
                    "inner_count": inner,
                }
            )
    return found


def saturation_sentence(rail: dict, unit: str = "g") -> str:
    """One rail of `held_out["saturation"]` in words (the CLI and the diagnosis alike)."""
    pile = (
        "at exactly that value"
        if rail["inner_count"] is None
        else f"against {rail['inner_count']} on the output level next inside it"
    )
    return (
        f"the output sits on a rail at {rail['level']:.6g} {unit} ({rail['count']} samples, "
        f"{100 * rail['fraction']:.2g} % of the record, {pile}): clipped by a range limit, "
        "outside the library; the fitted noise is biased low"
    )


def non_gaussian_sentence(found: dict) -> str:
    """`held_out["non_gaussian"]` in words, when significant (the CLI and the diagnosis)."""
    g2, z2 = found["excess_kurtosis"], found["excess_kurtosis_z"]
    g1, z1 = found["skewness"], found["skewness_z"]
    if abs(z2) >= abs(z1):
        what = f"excess kurtosis {g2:+.2f}, {abs(z2):.0f} standard errors from a Gaussian's"
        cause = (
            "two or more levels, as a random telegraph (popcorn) noise makes"
            if g2 < 0
            else "heavier tails than any Gaussian effect"
        )
    else:
        what = f"skewness {g1:+.2f}, {abs(z1):.0f} standard errors from a Gaussian's"
        cause = "an asymmetric distribution"
    return (
        f"the residual is not Gaussian ({what}): {cause}, outside the library; the fitted "
        "spectrum may be right, its Gaussian likelihood is not"
    )


def spectral_change_sentence(found: dict, duration_s: float) -> str:
    """`held_out["spectral_change"]` in words, when significant (the CLI and the diagnosis)."""
    low, high = found["band_Hz"]
    factor = math.exp(found["log_ratio_second_to_first"])
    half = duration_s / 2
    return (
        f"the spectrum changes during the record: {low:.3g}–{high:.3g} Hz carries "
        f"{factor:.2g} times the power after {half:.4g} s that it carried before (family-wise "
        f"p {found['p_family']:.1g}): a line or resonance that moves, a vibration that starts "
        "or stops; every model of the library is stationary, outside the library"
    )


# --------------------------------------------------------------------------------------
# Deterministic components
# --------------------------------------------------------------------------------------


def _line_design(t, f):
    return np.stack([np.cos(2 * np.pi * f * t), np.sin(2 * np.pi * f * t), np.ones_like(t)], 1)


LINE_BLOCK = 32
"""Samples per block of the demodulated record in the line's frequency search."""


def _fit_line(r: np.ndarray, t: np.ndarray, f0: float, width: float) -> dict:
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
    return {"frequency_Hz": float(f), "cos": float(coef[0]), "sin": float(coef[1])}


def _line_signal(line: dict, t: np.ndarray) -> np.ndarray:
    w = 2 * np.pi * line["frequency_Hz"] * t
    return line["cos"] * np.cos(w) + line["sin"] * np.sin(w)


def _transient_signal(transient: dict, t: np.ndarray) -> np.ndarray:
    return transient["amplitude"] * np.exp(-(t - t[0]) / transient["time_constant_s"])


# --------------------------------------------------------------------------------------
# The forward selection
# --------------------------------------------------------------------------------------


@dataclasses.dataclass
class _Model:
    names: tuple
    lines: tuple
    transient: dict | None
    z: np.ndarray
    train: float
    held: float
    held_terms: np.ndarray
    converged: bool


class _Record:
    def __init__(self, x, dt):
        self.x = x
        self.dt = dt
        self.n = x.size
        self.split = int(round((1 - HELD_OUT_FRACTION) * self.n))
        self.t = np.arange(self.n) * dt
        self.variance = float(np.var(np.diff(x[: self.split]))) / 2
        self._grams = {}

    def residual(self, lines, transient):
        r = self.x - np.mean(self.x[: self.split])
        for line in lines:
            r = r - _line_signal(line, self.t)
        if transient is not None:
            r = r - _transient_signal(transient, self.t)
        return r

    def grams(self, lines, transient):
        key = repr((lines, transient))
        if key not in self._grams:
            r = self.residual(lines, transient)
            self._grams[key] = (
                spectral.periodogram(r[: self.split]),
                spectral.periodogram(r[self.split :]),
            )
        return self._grams[key]


def _evaluate(record, floor, names, lines, transient, parent=None) -> _Model:
    train, held = record.grams(lines, transient)
    parent_z, parent_names = (parent.z, parent.names) if parent is not None else (None, ())
    z, log_lik, ok = spectral.fit_structure(
        list(names), train, floor, record.variance, parent_z, parent_names
    )
    mask = jnp.asarray(spectral._mask(names))
    terms = np.asarray(spectral.whittle_terms(jnp.asarray(z), mask, held, jnp.asarray(floor)))
    held_lik = float(np.sum(terms))
    return _Model(tuple(names), tuple(lines), transient, z, log_lik, held_lik, terms, ok)


def _cores() -> int:
    try:
        return len(os.sched_getaffinity(0))  # what this process may use (a pinned job: 1)
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def _evaluate_many(record, floor, specs: list) -> list:
    """`_evaluate` of each spec (names, lines, transient, parent), in order. Independent
    fits run on as many threads as the process has cores: a fit is one XLA call that runs
    on one core and releases the GIL (the first forward step of a 10⁶-sample record 3.3 s
    → 1.9 s on the 2-core machine). The same fits, the same results, in either case."""
    workers = min(len(specs), _cores())
    if workers < 2:
        return [_evaluate(record, floor, *spec) for spec in specs]

    def one(spec):
        with jax.enable_x64(True):  # thread-local: each worker sets it again
            return _evaluate(record, floor, *spec)

    with ThreadPoolExecutor(workers) as pool:
        return list(pool.map(one, specs))


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
"""The start-up transient is tested on the first `TRANSIENT_WINDOW` first differences of
the record (time constants up to a quarter of that)."""

TRANSIENT_TAUS = 24


def _differenced_autocovariance(model: _Model, floor: float, size: int) -> np.ndarray:
    """γ_y(h), h = 0..size−1, of the model's differenced record y = Δx: the inverse Fourier
    transform of its spectral density f_y (`spectral.spectrum`) on a grid of 8·size."""
    grid = 8 * size
    w = 2 * np.pi * np.arange(grid) / grid
    folded = np.minimum(w, 2 * np.pi - w)
    f = np.asarray(
        spectral.spectrum(
            jnp.asarray(model.z), jnp.asarray(spectral._mask(model.names)), folded, floor
        )
    )
    return np.real(np.fft.ifft(f))[:size]


def _innovations(gamma: np.ndarray, vectors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The one-step prediction errors of the columns of `vectors` under the stationary
    autocovariance γ (the Durbin–Levinson recursion: each sample predicted from all the
    earlier ones of the window) and their variances D_k; Σ_k e_k e'_k/D_k is then the exact
    Gaussian inner product uᵀ C⁻¹ v."""
    size = gamma.size
    out = np.empty_like(vectors)
    variance = np.empty(size)
    phi = np.zeros(0)
    d = float(gamma[0])
    out[0] = vectors[0]
    variance[0] = d
    for k in range(1, size):
        kappa = (gamma[k] - phi @ gamma[k - 1 : 0 : -1]) / d if k > 1 else gamma[1] / d
        phi = np.concatenate([phi - kappa * phi[::-1], [kappa]])
        d = d * (1 - kappa * kappa)
        if not d > 0:
            return out[:k], variance[:k]
        out[k] = vectors[k] - phi[::-1] @ vectors[:k]
        variance[k] = d
    return out, variance


def _transient_test(r: np.ndarray, dt: float, model: _Model, floor: float) -> dict:
    """The start-up transient a e^{−t/τ} that best explains the start of r, and its
    evidence 2 ln Λ against `model`'s noise, by generalised least squares in the time
    domain: on the first `TRANSIENT_WINDOW` first differences y of r (the difference takes
    the level out and makes a random walk stationary), the exact Gaussian likelihood ratio
    of y − a Δh_τ − b against y − b under the model's autocovariance of y (Durbin–Levinson;
    b, a constant rate of the level, is a nuisance: a linear drift is not a transient),
    2 ln Λ = (Δhᵀ C⁻¹ y)² / (Δhᵀ C⁻¹ Δh) with b projected out of both, maximised over a
    geometric grid of τ from 2Δ to a quarter of the window.

    The spectral (Whittle) likelihood cannot judge a transient: its taper gives the first
    samples of the record, where the transient lives, almost no weight."""
    y = np.diff(r)[:TRANSIENT_WINDOW]
    size = y.size
    taus = np.geomspace(2 * dt, max(size * dt / 4, 3 * dt), TRANSIENT_TAUS)
    k = np.arange(size + 1) * dt
    templates = np.diff(np.exp(-k[:, None] / taus[None, :]), axis=0)
    gamma = _differenced_autocovariance(model, floor, size)
    columns = np.concatenate([y[:, None], np.ones((size, 1)), templates], axis=1)
    e, d = _innovations(gamma, columns)
    weighted = e / d[:, None]
    gram = weighted.T @ e  # the C⁻¹ inner products of every pair of columns
    # the level's drift (a constant mean of y) taken out: a ramp is not a transient
    drift = gram[1, 1]
    cross = gram[2:, 0] - gram[2:, 1] * gram[1, 0] / drift
    energy = np.diag(gram)[2:] - gram[2:, 1] ** 2 / drift
    z2 = np.where(energy > 0, cross**2 / np.where(energy > 0, energy, 1.0), 0.0)
    i = int(np.argmax(z2))
    return {
        "evidence": float(z2[i]),
        "time_constant_s": float(taus[i]),
        "amplitude": float(cross[i] / energy[i]) if energy[i] > 0 else 0.0,
    }


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


def _physical(model: _Model, dt: float, floor: float) -> dict:
    z = model.z
    out = {"white_sigma": math.sqrt(math.exp(z[0]))}
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
    if "bandlimit" in model.names:
        corner = float(jax.nn.sigmoid(z[8])) * math.pi / 2
        out["bandlimit"] = {"corner_Hz": corner / (math.pi * dt)}
    if model.lines:
        out["sinusoid"] = [
            {
                "frequency_Hz": line["frequency_Hz"],
                "amplitude": math.hypot(line["cos"], line["sin"]),
            }
            for line in model.lines
        ]
    if model.transient is not None:
        out["startup_transient"] = dict(model.transient)
    out["post_filter_floor_variance"] = floor
    return out


def _explained(dev: dict, nominal: dict) -> float:
    """The share of the nominal model's held-out excess deviance that a model removes."""
    if not nominal["excess_deviance"] > 0:
        return 0.0
    return min(max(1 - dev["excess_deviance"] / nominal["excess_deviance"], 0.0), 1.0)


def _backward(rec, floor, model: _Model, log_j: float, evidence: float):
    """The backward check of the forward selection: each effect of the final model is
    judged again against the final model without it (a stochastic effect by its Whittle
    2 ln B on the whole record, `_evidence`, the start-up transient by its time-domain test against
    the reduced noise model); the weakest that falls below `evidence` is removed and the
    check repeats. An effect added early can lose its evidence once a later one is in: a
    random walk taken for the low-frequency power of a start-up transient, or a transient
    seen in the start of a record whose wandering level was not yet modelled.

    Returns (model, removed: [{"effect", "evidence"}])."""
    removed = []
    while True:
        weakest = None
        specs = []
        for name in model.names:
            names = tuple(n for n in model.names if n != name)
            parent = dataclasses.replace(model, names=names)
            specs.append((names, model.lines, model.transient, parent))
        for name, reduced in zip(model.names, _evaluate_many(rec, floor, specs), strict=True):
            score = _evidence(model, reduced, PARAMETER_COUNT[name], log_j)
            if weakest is None or score < weakest[0]:
                weakest = (score, name, reduced)
        if model.transient is not None:
            r = rec.residual(model.lines, None)
            found = _transient_test(r[: rec.split], rec.dt, model, floor)
            score = found["evidence"] - PARAMETER_COUNT["startup_transient"] * log_j
            if weakest is None or score < weakest[0]:
                reduced = _evaluate(rec, floor, model.names, model.lines, None, model)
                weakest = (score, "startup_transient", reduced)
        if weakest is None or weakest[0] >= evidence:
            return model, removed
        removed.append({"effect": weakest[1], "evidence": float(weakest[0])})
        model = weakest[2]


LOW_FREQUENCY = ("gauss_markov", "random_walk", "flicker")
"""The effects that put their power at the lowest frequencies: on a record a few of their
time scales long, one can stand in for another."""

EXCHANGED = (*LOW_FREQUENCY, "exp_cosine")
"""The named effects the exchange tries the `LOW_FREQUENCY` ones in place of: an
exponential-cosine process too can stand in for a low-frequency one (its oscillation
frequency fitted near 0 it is a Gauss–Markov process; harness record 166663425, flicker
with a line, took it first, before the line was in and while the line's power favoured a
peaked spectrum, and kept it)."""


def _exchanges(rec, floor, model: _Model, log_j: float, evidence: float):
    """Each named effect of `EXCHANGED` against each unnamed `LOW_FREQUENCY` one in its
    place (the rest of the model kept, the substitute's fit started from the model's
    optimum): 2 ln B of the named effect over the substitute, 2 Δ ln L − (k − k') ln J on
    the whole record as in the forward selection. A substitute that beats the named effect by `evidence` or
    more replaces it (the forward path added the first that stood, not the best: a random
    walk with a start-up transient can look like flicker until the transient is in), and
    the exchange repeats; one within `evidence` either way is reported as a tie: the
    record cannot tell the two apart.

    Returns (model, exchanged: [{"effect", "by", "evidence"}], ties: [{"effect",
    "alternative", "evidence"}])."""
    exchanged = []
    for _ in range(len(EXCHANGED) + 1):
        ties, best = [], None
        pairs, specs = [], []
        for name in model.names:
            if name not in EXCHANGED:
                continue
            rest = tuple(n for n in model.names if n != name)
            for other in LOW_FREQUENCY:
                if other in model.names:
                    continue
                names = tuple(other if n == name else n for n in model.names)
                parent = dataclasses.replace(model, names=rest)
                pairs.append((name, other, parent))
                specs.append((names, model.lines, model.transient, parent))
        for (name, other, parent), alt in zip(
            pairs, _evaluate_many(rec, floor, specs), strict=True
        ):
            score = (
                2 * ((model.train + model.held) - (alt.train + alt.held))
                - (PARAMETER_COUNT[name] - PARAMETER_COUNT[other]) * log_j
            )
            if score <= -evidence and _held_out_z(alt, parent) >= -HELD_OUT_Z:
                if best is None or score < best[0]:
                    best = (score, alt, name, other)
            elif score < evidence:
                ties.append(
                    {
                        "effect": name,
                        "alternative": other,
                        "evidence": float(score),
                        "bar": float(evidence),
                    }
                )
        if best is None:
            return model, exchanged, ties
        score, model, name, other = best
        exchanged.append({"effect": name, "by": other, "evidence": float(-score)})
    ties = [t for t in ties if t["effect"] in model.names and t["alternative"] not in model.names]
    return model, exchanged, ties


def select_sensor_noise(
    record, sample_interval: float, *, evidence: float = EVIDENCE, max_lines: int = MAX_LINES
) -> SensorNoiseSelection:
    """Forward selection of the effects a static record shows (module docstring).

    **Arguments:** `record` x (n ≥ 64 samples, any unit); `sample_interval` Δ [s];
    `evidence` the 2 ln B an addition needs; `max_lines` the most periodic lines.

    **Returns:** a `SensorNoiseSelection`. Parameters are in the record's unit. Bad input
    raises `ValueError`.
    """
    with jax.enable_x64(True):
        x = np.asarray(_validate_record("select_sensor_noise", record, min_samples=64), np.float64)
        _sample_interval("select_sensor_noise", sample_interval)
        dt = float(sample_interval)
        shifts = []
        grid = detect_quantization(x)
        record_values = x  # as given: steps taken out below would move its extremes
        selection, model, floor, residual = _select(x, dt, evidence, max_lines, grid)
        for attempt in range(MAX_LEVEL_SHIFTS + 1):
            found = _level_shift(residual, dt, model, floor)
            selection.held_out["level_shift_test"] = found
            if found is None or not found["significant"]:
                break
            if _at_burst(found, selection):  # an impulsive event, reported as such
                break
            if attempt == MAX_LEVEL_SHIFTS:  # one more than taken out: said, not hidden
                selection.held_out["more_level_shifts"] = True
                break
            # Outside the library: taken out of the record, and the selection run again on
            # what is left, so that no effect takes the credit for the step.
            size = found["size"]
            if grid is not None:  # a whole number of grid steps keeps the record on its grid
                size = round(size / grid["step"]) * grid["step"]
            taken_out = size != 0 and math.isfinite(size)  # not under half a grid step
            near = next(
                (
                    sh
                    for sh in shifts
                    if abs(sh["index"] - found["index"]) * dt
                    <= max(sh["size_window_s"], found["size_window_s"])
                ),
                None,
            )
            if near is not None:  # what the first estimate of that step left
                near["size"] += size if taken_out else 0.0
            else:
                shifts.append(
                    {
                        **{
                            k: found[k]
                            for k in ("time_s", "index", "z", "window_s", "size_window_s")
                        },
                        "size": size if taken_out else found["size"],
                        "taken_out": bool(taken_out),
                        # the held-out misfit with the step still in, beside the final one
                        "held_out_z_with_it": selection.held_out["z"],
                        "effects_with_it": list(selection.effects),
                    }
                )
            if not taken_out:
                break
            corrected = x - size * (np.arange(x.size) >= found["index"])
            try:
                rerun = _select(corrected, dt, evidence, max_lines, grid)
            except ValueError:  # nothing left but the steps (a record without noise)
                break
            x = corrected
            selection, model, floor, residual = rerun
        if not shifts and "random_walk" in model.names:
            test, swapped = _shift_in_place_of_walk(
                x, dt, evidence, max_lines, grid, model, floor, selection
            )
            selection.held_out["step_or_walk"] = test
            if swapped is not None:
                shift, rerun = swapped
                shift["held_out_z_with_it"] = selection.held_out["z"]
                shift["effects_with_it"] = list(selection.effects)
                selection, model, floor, residual = rerun
                selection.held_out["level_shift_test"] = _level_shift(residual, dt, model, floor)
                selection.held_out["step_or_walk"] = test
                shifts.append(shift)
        selection.held_out["level_shifts"] = shifts
        rails = detect_saturation(record_values, grid)
        selection.held_out["saturation"] = rails
        if shifts or selection.held_out.get("more_level_shifts") or rails:
            selection = dataclasses.replace(selection, unexplained=True)
        return selection


def _select(
    x: np.ndarray,
    dt: float,
    evidence: float,
    max_lines: int,
    grid: dict | None,
    transient_first: bool = True,
):
    """The forward selection on x, whose output grid is `grid` (`detect_quantization`;
    a step taken out is a whole number of its steps); returns (selection, final model,
    floor, residual).

    With `transient_first`, a start-up transient that clears the bar is added before a
    noise component that scores higher; should the backward check then remove it (the
    start of a random walk looks like a decay against white noise alone, and the noise
    fitted after a false transient is not the one fitted first: harness record
    128256395, a walk, was named Gauss–Markov), the selection is run again in the
    order of the evidence alone."""
    rec = _Record(x, dt)
    if not rec.variance > (1e-10 * float(np.max(np.abs(x)))) ** 2:
        raise ValueError(
            "select_sensor_noise: the record's first differences are constant over its "
            "training part (a pure ramp or a staircase of one step): no noise to model."
        )
    floor = grid["step"] ** 2 / 12 if grid else 1e-9 * rec.variance
    model = _evaluate(rec, floor, (), (), None)
    nominal_dev = _held_out_deviance(rec, floor, model)
    steps = [
        {
            "model": "white",
            "added": None,
            "evidence": 0.0,
            "held_out_gain": 0.0,
            "explained_fraction": 0.0,
            "held_out_z": nominal_dev["z"],
        }
    ]
    train_gram, held_gram = rec.grams((), None)
    log_j = math.log(train_gram.n_bins + held_gram.n_bins)
    promoted = False  # a transient added before a noise component that scored higher
    for _ in range(MAX_STEPS):
        labels, specs = [], []
        for name in spectral.COMPONENTS:
            if name not in model.names:
                labels.append(name)
                specs.append(((*model.names, name), model.lines, model.transient, model))
        if len(model.lines) < max_lines:
            f0, width = _standardised_peak(rec, floor, model)
            r = rec.residual(model.lines, model.transient)
            line = _fit_line(r[: rec.split], rec.t[: rec.split], f0, width)
            labels.append("sinusoid")
            specs.append((model.names, (*model.lines, line), model.transient, model))
        trials = list(zip(labels, _evaluate_many(rec, floor, specs), strict=True))
        scored = [
            (_evidence(m, model, PARAMETER_COUNT[name], log_j), name, m) for name, m in trials
        ]
        if model.transient is None:
            r = rec.residual(model.lines, None)
            found = _transient_test(r[: rec.split], dt, model, floor)
            transient = {k: found[k] for k in ("time_constant_s", "amplitude")}
            score = found["evidence"] - PARAMETER_COUNT["startup_transient"] * log_j
            score = score if math.isfinite(score) else -math.inf
            # the noise refit without the transient only when it can be accepted
            refit = None
            if score >= evidence:
                refit = _evaluate(rec, floor, model.names, model.lines, transient, model)
                # Tested again against that refit: the current model's noise took in
                # the transient's power (a white variance inflated by it makes the
                # transient look small beside a slow Gauss–Markov fitted to it).
                found = _transient_test(r[: rec.split], dt, refit, floor)
                transient = {k: found[k] for k in ("time_constant_s", "amplitude")}
                score = found["evidence"] - PARAMETER_COUNT["startup_transient"] * log_j
                refit = _evaluate(rec, floor, model.names, model.lines, transient, refit)
            scored.append((score, "startup_transient", refit))
        scored.sort(key=lambda s: -s[0])
        # A start-up transient that clears the bar goes in first: its decay puts power
        # in the lowest periodogram bins, where a random walk or flicker fitted before it
        # takes that power for its own and leaves the transient under the bar (harness
        # record 1079240685: flicker 0.38 mg + an 11 mg, τ 4.5 s warm-up was named a
        # random walk alone). The backward check removes it again should the noise
        # added after it explain it.
        top = scored[0][1] if scored else None
        if transient_first:
            scored.sort(key=lambda s: not (s[1] == "startup_transient" and s[0] >= evidence))
        accepted = None
        for score, name, m in scored:
            if score < evidence:
                break
            # A start-up transient lies in the training part (τ ≤ a quarter of
            # `TRANSIENT_WINDOW` samples): the held-out part has nothing to check, and
            # the refit of the noise without it moves the held-out likelihood by
            # sampling error alone. Its time-domain test is its evidence.
            if name == "startup_transient" or _held_out_z(m, model) >= -HELD_OUT_Z:
                accepted = (score, name, m)
                break
        if accepted is None:
            break
        score, name, new = accepted
        promoted = promoted or (name == "startup_transient" and top != name)
        dev = _held_out_deviance(rec, floor, new)
        fraction = _explained(dev, nominal_dev)
        steps.append(
            {
                "model": "+".join(["white", *_named(new)]),
                "added": name,
                "evidence": float(score),
                "held_out_gain": float(new.held - model.held),
                "held_out_check_z": (
                    None if name == "startup_transient" else _held_out_z(new, model)
                ),
                "explained_fraction": float(fraction),
                "held_out_z": dev["z"],
            }
        )
        model = new
    model, removed = _backward(rec, floor, model, log_j, evidence)
    if promoted and model.transient is None:
        return _select(x, dt, evidence, max_lines, grid, transient_first=False)
    kept_before = set(_named(model))
    model, exchanged, ties = _exchanges(rec, floor, model, log_j, evidence)
    if exchanged:  # the substitute may leave another effect without evidence
        model, again = _backward(rec, floor, model, log_j, evidence)
        removed += again
    if removed or exchanged:
        swap = {}  # the effect the forward path added → the one now in its place
        for e in exchanged:
            origin = next((k for k, v in swap.items() if v == e["effect"]), e["effect"])
            swap[origin] = e["by"]
        kept = set(_named(model))
        steps = [
            steps[0],
            *(
                st
                for st in steps[1:]
                if st["added"] in kept_before and swap.get(st["added"], st["added"]) in kept
            ),
        ]
        for st in steps[1:]:
            tokens = [
                swap.get(t, t) for t in st["model"].split("+") if t == "white" or t in kept_before
            ]
            st["model"] = "+".join(t for t in tokens if t == "white" or t in kept)
            if st["added"] in swap:  # its evidence is the replaced effect's
                st["replaced"], st["added"] = st["added"], swap[st["added"]]
        dev = _held_out_deviance(rec, floor, model)
        steps[-1] = {
            **steps[-1],
            "explained_fraction": _explained(dev, nominal_dev),
            "held_out_z": dev["z"],
        }
    final = _held_out_deviance(rec, floor, model)
    final["removed"] = removed
    final["exchanged"] = exchanged
    final["ties"] = ties
    effects = _named(model)
    params = _physical(model, dt, floor)
    quantization = None
    share = grid["step"] ** 2 / 12 / rec.variance if grid is not None else 0.0
    if grid is not None:
        quantization = {**grid, "noise_share_of_white": float(share)}
        if share >= QUANTIZATION_SHARE:
            effects.append("quantization")
            params["quantization"] = {"step": grid["step"]}
    residual = rec.residual(model.lines, model.transient)
    bursts = _bursts(residual, dt)
    final["bursts"] = bursts
    gaussian = _non_gaussian(residual, share)
    final["non_gaussian"] = gaussian
    change = _spectral_change(residual, dt)
    final["spectral_change"] = change
    # The first difference makes a linear drift a constant, which the periodogram never
    # sees: test it in the time domain unless a wandering level was named.
    drift = _drift(residual, dt)
    final["drift"] = drift
    drifting = drift["t"] > DRIFT_T and not {"random_walk", "flicker"} & set(effects)
    final["drifting"] = bool(drifting)
    selection = SensorNoiseSelection(
        effects=tuple(effects),
        unexplained=bool(
            final["z"] > UNEXPLAINED_Z
            or bursts
            or drifting
            or gaussian["significant"]
            or change["significant"]
        ),
        steps=steps,
        parameters=params,
        held_out=final,
        quantization=quantization,
        sample_interval=dt,
        n_samples=int(x.size),
    )
    return selection, model, floor, residual


BURST_Z = 8.0
"""A first difference this many robust standard deviations from the median is an impulsive
event (a shock, a glitch): no Gaussian effect of the library makes one (probability
~1e-15 per sample)."""


def _bursts(r: np.ndarray, dt: float) -> list:
    """Impulsive events: runs of first differences beyond `BURST_Z` robust standard
    deviations (MAD), merged when closer than 10 samples; start, end [s] and the peak
    departure from the median level."""
    d = np.diff(r)
    centre = np.median(d)
    spread = 1.4826 * np.median(np.abs(d - centre))
    if not spread > 0:
        return []
    hits = np.flatnonzero(np.abs(d - centre) > BURST_Z * spread)
    if hits.size == 0:
        return []
    groups = np.split(hits, np.flatnonzero(np.diff(hits) > 10) + 1)
    level = np.median(r)
    out = []
    for g in groups[:20]:
        lo, hi = int(g[0]), int(g[-1]) + 1
        out.append(
            {
                "start_s": lo * dt,
                "end_s": hi * dt,
                "peak": float(np.max(np.abs(r[lo : hi + 1] - level))),
            }
        )
    return out


NON_GAUSSIAN_Z = 6.0
NON_GAUSSIAN_SIZE = 0.2
"""The residual is non-Gaussian when its skewness or excess kurtosis stands more than
`NON_GAUSSIAN_Z` standard errors from zero and is at least `NON_GAUSSIAN_SIZE` in size (the
second bar keeps a long record from being called non-Gaussian for a departure no user
would act on)."""


def _non_gaussian(r: np.ndarray, grid_share: float) -> dict:
    """The marginal distribution of the residual r against a Gaussian one: its skewness g₁
    and excess kurtosis g₂, with standard errors for a stationary Gaussian process of r's
    autocorrelation ρ (var g₁ ≈ 6 Σ_h ρ(h)³/n, var g₂ ≈ 24 Σ_h ρ(h)⁴/n, the sums over
    |h| < n/4 of the sample autocorrelation: a correlated record, a slow Gauss–Markov or a
    walk, has far fewer independent values than samples, and a walk's residual is never
    called non-Gaussian). A random telegraph (popcorn) noise, whose Lorentzian spectrum a
    Gauss–Markov process matches exactly, shows here as a negative excess kurtosis (two
    levels); heavy tails too rare for `_bursts` as a positive one.

    Not tested where the output grid's noise is `QUANTIZATION_SHARE` of the white variance
    or more: a coarse grid's values are a discrete distribution whose kurtosis departs from
    a Gaussian's by itself (g₂ up to 0.34 on the harness's quantised records)."""
    if grid_share >= QUANTIZATION_SHARE or r.size < 64:
        return {"tested": False, "significant": False}
    c = r - r.mean()
    n = c.size
    v = float(c @ c) / n
    if not v > 0:
        return {"tested": False, "significant": False}
    g1 = float(np.mean(c**3)) / v**1.5
    g2 = float(np.mean(c**4)) / v**2 - 3.0
    size = 1 << int(math.ceil(math.log2(2 * n)))
    spectrum = np.fft.rfft(c, size)
    rho = np.fft.irfft(spectrum * np.conj(spectrum), size)[: n // 4] / (n * v)
    s3 = 1.0 + 2.0 * float(np.sum(rho[1:] ** 3))
    s4 = 1.0 + 2.0 * float(np.sum(rho[1:] ** 4))
    z1 = g1 / math.sqrt(6.0 * max(abs(s3), 1.0) / n)
    z2 = g2 / math.sqrt(24.0 * s4 / n)
    significant = (abs(z1) > NON_GAUSSIAN_Z and abs(g1) >= NON_GAUSSIAN_SIZE) or (
        abs(z2) > NON_GAUSSIAN_Z and abs(g2) >= NON_GAUSSIAN_SIZE
    )
    return {
        "tested": True,
        "skewness": g1,
        "skewness_z": z1,
        "excess_kurtosis": g2,
        "excess_kurtosis_z": z2,
        "significant": bool(significant),
    }


def detect_non_gaussian(x: np.ndarray, grid: dict | None = None) -> dict:
    """Whether a record's values are far from Gaussian (`_non_gaussian` on x itself): a
    random telegraph noise's two levels, heavy tails. `grid` is the record's output grid
    (`detect_quantization`), whose noise share of the short-term variance (half the variance
    of the first difference) decides whether the test is run at all. Returns {"tested",
    "significant"} and, when tested, "skewness", "skewness_z", "excess_kurtosis",
    "excess_kurtosis_z". The selection tests its residual in the same way
    (`held_out["non_gaussian"]`); this tests the raw record, so a line, a transient or a step
    in it counts against Gaussianity."""
    x = np.asarray(x, np.float64)
    if x.ndim != 1 or x.size == 0 or not np.all(np.isfinite(x)):
        raise ValueError(
            "detect_non_gaussian: the record must be a non-empty 1-D array of finite values"
        )
    return _non_gaussian(x, grid_noise_share(x, grid))


def grid_noise_share(x: np.ndarray, grid: dict | None) -> float:
    """The output grid's noise q²/12 as a share of the record's short-term variance (half
    the variance of its first difference); 0 without a grid, inf on a constant record."""
    if grid is None:
        return 0.0
    white = float(np.var(np.diff(x))) / 2 if np.size(x) > 1 else 0.0
    return grid["step"] ** 2 / 12 / white if white > 0 else math.inf


SPECTRAL_CHANGE_ALPHA = 1e-4
"""Family-wise false-alarm rate of the spectral-change test (`_spectral_change`)."""
SPECTRAL_CHANGE_SIZE = math.log(2.0)
"""A band's power must change by at least this log ratio (a factor 2) between the record's
halves: a long record is not called non-stationary for a change no user would act on."""
SPECTRAL_CHANGE_SCALES = (16, 64, 256)
"""Band widths of the scan, in (every other) periodogram bins of a half."""
SPECTRAL_CHANGE_SMOOTH = 33
"""Bins of the moving average of the halves' pooled periodogram by which each bin is
standardised (the bands then hold bins of equal expected size)."""


def _spectral_change(r: np.ndarray, dt: float) -> dict:
    """Whether the residual's spectrum changes between the record's first and second half
    (a line or resonance that moves with temperature, a vibration that starts or stops):
    every model of the library is stationary. Each half of the first difference (the
    difference takes a walk's wander and a level shift's step out), Hann-tapered; every
    other periodogram bin (the taper correlates neighbours), each divided by the moving
    average of both halves' (`SPECTRAL_CHANGE_SMOOTH` bins); then bands of
    `SPECTRAL_CHANGE_SCALES` bins: under a stationary spectrum the first half's share of a
    band's sum is Beta(k, k). Significant when the smallest two-sided p, Bonferroni over
    all bands, is below `SPECTRAL_CHANGE_ALPHA` and that band's power changes by a factor
    of at least 2 (`SPECTRAL_CHANGE_SIZE`).

    Calibration (NumPy records, 10⁴ samples): family-wise p < 0.05 in 5.7 % of 300 white,
    7.7 % of walk, 4 % of slow and 4.7 % of fast Gauss–Markov, 7 % of flicker records; on
    the 624 sensor-noise harness truths (lines and transients out) the smallest p is 0.002.
    A line sweeping 1 → 3 Hz at half the white σ is found (p ≈ 3e-10), at a quarter not."""
    from scipy import stats

    d = np.diff(np.asarray(r, np.float64))
    h = d.size // 2
    if h < 4 * (2 * SPECTRAL_CHANGE_SCALES[0] + 4):
        return {"tested": False, "significant": False}
    window = np.hanning(h)
    halves = [d[:h], d[h : 2 * h]]
    if not all(np.ptp(v) > 0 for v in halves):
        # A half without noise (a bare step, a constant stretch): no spectrum to compare.
        return {"tested": False, "significant": False}
    grams = [
        (np.abs(np.fft.rfft(window * (v - v.mean()))) ** 2)[2:-2:2] for v in halves
    ]
    kernel = np.ones(SPECTRAL_CHANGE_SMOOTH)
    pooled = np.convolve((grams[0] + grams[1]) / 2, kernel, mode="same")
    level = pooled / np.convolve(np.ones_like(grams[0]), kernel, mode="same")
    if not np.all(level > 0):
        return {"tested": False, "significant": False}
    a, b = grams[0] / level, grams[1] / level
    bands = []
    for k in SPECTRAL_CHANGE_SCALES:
        m = a.size // k
        if m < 2:
            continue
        sa = a[: m * k].reshape(m, k).sum(axis=1)
        sb = b[: m * k].reshape(m, k).sum(axis=1)
        share = sa / (sa + sb)
        p = 2 * np.minimum(stats.beta.cdf(share, k, k), stats.beta.sf(share, k, k))
        bands.append((k, p, np.log(sb / sa)))
    tests = sum(p.size for _, p, _ in bands)
    k, p, ratio = min(bands, key=lambda band: float(np.min(band[1])))
    j = int(np.argmin(p))
    family = min(float(p[j]) * tests, 1.0)
    # Kept bin i of a half is its periodogram bin 2 + 2i, at (2 + 2i) / (h Δt) Hz.
    low, high = (2 + 2 * j * k) / (h * dt), (2 + 2 * ((j + 1) * k - 1)) / (h * dt)
    return {
        "tested": True,
        "p_family": family,
        "band_Hz": (low, high),
        "log_ratio_second_to_first": float(ratio[j]),
        "bands_tested": int(tests),
        "significant": bool(
            family < SPECTRAL_CHANGE_ALPHA and abs(ratio[j]) >= SPECTRAL_CHANGE_SIZE
        ),
    }


def detect_spectral_change(x: np.ndarray, sample_interval: float = 1.0) -> dict:
    """Whether a record's spectrum changes between its first and second half
    (`_spectral_change` on x itself; the selection tests its residual in the same way,
    `held_out["spectral_change"]`). Returns {"tested", "significant"} and, when tested,
    "p_family", "band_Hz" (at `sample_interval` seconds per sample),
    "log_ratio_second_to_first" and "bands_tested". On the raw record a start-up transient counts as a change too."""
    x = np.asarray(x, np.float64)
    if x.ndim != 1 or x.size == 0 or not np.all(np.isfinite(x)):
        raise ValueError(
            "detect_spectral_change: the record must be a non-empty 1-D array of finite values"
        )
    if not (math.isfinite(sample_interval) and sample_interval > 0):
        raise ValueError("detect_spectral_change: sample_interval must be a positive number")
    return _spectral_change(x, sample_interval)


LEVEL_SHIFT_ALPHA = 1e-3
"""Family-wise false-alarm rate of the level-shift test (`_level_shift`)."""
MAX_LEVEL_SHIFTS = 3
SHIFT_SIZE_Z = 3.0
"""A shift's size, measured in the window where it is most precise under the model, must
be this many standard deviations from zero (a spike's falls as 1/w there)."""


def _variogram(model: _Model, floor: float, size: int) -> np.ndarray:
    """V(h) = ½ E (x_{t+h} − x_t)², h = 0..size−1, of the model (defined for a random walk
    and flicker too): ½ Σ_{i,j=1}^{h} γ_y(i − j) of the differenced record's γ_y."""
    g = _differenced_autocovariance(model, floor, size)
    h = np.arange(size, dtype=np.float64)
    tau = np.arange(1, size, dtype=np.float64)
    s1 = np.concatenate([[0.0, 0.0], np.cumsum(g[1:])[: size - 2]])
    s2 = np.concatenate([[0.0, 0.0], np.cumsum(tau * g[1:])[: size - 2]])
    return 0.5 * (h * g[0] + 2 * (h * s1 - s2))


def _haar_variance(v: np.ndarray, w: int) -> float:
    """Var(D) of D = mean(x[j : j+w]) − mean(x[j−w : j]) from the variogram V:
    (2/w²) [Σ_{h=1}^{2w−1} min(h, 2w−h) V(h) − 2 Σ_{h=1}^{w−1} (w−h) V(h)]
    (2σ²/w for white noise of variance σ²)."""
    h = np.arange(1, 2 * w)
    across = np.minimum(h, 2 * w - h) @ v[1 : 2 * w]
    within = (w - h[: w - 1]) @ v[1:w]
    return 2.0 / w**2 * float(across - 2 * within)


def _haar_scan(r: np.ndarray, v: np.ndarray, scales: list):
    """The largest |z_w(j)| of the Haar differences of r (less its least-squares line) at
    the dyadic windows `scales`, Var D_w from the variogram v; returns (best: {"z",
    "index", "size", "window"} or None, the cumulative sum of r less its mean)."""
    n = r.size
    # A linear drift moves every D_w(j) alike: it is taken out here (the drift check
    # judges it), and what stands out is localised.
    t = np.arange(n) - (n - 1) / 2
    raw = np.concatenate([[0.0], np.cumsum(r - np.mean(r))])
    c = raw - np.concatenate([[0.0], np.cumsum(t)]) * (t @ r) / (t @ t)
    best = None
    for w in scales:
        var = _haar_variance(v, w)
        if not var > 0:
            continue
        j = np.arange(w, n - w + 1)
        d = ((c[j + w] - c[j]) - (c[j] - c[j - w])) / w
        z = d / math.sqrt(var)
        i = int(np.argmax(np.abs(z)))
        if best is None or abs(z[i]) > abs(best["z"]):
            best = {"z": float(z[i]), "index": int(j[i]), "size": float(d[i]), "window": w}
    return best, raw


def _shift_critical_z(n: int, scales: list) -> float:
    """Bonferroni over Σ_w 2n/w nearly independent positions at `LEVEL_SHIFT_ALPHA`."""
    tests = sum(2 * n / w for w in scales)
    return statistics.NormalDist().inv_cdf(1 - LEVEL_SHIFT_ALPHA / (2 * tests))


SCREEN_BLOCKS = 64
"""The level-shift screen's widest window is n / `SCREEN_BLOCKS` (its robust scale then
rests on at least that many independent windows)."""


def level_shift_screen(x: np.ndarray) -> dict:
    """A model-free screen for a step in the level: the Haar differences D_w(j) of
    `_level_shift` at dyadic windows up to n/`SCREEN_BLOCKS`, each standardised by its own
    robust scale over j (1.4826 × the median absolute deviation): whatever noise the record
    has, a Gauss–Markov process's wander included, sets the scale, and a step, which moves
    D_w at only 2w of the n places, stands out of it. (The record's own variogram or Allan
    variance would not do: at the wide windows where a small step shows, the step itself
    inflates them.) For deciding whether the forward selection, whose level-shift test
    judges against the fitted model, must run; a screen, so a false trigger costs only that
    run. Returns {"z", "critical_z", "index", "significant"}."""
    x = np.asarray(x, np.float64)
    n = x.size
    scales = [1 << k for k in range(2, 40) if SCREEN_BLOCKS << k <= n]
    best = {"z": 0.0, "index": 0}
    t = np.arange(n) - (n - 1) / 2
    c = np.concatenate([[0.0], np.cumsum(x - np.mean(x))])
    c = c - np.concatenate([[0.0], np.cumsum(t)]) * (t @ x) / (t @ t)
    for w in scales:
        j = np.arange(w, n - w + 1)
        d = ((c[j + w] - c[j]) - (c[j] - c[j - w])) / w
        scale = 1.4826 * float(np.median(np.abs(d - np.median(d))))
        if not scale > 0:
            continue
        z = d / scale
        i = int(np.argmax(np.abs(z)))
        if abs(z[i]) > abs(best["z"]):
            best = {"z": float(z[i]), "index": int(j[i])}
    critical = _shift_critical_z(n, scales) if scales else math.inf
    return {**best, "critical_z": float(critical), "significant": bool(abs(best["z"]) > critical)}


def _level_shift(r: np.ndarray, dt: float, model: _Model, floor: float) -> dict | None:
    """The most significant shift of the level in the residual r against the model's own noise: the
    Haar statistic z_w(j) = D_w(j)/√Var D_w, D_w(j) the mean of the w samples after j less
    the mean of the w before, over every j and dyadic w from 4 to n/8, Var D_w from the
    model's variogram (so a random walk or flicker in the model widens it as it should), on
    r less its least-squares line. A step is concentrated in time, where a random walk of
    the same low-frequency power spreads its increments over the record: the periodogram
    cannot tell them apart, this can. Critical |z|: Bonferroni over Σ_w 2n/w nearly
    independent positions at `LEVEL_SHIFT_ALPHA`. Returns the largest |z| (time of the shift
    [s], its size, the window w Δ [s]) with the critical value, or None for a record too
    short (n < 32)."""
    n = r.size
    scales = [1 << k for k in range(2, 40) if 8 << k <= n]
    if not scales:
        return None
    v = _variogram(model, floor, 2 * scales[-1])
    best, raw = _haar_scan(r, v, scales)
    if best is None:
        return None
    # The size at that place from the window whose D has the least variance under the
    # model (the widest the record allows for white noise, shorter where the model
    # wanders): the window that located the step is picked for its |z|, which biases its
    # own D upwards.
    j = best["index"]
    var, w = min((_haar_variance(v, w), w) for w in scales if w <= min(j, n - j))
    # (on r as it is: the line taken out above would bias a step's size)
    size = float(((raw[j + w] - raw[j]) - (raw[j] - raw[j - w])) / w)
    critical = _shift_critical_z(n, scales)
    size_z = size / math.sqrt(var)
    return {
        "z": best["z"],
        "critical_z": float(critical),
        "time_s": j * dt,
        "index": j,
        "size": size,
        # A step holds its size in every window; a spike's D falls as 1/w: the size must
        # stand in its own window too (a shape check, `SHIFT_SIZE_Z`; the false-alarm rate
        # is the located |z|'s). A spike is a burst (`_bursts`), not a shift.
        "size_z": float(size_z),
        "significant": bool(abs(best["z"]) > critical and abs(size_z) > SHIFT_SIZE_Z),
        "window_s": best["window"] * dt,
        "size_window_s": w * dt,
    }


def _parameters(model: _Model) -> int:
    k = sum(PARAMETER_COUNT[n] for n in model.names)
    k += PARAMETER_COUNT["sinusoid"] * len(model.lines)
    return k + (PARAMETER_COUNT["startup_transient"] if model.transient is not None else 0)


def _at_burst(found: dict, selection) -> bool:
    """Whether a level shift found lies at an impulsive event of `selection` (a shock that
    settles at a new level is reported as the event, not as a step)."""
    margin = found["size_window_s"]
    return any(
        b["start_s"] - margin <= found["time_s"] <= b["end_s"] + margin
        for b in selection.held_out.get("bursts", [])
    )


def _shift_in_place_of_walk(
    x, dt, evidence, max_lines, grid, model: _Model, floor: float, selection
):
    """A random walk named where the record holds a step of its level instead: the two have
    the same 1/f² spectrum, and once the walk is in the model its wander covers the step,
    so the level-shift test against the final model cannot see it. Here the step is sought
    against the model *without* the walk (the rest refitted); one found there is taken out
    and the selection run again on what is left, and the step replaces the walk when the
    whole record's likelihood says so: 2 Δ ln L of (the new selection + the step) over the
    walk's model, less Δk ln J for the noise parameters, at least the shift test's own
    critical z² (the price of searching its place and size) plus `evidence`. A true walk
    keeps its wander after one step is taken out: the new selection names it again and
    gains little. Returns (the test: the step sought, its score and bar, or None where no
    step stands against the reduced model; (shift, the new `_select` result) or None)."""
    rec = _Record(x, dt)
    names = tuple(n for n in model.names if n != "random_walk")
    reduced = _evaluate(rec, floor, names, model.lines, model.transient)
    residual = rec.residual(model.lines, model.transient)
    found = _level_shift(residual, dt, reduced, floor)
    if found is None or not found["significant"] or _at_burst(found, selection):
        return None, None
    size = found["size"]
    if grid is not None:
        size = round(size / grid["step"]) * grid["step"]
    if not (size != 0 and math.isfinite(size)):
        return None, None
    corrected = x - size * (np.arange(x.size) >= found["index"])
    try:
        rerun = _select(corrected, dt, evidence, max_lines, grid)
    except ValueError:
        return None, None
    new = rerun[1]
    gain = 2 * ((new.train + new.held) - (model.train + model.held))
    train, held = rec.grams((), None)
    score = gain - (_parameters(new) + 1 - _parameters(model)) * math.log(
        train.n_bins + held.n_bins
    )
    test = {
        "time_s": found["time_s"],
        "size": size,
        "z_without_the_walk": found["z"],
        "evidence_over_the_walk": float(score),
        "bar": float(found["critical_z"] ** 2 + evidence),
        "effects_with_the_step_out": list(rerun[0].effects),
    }
    # the step in the walk's place: a walk still named once the step is out is a step in
    # a walk, which the level-shift test against the walk's model judges
    if not score >= test["bar"] or "random_walk" in new.names:
        return test, None
    shift = {
        **{k: found[k] for k in ("time_s", "index", "z", "window_s", "size_window_s")},
        "size": size,
        "taken_out": True,
        "in_place_of": "random_walk",
        "evidence_over_the_walk": float(score),
    }
    return test, (shift, rerun)


def level_shift_sentence(shift: dict, unit: str = "g") -> str:
    """One level shift of `held_out["level_shifts"]` in words (the CLI and the diagnosis
    say it alike)."""
    what = (
        "taken out before the effects were selected"
        if shift.get("taken_out", True)
        else "under half the output grid's step, left in"
    )
    return (
        f"the level steps by {shift['size']:.3g} {unit} at {shift['time_s']:.4g} s "
        f"(|z| = {abs(shift['z']):.1f} against the model's own wander over "
        f"{shift['window_s']:.3g} s windows): outside the library; {what}"
    )


DRIFT_T = 8.0
DRIFT_BLOCKS = 32


def _drift(r: np.ndarray, dt: float) -> dict:
    """The least-squares slope of `DRIFT_BLOCKS` block means against time and its t value
    against their own scatter about the line (blocks much longer than the noise's
    correlation: a stationary noise gives |t| ≲ 4, a ramp of a few σ over the record
    |t| in the tens)."""
    usable = r.size // DRIFT_BLOCKS * DRIFT_BLOCKS
    means = r[:usable].reshape(DRIFT_BLOCKS, -1).mean(1)
    centre = (np.arange(DRIFT_BLOCKS) - (DRIFT_BLOCKS - 1) / 2) * usable / DRIFT_BLOCKS * dt
    slope = float(centre @ (means - means.mean()) / (centre @ centre))
    scatter = means - means.mean() - slope * centre
    se = math.sqrt(float(scatter @ scatter) / (DRIFT_BLOCKS - 2) / float(centre @ centre))
    return {"slope_per_s": slope, "t": abs(slope) / se if se > 0 else math.inf}


def _named(model: _Model) -> list:
    names = list(model.names)
    if model.lines:
        names.append("sinusoid")
    if model.transient is not None:
        names.append("startup_transient")
    return names
