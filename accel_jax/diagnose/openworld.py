"""The open-world verdict: a diagnosis that can say "not something I know".

The verdict of a diagnosis is one of four (docs/models.md §5, issue 19):

- `none`: nothing is missing. Only when the refitted nominal model leaves held-out residuals
  consistent with the noise floor (their excess RMS over the floor at most
  `FLOOR_FACTOR`·floor, a whiteness test passed), its refit converged inside its prior,
  and no library effect is significant.
- an effect's name: the effect is significant (evidence and held-out improvement) and,
  with it, the held-out residual is at the floor. Deterministic effects are tried before
  stochastic ones, and a stochastic effect (correlated noise) is named only when the misfit
  it absorbs is not predictable from the input changes or from a periodic or trend
  component of the training residual (an AR(1) noise with φ → 1 whitens any smooth misfit;
  a noise cannot be locked to the test sequence).
- `cannot_tell`: two effects both explain the record and their evidence differs by less
  than `INDISTINCT`.
- `unexplained`: the gap is significant and neither the refit nor any library effect brings
  it to the floor, or the record is outside the model family (a domain check). The best
  partial effect, the fraction of the excess it explains and the gap that remains are
  reported.

The noise floor is estimated without the model (`noise_floor`), so that a model that fits
badly cannot raise its own floor; records quantised by an ADC get the quantisation floor
q/√12 when it is the larger.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence

import numpy as np

from .._deprecated import LegacyItems
from .._io import field_dict
from .._noise.mean_models import PeriodicLine
from .base import INDISTINCT, ljung_box

FLOOR_FACTOR = 1.0
"""A model explains the held-out data when the RMS of its held-out error in excess of the
noise floor is at most this many floors (so its mean square is at most (1 + F²)·σ²)."""

MODEL_FORM = 0.05
"""A deterministic effect that leaves at most this fraction of the gap it closes (RMS, on
the training and the held-out part alike: ≥ 99.75 % of the excess mean square) explains the
record even when what is left stands above the floor: the effect is right and its model
differs in form from the record's physics (e.g. a stiff penalty contact at a stop instead
of the model's inelastic one). The verdict names it and reports what remains."""

WHITENESS_LEVEL = 1e-3
"""Ljung–Box level below which a held-out residual counts as not white."""

PREDICTABLE = 0.2
"""A misfit is deterministic when a predictor fitted on the training residual alone (a
template locked to the input changes, a sinusoid, a trend) removes at least this fraction
of the held-out residual's mean square."""

LINE_Z = 5.0
"""On a residual whose null is white (a noise model's standardised one-step errors), a line
of the training part continues into the held-out part when the held-out residual's
projection on the continued sinusoid is this many standard errors from zero. The frequency
is chosen on the training part alone, so the held-out projection is a single test: z ~ N(0,
1) under the null, and 5 leaves a false line once in ~3.5 million records. A line far below
`PREDICTABLE`'s size is found this way (1.5 mg at 0.56 Hz under 4.6 mg of white noise)."""

LINE_PEAKS = 3
"""The periodic predictor's candidate lines: this many of the largest local maxima of the
training residual's zero-filled periodogram, each refined by least squares on the training
samples (`_training_line`)."""

PRIOR_LIMIT = 5.0
"""A refit that moves a parameter beyond this many σ of its prior is not credible: it can
never give `none`, and an effect whose fit needs it is not named."""

VERDICTS = ("none", "cannot_tell", "unexplained")
"""The verdicts that are not an effect's name."""


@dataclasses.dataclass(frozen=True)
class Decision(LegacyItems):
    """The open-world verdict (`decide`) and how it was reached.

    - `verdict`: `none`, `cannot_tell`, `unexplained` or an effect's name;
    - `tied`: the two effects of a `cannot_tell` (else empty);
    - `chosen`: the effect whose model is reported "after" (None for `none` and
        `unexplained`);
    - `best_partial`: with `unexplained`, the significant, credible effect that explains
        most of the excess (None if none);
    - `path`: which rule decided (`domain`, `nominal`, `deterministic`, `stochastic`, either
        `+nested`, `unexplained`; a kind's own later rule, e.g. the step kind's
        `nuisances`).

    It was a plain dict; `decision["verdict"]` still reads for one release, with a
    `DeprecationWarning`.
    """

    verdict: str
    tied: tuple[str, ...] = ()
    chosen: str | None = None
    best_partial: str | None = None
    path: str = ""

    def to_dict(self) -> dict:
        return field_dict(self)

    def _legacy(self) -> dict:
        return self.to_dict()


@dataclasses.dataclass(frozen=True)
class NominalStatus:
    """What `decide` reads of the refitted nominal model: `explains` (its held-out excess
    is at most `FLOOR_FACTOR` floors), `white` (its held-out residual passes the whiteness
    test), `plausible` (its refit converged inside its prior)."""

    explains: bool
    white: bool
    plausible: bool

    @classmethod
    def from_mapping(cls, status: Mapping) -> NominalStatus:
        """From the plain dict `decide` took before (keys as the fields)."""
        return cls(bool(status["explains"]), bool(status["white"]), bool(status["plausible"]))


@dataclasses.dataclass(frozen=True)
class Candidate:
    """One effect's fit as `decide` reads it.

    - `effect`: its name;
    - `evidence`: 2 ln B over the nominal model;
    - `significant`: its evidence and held-out improvement count (each kind's rule);
    - `stochastic`: a noise model (tried after the deterministic effects);
    - `explains`: with the effect, the held-out residual is at the floor;
    - `plausible`: its fit converged and is credible;
    - `explained_fraction`: what it removes of the nominal's held-out excess, in [0, 1];
    - `deterministic_misfit`: for a noise model, the misfit it absorbs is predictable
        (`predictability`), so it explains none of it.

    A kind's ranking entry may extend it (the step kind's `RankingEntry`).
    """

    effect: str
    evidence: float
    significant: bool
    stochastic: bool
    explains: bool
    plausible: bool
    explained_fraction: float
    deterministic_misfit: bool

    @classmethod
    def from_mapping(cls, entry: Mapping) -> Candidate:
        """From a kind's ranking dict (keys as the fields; `deterministic_misfit` False
        where absent)."""
        return cls(
            effect=entry["effect"],
            evidence=float(entry["evidence"]),
            significant=bool(entry["significant"]),
            stochastic=bool(entry["stochastic"]),
            explains=bool(entry["explains"]),
            plausible=bool(entry["plausible"]),
            explained_fraction=float(entry["explained_fraction"]),
            deterministic_misfit=bool(entry.get("deterministic_misfit", False)),
        )


@dataclasses.dataclass(frozen=True)
class NoiseFloorEstimate(LegacyItems):
    """A record's white-noise floor measured without any model (`noise_floor`), in the
    record's unit (V for a step record's output).

    - `sigma`: the floor used, the larger of `sigma_differences` and the quantisation
        floor q/√12;
    - `sigma_differences`: σ from the median absolute `order`-th difference;
    - `quantum`: the step q of the ADC grid the values lie on (0 when none is found).

    It was a plain dict; `floor["sigma"]` still reads for one release, with a
    `DeprecationWarning`.
    """

    sigma: float
    sigma_differences: float
    quantum: float

    def to_dict(self) -> dict:
        return field_dict(self)

    def _legacy(self) -> dict:
        return self.to_dict()


@dataclasses.dataclass(frozen=True)
class Whiteness(LegacyItems):
    """The Ljung–Box test of a residual (`whiteness`, on `base.ljung_box`) with its verdict.

    - `statistic`: Q (dimensionless);
    - `lags`: L, the lags summed (capped at a quarter of the samples);
    - `p_value`: P(χ²(L) > Q);
    - `white`: whether `p_value` ≥ `level`;
    - `level`: the level of the test (`WHITENESS_LEVEL`).

    It was a plain dict (`ljung_box`'s less its `autocorrelation`, with `white` and
    `level`); `test["white"]` still reads for one release, with a `DeprecationWarning`.
    """

    statistic: float
    lags: int
    p_value: float
    white: bool
    level: float

    def to_dict(self) -> dict:
        return field_dict(self)

    def _legacy(self) -> dict:
        return self.to_dict()


PREDICTORS = ("input_locked", "periodic", "trend")
"""The predictors of `predictability`, each a field of `Predictability`."""


@dataclasses.dataclass(frozen=True)
class Predictability(LegacyItems):
    """How much of a held-out residual a predictor fitted on the training residual alone
    removes (`predictability`).

    - `input_locked`, `periodic`, `trend`: the fraction of the held-out mean square each
        predictor removes (dimensionless; negative when it only adds its own noise);
    - `periodic_z`: the held-out residual's projection on the continued sinusoid, in
        standard errors;
    - `periodic_rms`: that projection's RMS in the held-out part, in the residual's unit;
    - `frequency_Hz` [Hz]: the sinusoid's frequency (None when none was fitted);
    - `deterministic`: whether the misfit counts as deterministic.

    A kind may extend it (the step kind's `noise_null.CalibratedPredictability`). It was a
    plain dict; `out["deterministic"]` still reads for one release, with a
    `DeprecationWarning`.
    """

    input_locked: float
    periodic: float
    periodic_z: float
    periodic_rms: float
    trend: float
    frequency_Hz: float | None
    deterministic: bool

    def removed(self, test: str) -> float:
        """The fraction that the predictor `test` (one of `PREDICTORS`) removes."""
        if test not in PREDICTORS:
            raise KeyError(test)
        return getattr(self, test)

    def to_dict(self) -> dict:
        """The fields in their order (a subclass's after them)."""
        return field_dict(self)

    def _legacy(self) -> dict:
        return self.to_dict()


def excess(mean_square: float, floor_variance: float) -> float:
    """RMS in excess of the floor, sqrt(max(ms − σ², 0))."""
    return float(math.sqrt(max(mean_square - floor_variance, 0.0)))


def explained_fraction(before: float, after: float) -> float:
    """The fraction of the excess mean square (gap²) an effect removes, in [0, 1]."""
    if before <= 0:
        return 0.0
    return float(min(max(1.0 - (after / before) ** 2, 0.0), 1.0))


def quantum(values: np.ndarray) -> float:
    """The step q of an ADC grid the values lie on (0 when they do not): the smallest
    spacing of the distinct values, accepted when at least 99 % of the spacings are whole
    multiples of it (to 1 % of q). Continuous values fail that test (their smallest spacing
    is tiny and the others are no multiples of it)."""
    x = np.unique(np.asarray(values, dtype=np.float64))
    if x.size < 3:
        return 0.0
    gaps = np.diff(x)
    scale = max(float(np.max(np.abs(x))), 1e-300)
    gaps = gaps[gaps > 1e-12 * scale]
    if gaps.size == 0:
        return 0.0
    q = float(np.min(gaps))
    ratio = gaps / q
    whole = np.abs(ratio - np.round(ratio)) < 0.01
    return q if np.mean(whole) >= 0.99 else 0.0


def noise_floor(
    values: np.ndarray, exclude: np.ndarray | None = None, order: int = 2
) -> NoiseFloorEstimate:
    """The white-noise floor of a record, without any model of it.

    σ from the median absolute `order`-th difference (variance factor C(2k, k): 6 for the
    second, 70 for the fourth; robust to steps and transients, and a smooth signal adds
    only x⁽ᵏ⁾Δᵏ), and the quantisation floor q/√12 of an ADC grid (`quantum`). `exclude`
    masks samples whose differences are not noise (e.g. next to a step). Returns a
    `NoiseFloorEstimate`: `sigma` (the floor used, the larger of the two),
    `sigma_differences`, `quantum`."""
    x = np.asarray(values, dtype=np.float64)
    k = int(order)
    diff = np.diff(x, k)
    if exclude is not None:
        bad = np.zeros(diff.size, dtype=bool)
        for shift in range(k + 1):
            bad |= exclude[shift : shift + diff.size]
        if np.sum(~bad) >= 16:
            diff = diff[~bad]
    mad = float(np.median(np.abs(diff - np.median(diff))))
    sigma = mad / 0.6745 / math.sqrt(math.comb(2 * k, k))
    q = quantum(x)
    floor = max(sigma, q / math.sqrt(12.0))
    return NoiseFloorEstimate(sigma=floor, sigma_differences=sigma, quantum=q)


def whiteness(residual: np.ndarray, lags: int = 20) -> Whiteness:
    """Ljung–Box on a residual (`base.ljung_box`), with the verdict at `WHITENESS_LEVEL`:
    a `Whiteness`."""
    test = ljung_box(residual, lags=lags)
    return Whiteness(
        statistic=test["statistic"],
        lags=test["lags"],
        p_value=test["p_value"],
        white=bool(test["p_value"] >= WHITENESS_LEVEL),
        level=WHITENESS_LEVEL,
    )


def _reduction(before: np.ndarray, predicted: np.ndarray) -> float:
    ms = float(np.mean(before**2))
    if ms <= 0:
        return 0.0
    return 1.0 - float(np.mean((before - predicted) ** 2)) / ms


def _training_line(r: np.ndarray, train: np.ndarray, t: np.ndarray, dt: float) -> float | None:
    """The frequency [Hz] of the periodic predictor's line, chosen on the training samples
    alone (None where the record holds fewer than 3 cycles of any frequency on its grid).

    The training residual's periodogram, zero-filled over the held-out samples and
    Hann-windowed, on a 16× zero-padded grid (2× beyond 65 536 samples): its `LINE_PEAKS`
    largest local maxima are the candidates. Each is refined on that grid within ± one
    Fourier bin, 1/(n dt), by the least-squares fit of a sinusoid and a constant to the
    training samples, and the frequency whose fit leaves the least is the line: the
    least-squares (Lomb–Scargle) periodogram of the training samples near the peaks. The
    held-out gaps put sidelobes beside a line, and the zero-filled periodogram's own largest
    peak can be one of them. Seen on a blind record of a 382 Hz disturbance (12 ms, two
    held-out runs): the largest peak lay at 791.7 Hz (0.912 against 0.908 at 395.8 Hz), and
    its continued sinusoid removed −0.16 of the held-out mean square; the line chosen here,
    at 390.6 Hz, removes 0.46."""
    n = r.size
    centred = np.where(train, r - np.mean(r[train]), 0.0)
    pad = 16 * n if n <= 1 << 16 else 2 * n  # a finer grid than the FFT's; bounded cost
    spectrum = np.abs(np.fft.rfft(centred * np.hanning(n), pad))
    freqs = np.fft.rfftfreq(pad, dt)
    usable = freqs >= 3.0 / (n * dt)
    if not np.any(usable):
        return None
    inside = np.flatnonzero(usable)
    inside = inside[(inside > 0) & (inside < freqs.size - 1)]
    peak = inside[
        (spectrum[inside] >= spectrum[inside - 1]) & (spectrum[inside] >= spectrum[inside + 1])
    ]
    if peak.size == 0:
        return float(freqs[usable][np.argmax(spectrum[usable])])
    peak = peak[np.argsort(spectrum[peak])[::-1][:LINE_PEAKS]]
    reach = int(round(pad / n))  # one Fourier bin, in grid steps
    grid = np.unique(np.clip(peak[:, None] + np.arange(-reach, reach + 1), 0, freqs.size - 1))
    grid = freqs[grid[usable[grid]]]
    tt, y = t[train], r[train] - np.mean(r[train])
    explained = np.empty(grid.size)  # y·y − the fit's residual sum of squares
    step = max(1, _LINE_CHUNK // max(tt.size, 1))  # frequencies at once: memory O(n) still
    for start in range(0, grid.size, step):
        explained[start : start + step] = _explained(tt, y, grid[start : start + step])
    return float(grid[np.argmax(explained)])


_LINE_CHUNK = 1 << 20
"""Numbers of cos 2πft (and of sin) `_training_line` holds at once: its frequencies are
fitted in chunks of this over the training samples' count."""


def _explained(tt: np.ndarray, y: np.ndarray, frequencies: np.ndarray) -> np.ndarray:
    """For each frequency f, y·y less the residual sum of squares of the least-squares fit
    of [cos 2πft, sin 2πft, 1] to y at times tt: the normal equations' solution by the
    pseudo-inverse of each 3×3 Gram matrix, cut at LAPACK's default (3ε of its largest
    singular value: a sine on the Nyquist grid, whose column vanishes, is dropped as a
    least-squares solver drops it). All frequencies at once; the same figures, to
    round-off, as one `np.linalg.lstsq` per frequency (tests/test_openworld.py); on a
    1,280-block record `_training_line` ~3× faster for it (docs/performance.md), which the
    noise null runs on each of its ~100 simulated residuals."""
    cos, sin = PeriodicLine.basis(tt[None, :], frequencies[:, None])
    n = np.full(frequencies.size, float(tt.size))
    cc, ss, cs = (np.einsum("kn,kn->k", a, b) for a, b in ((cos, cos), (sin, sin), (cos, sin)))
    c1, s1 = cos.sum(axis=1), sin.sum(axis=1)
    gram = np.stack(
        [np.stack([cc, cs, c1], -1), np.stack([cs, ss, s1], -1), np.stack([c1, s1, n], -1)], -2
    )
    projection = np.stack([cos @ y, sin @ y, np.full(frequencies.size, np.sum(y))], -1)
    inverse = np.linalg.pinv(gram, rcond=3 * np.finfo(np.float64).eps)
    coef = np.einsum("kij,kj->ki", inverse, projection)
    return np.einsum("ki,ki->k", coef, projection)


def predictability(
    residual: np.ndarray,
    held,
    dt: float,
    change_index: np.ndarray,
    change_step: np.ndarray,
    window: int,
    tests: tuple[str, ...] = ("input_locked", "periodic", "trend"),
    line_z: float | None = None,
) -> Predictability:
    """How much of the held-out residual a predictor fitted on the training residual alone
    removes: the test that tells a deterministic misfit from a stochastic one.

    - `input_locked`: a template h(m) of the residual after each input change, scaled by
      the change ΔU_j (least squares over the changes in the training part), predicts the
      windows after the held-out changes;
    - `periodic`: the strongest line of the training residual (at least 3 cycles in the
      record; its frequency chosen by least squares on the training samples near the
      periodogram's largest peaks, `_training_line`), fitted as a sinusoid on the training
      samples and continued over the held-out ones;
    - `trend`: a straight line fitted to the training residual and carried over.

    `held`: a boolean mask of the held-out samples, or the index where a held-out end part
    starts. Returns a `Predictability`: each predictor's fraction of the held-out mean
    square removed (negative when the predictor only adds its own noise, as it does for a
    stochastic residual); the misfit is `deterministic` when one of `tests` removes at least
    `PREDICTABLE` (a static record leaves out the trend: a random walk, a noise, is as
    predictable by a line).

    `line_z`: for a residual whose null is white, also call the misfit deterministic when
    the continued line's held-out projection is at least this many standard errors
    (`periodic_z`, `LINE_Z`) and it removes something — a significance test where the
    `PREDICTABLE` fraction is a size test."""
    r = np.asarray(residual, dtype=np.float64)
    n = r.size
    if np.ndim(held) == 0:
        held = np.arange(n) >= int(held)
    held = np.asarray(held, dtype=bool)
    train = ~held
    input_locked = periodic = periodic_z = periodic_rms = 0.0
    frequency_Hz = None
    if np.sum(held) < 8 or np.sum(train) < 16:
        return Predictability(
            input_locked, periodic, periodic_z, periodic_rms, 0.0, frequency_Hz, False
        )
    t = np.arange(n) * dt
    # Input-locked template: windows after the changes that start in the training part.
    steps = np.asarray(change_step, dtype=np.float64)
    index = np.asarray(change_index)
    use = steps != 0
    index, steps = index[use], steps[use]
    bounds = np.concatenate([index, [n]])
    numerator = np.zeros(window)
    denominator = np.zeros(window)
    predicted = np.zeros(n)
    covered = np.zeros(n, dtype=bool)
    for j, (i, step) in enumerate(zip(index, steps, strict=True)):
        stop = min(bounds[j + 1], i + window)
        if i >= n or stop <= i:
            continue
        if not held[i]:
            part = np.arange(i, stop)
            part = part[train[part]]
            numerator[part - i] += step * r[part]
            denominator[part - i] += step**2
    template = np.where(denominator > 0, numerator / np.where(denominator > 0, denominator, 1), 0)
    for j, (i, step) in enumerate(zip(index, steps, strict=True)):
        stop = min(bounds[j + 1], i + window)
        if i < n and held[i] and stop > i:
            predicted[i:stop] = step * template[: stop - i]
            covered[i:stop] = True
    covered &= held
    if np.any(covered):
        input_locked = _reduction(r[covered], predicted[covered])
    # Periodic component.
    f = _training_line(r, train, t, dt)
    if f is not None:
        basis = np.stack([*PeriodicLine.basis(t, f), np.ones(n)], 1)
        coef, *_ = np.linalg.lstsq(basis[train], r[train], rcond=None)
        # the least-squares prediction (a matrix product: `PeriodicLine.signal`, c cos + s sin
        # elementwise, is the same line but differs in the last bit at ~1 sample in 4)
        sinusoid = basis[:, :2] @ coef[:2]
        periodic = _reduction(r[held] - coef[2], sinusoid[held])
        frequency_Hz = f
        line = sinusoid[held]
        rest = r[held] - np.mean(r[held])
        scale = np.std(rest) * np.sqrt(np.sum(line**2))
        periodic_z = float(np.sum(rest * line) / scale) if scale > 0 else 0.0
        power = float(np.sum(line**2))
        beta = float(np.sum(rest * line)) / power if power > 0 else 0.0
        periodic_rms = abs(beta) * math.sqrt(power / line.size)  # in the held-out part
    # Trend.
    slope, intercept = np.polyfit(t[train], r[train], 1)
    trend = _reduction(r[held], slope * t[held] + intercept)
    out = Predictability(
        input_locked, periodic, periodic_z, periodic_rms, trend, frequency_Hz, False
    )
    deterministic = max(out.removed(test) for test in tests) >= PREDICTABLE
    if line_z is not None and "periodic" in tests:
        deterministic |= periodic_z >= line_z and periodic > 0
    return dataclasses.replace(out, deterministic=bool(deterministic))


def decide(
    nominal: NominalStatus | Mapping,
    candidates: Sequence[Candidate | Mapping],
    *,
    domain: list[str] | None = None,
    indistinct: float = INDISTINCT,
    resolve_tie=None,
) -> Decision:
    """The open-world verdict from the nominal model's status and the candidates' fits.

    **Arguments:**

    - `nominal`: the refitted nominal model's `NominalStatus` (or a dict of its fields).
    - `candidates`: one `Candidate` per effect (or a dict of its fields, where a noise
        model's `deterministic_misfit` may be left out).
    - `domain`: problems found by a domain check (the record is outside the model family).
    - `resolve_tie(first, second)`: the effect a tie resolves to, or None (nested effects).

    **Returns:** a `Decision`: `verdict`, `tied`, `chosen` (the effect whose model is
    reported "after", or None), `best_partial` (for `unexplained`), `path` (which rule
    decided).
    """
    if not isinstance(nominal, NominalStatus):
        nominal = NominalStatus.from_mapping(nominal)
    typed = [c if isinstance(c, Candidate) else Candidate.from_mapping(c) for c in candidates]
    if domain:
        partial = _best_partial(typed)
        return Decision(verdict="unexplained", best_partial=partial, path="domain")
    usable = [c for c in typed if c.significant and c.plausible]
    if not usable and nominal.explains and nominal.white and nominal.plausible:
        return Decision(verdict="none", path="nominal")
    deterministic = [c for c in usable if not c.stochastic and c.explains]
    stochastic = [c for c in usable if c.stochastic and c.explains and not c.deterministic_misfit]
    for group, path in ((deterministic, "deterministic"), (stochastic, "stochastic")):
        if not group:
            continue
        group = sorted(group, key=lambda c: c.evidence, reverse=True)
        if len(group) > 1 and group[0].evidence - group[1].evidence < indistinct:
            first, second = group[0].effect, group[1].effect
            simpler = resolve_tie(first, second) if resolve_tie else None
            if simpler is not None:
                return Decision(verdict=simpler, chosen=simpler, path=path + "+nested")
            return Decision(verdict="cannot_tell", tied=(first, second), chosen=first, path=path)
        return Decision(verdict=group[0].effect, chosen=group[0].effect, path=path)
    partial = _best_partial(typed)
    return Decision(verdict="unexplained", best_partial=partial, path="unexplained")


def _best_partial(candidates: list[Candidate]) -> str | None:
    """The significant, credible effect that explains most of the excess (None if none)."""
    usable = [c for c in candidates if c.significant and c.plausible]
    if not usable:
        return None
    best = max(usable, key=lambda c: (c.explained_fraction, c.evidence))
    return best.effect if best.explained_fraction > 0 else None
