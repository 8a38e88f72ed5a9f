"""A step record's inputs as a test stand records them: the plateaus and change times of a
measured (noisy, quantised, spiky, delayed, drifting) test-voltage or acceleration column.

The step diagnosis models the input as piecewise constant. A library record, or a column
written from the command sequence, is exactly that; a real test stand digitises its
calibration input beside the output, so its `u_test` column carries the ADC's noise and
step, a relay spike at each switch, an anti-alias filter's edge, an offset and a slow
drift. `read_input` finds the plateaus of such a column and returns the piecewise-constant
input they define, with what it found in words; an input without plateaus (a swept sine, a
continuous random signal) is refused with one `DataError`.

**Method** (NumPy, no model of the loop): a running median of 5 samples takes out spikes of
up to two samples; a sample is *steady* when the median-filtered column moves by at most
`STEADY_SIGMAS` times the input's own noise (estimated from the column's first
differences by their median absolute deviation, or one ADC step where the noise is below
it) to both neighbours; runs of at least `MIN_PLATEAU` steady samples are plateaus, and
neighbouring plateaus whose levels differ by less than `MERGE_SIGMAS` noise σ (a spike or a
noise burst splitting one plateau) are joined. Each plateau's level is the mean of its raw
samples within 5 σ of its median (spikes out). A change is placed at the first sample past
the midpoint between the two levels (on the median-filtered column); the delay between the
input and output channels and the sub-sample phase are the fit's change-time nuisances.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..._data import DataError, StepData

MIN_PLATEAU = 3
"""Fewest steady samples a plateau has (a relay spike lasts one or two)."""

STEADY_SIGMAS = 6.0
"""A sample is steady when the filtered input moves by at most this many noise σ to its
neighbours."""

MERGE_SIGMAS = 10.0
"""Neighbouring plateaus closer than this many noise σ (in level) are one plateau."""

STEADY_SHARE = 0.6
"""An input is piecewise constant when at least this share of its samples lie on plateaus."""

DRIFT_SIGMAS = 4.0
"""A drift of the input within its plateaus (their pooled slope) is taken into the levels'
errors when it is this many standard errors from zero."""

SPREAD_SIGMAS = 4.0
"""A plateau's samples spread (robust σ) by at most this many noise σ (a slow drift of the
input within `MERGE_SIGMAS` noise σ included)."""

DRIFT_SHARE = 0.25
"""A plateau whose level moves (between its first and last quarters) by more than
`MERGE_SIGMAS` noise σ and more than this share of the smallest step next to it (or at
all, with no step next to it) is not a plateau: the input is not piecewise constant (a
sweep, a continuous signal)."""


@dataclasses.dataclass(frozen=True)
class InputReading:
    """A test input as the step diagnosis reads it.

    **Fields:** `values` the piecewise-constant input (shape (n,)); `measured` whether the
    column was a measurement that had to be read (False: already piecewise constant, used
    as it is); `levels` each plateau's level; `change_index` the first sample of each level
    after the first; `noise` the input's noise σ per sample; `level_sigma` each level's
    standard error; `spikes` samples set aside as spikes; `note` what was found, in words;
    `level_drift` each level's error per unit of the input channel's drift nuisance (a
    standard normal: the drift found, or the largest the plateaus cannot rule out).
    """

    values: np.ndarray
    measured: bool
    levels: np.ndarray
    change_index: np.ndarray
    noise: float
    level_sigma: np.ndarray
    spikes: int
    note: str
    level_drift: np.ndarray | None = None


def _median5(x: np.ndarray) -> np.ndarray:
    """Running median of 5 samples (edges padded by repetition)."""
    padded = np.concatenate([np.repeat(x[:1], 2), x, np.repeat(x[-1:], 2)])
    windows = np.lib.stride_tricks.sliding_window_view(padded, 5)
    return np.median(windows, axis=1)


def _runs(flags: np.ndarray) -> list[tuple[int, int]]:
    """(start, stop) of each run of True in `flags`."""
    edges = np.diff(np.concatenate([[0], flags.astype(np.int8), [0]]))
    starts, stops = np.flatnonzero(edges == 1).tolist(), np.flatnonzero(edges == -1).tolist()
    return list(zip(starts, stops, strict=True))


UNCLOCKED_CHANGES = 64
"""A column of more changes is taken as piecewise constant only when they fall on one bit
clock (`clock_grid`): an ADC's flicker can leave runs as long as a plateau's."""


def _exact(x: np.ndarray, max_changes: int | None) -> bool:
    """Already piecewise constant: every run of equal values at least `MIN_PLATEAU` long
    (its first and last may be shorter: the record cuts them), where given at most
    `max_changes` changes, and more than `UNCLOCKED_CHANGES` only on one clock."""
    change = np.flatnonzero(np.diff(x) != 0) + 1
    if max_changes is not None and change.size > max_changes:
        return False
    if change.size > UNCLOCKED_CHANGES and clock_grid(change) is None:
        return False
    lengths = np.diff(np.concatenate([[0], change, [x.size]]))
    return bool(lengths.size <= 2 or np.all(lengths[1:-1] >= MIN_PLATEAU))


def _noise(x: np.ndarray) -> tuple[float, float]:
    """(σ per sample from the first differences' MAD, the ADC step seen in the column)."""
    d = np.diff(x)
    sigma = 1.4826 * float(np.median(np.abs(d - np.median(d)))) / math.sqrt(2)
    nonzero = np.abs(d[d != 0])
    step = 0.0
    if nonzero.size:
        smallest = float(nonzero.min())
        # An ADC step is the commonest small difference (flicker between two codes).
        close = nonzero[nonzero <= smallest * 1.5]
        if close.size >= max(10, x.size // 1000) and smallest <= 0.05 * float(np.ptp(x)):
            step = smallest
    return sigma, step


def read_input(
    x, *, name: str = "u_test", unit: str = "V", max_changes: int | None = None
) -> InputReading:
    """Read a step record's input column `x` as a piecewise-constant sequence.

    A column that is piecewise constant already (every plateau ≥ `MIN_PLATEAU` samples, at
    most `max_changes` changes) is returned as it is (`measured` False). Otherwise the
    plateaus are found as the module docstring says; `DataError` when the column has none
    (a sweep, a continuous random signal), naming `name`.
    """
    x = np.asarray(x, dtype=np.float64)
    n = x.size
    if _exact(x, max_changes):
        change = np.flatnonzero(np.diff(x) != 0) + 1
        starts = np.concatenate([[0], change])
        return InputReading(
            values=x,
            measured=False,
            levels=x[starts],
            change_index=change,
            noise=0.0,
            level_sigma=np.zeros(starts.size),
            spikes=0,
            note="",
        )
    sigma, step = _noise(x)
    scale = max(float(np.ptp(x)), 1e-300)
    tolerance = max(STEADY_SIGMAS * sigma, 1.5 * step, 1e-9 * scale)
    filtered = _median5(x)
    moves = np.abs(np.diff(filtered))
    steady = np.ones(n, dtype=bool)
    steady[1:] &= moves <= tolerance
    steady[:-1] &= moves <= tolerance
    runs = [(a, b) for a, b in _runs(steady) if b - a >= MIN_PLATEAU]
    refuse = (
        f"{name} has no plateaus: it is not a piecewise-constant test sequence (a swept "
        "sine or a continuous random signal?); the step diagnosis needs the input held at "
        "levels between changes"
    )
    if not runs or sum(b - a for a, b in runs) < STEADY_SHARE * n:
        raise DataError(refuse + f" ({_share(runs, n):.0%} of the samples lie on plateaus).")
    noise_level = max(sigma, step / math.sqrt(12), 1e-12 * scale)
    merge = MERGE_SIGMAS * noise_level + 2 * step
    plateaus: list[tuple[int, int, float]] = []  # (start, stop, median level)
    for a, b in runs:
        level = float(np.median(x[a:b]))
        if plateaus and abs(level - plateaus[-1][2]) <= merge:
            start = plateaus[-1][0]
            plateaus[-1] = (start, b, float(np.median(x[start:b])))
        else:
            plateaus.append((a, b, level))
    levels, sigmas, spikes = [], [], 0
    slope_sums = np.zeros(2)  # Σ s_k w_k, Σ w_k: the plateaus' pooled within-slope
    middles = []
    for a, b, median in plateaus:
        values = x[a:b]
        keep = np.abs(values - median) <= 5 * noise_level + step
        spikes += int(np.sum(~keep))
        levels.append(float(np.mean(values[keep])))
        sigmas.append(noise_level / math.sqrt(max(int(np.sum(keep)), 1)))
        k = np.flatnonzero(keep).astype(np.float64)
        middles.append(a + (float(k.mean()) if k.size else 0.5 * (b - a)))
        if k.size >= 3:
            centred = k - k.mean()
            weight = float(np.sum(centred**2))
            if weight > 0:
                slope_sums += (float(np.sum(centred * values[keep])), weight)
    # A drift of the input channel (its level moving within the plateaus alike): the
    # levels are then known only to where on the drift each plateau sits. `drift_shape`
    # is each level's error per unit of one drift nuisance (standard normal): the pooled
    # slope — or the largest one the plateaus cannot rule out — times the plateau's
    # distance from the record's middle. The output then tells a drifting measurement
    # from a drifting input (errors in variables).
    drift = 0.0
    drift_shape = [0.0] * len(plateaus)
    # A level the sequence returns to tells the drift across the record as well: its
    # plateaus' means about their own mean, against their places (a PRBS's two levels, over
    # hundreds of plateaus, pin the drift far tighter than the short plateaus' own slopes).
    slope_sums += _repeated_level_slope(levels, sigmas, middles, merge, noise_level)
    if slope_sums[1] > 0:
        slope = slope_sums[0] / slope_sums[1]
        slope_sigma = noise_level / math.sqrt(slope_sums[1])
        if abs(slope) > DRIFT_SIGMAS * slope_sigma:
            drift = slope * n
        # The drift the levels allow for: the one found, or the largest the input's own
        # record could not have found (`DRIFT_SIGMAS` standard errors of the slope): one
        # nuisance of the fit, each level moved by it in proportion to its place.
        allowance = max(abs(slope), DRIFT_SIGMAS * slope_sigma)
        centre = float(np.mean(middles))
        drift_shape = [allowance * (mid - centre) for mid in middles]
    levels_arr = np.asarray(levels)
    steps = np.abs(np.diff(levels_arr))
    for k, (a, b, _) in enumerate(plateaus):
        values = x[a:b]
        spread = 1.4826 * float(np.median(np.abs(values - np.median(values))))
        if spread > SPREAD_SIGMAS * noise_level + step:
            raise DataError(
                refuse + f" (a stretch of {b - a} samples that moves by less than the noise "
                f"from sample to sample spreads over {spread:.3g} {unit} (robust σ), "
                f"{spread / noise_level:.3g} times the input's noise)."
            )
        quarter = max((b - a) // 4, 1)
        moved = abs(float(np.median(filtered[b - quarter : b]) - np.median(filtered[a : a + quarter])))
        near = [steps[j] for j in (k - 1, k) if 0 <= j < steps.size]
        if moved > merge and (not near or moved > DRIFT_SHARE * min(near)):
            against = f", against steps of {min(near):.3g} {unit}" if near else ""
            raise DataError(
                refuse + f" (its level moves by {moved:.3g} {unit} within a stretch of "
                f"{b - a} samples{against})."
            )
    change = []
    for k in range(1, len(plateaus)):
        gap_start, gap_stop = plateaus[k - 1][1], plateaus[k][0]
        middle = 0.5 * (levels[k - 1] + levels[k])
        rising = levels[k] > levels[k - 1]
        segment = filtered[gap_start - 1 : gap_stop + 1]
        past = np.flatnonzero(segment >= middle) if rising else np.flatnonzero(segment <= middle)
        index = gap_start - 1 + int(past[0]) if past.size else gap_stop
        change.append(min(max(index, plateaus[k - 1][0] + 1), gap_stop))
    change_arr = np.asarray(change, dtype=int)
    if change_arr.size == 0:
        raise DataError(
            f"{name} holds one level with noise (σ {noise_level:.3g} {unit} per sample): no "
            "change of the test input was found, so there is no step response to diagnose"
        )
    if max_changes is not None and change_arr.size > max_changes:
        raise DataError(
            f"{name} changes {change_arr.size} times; the step diagnosis takes at most "
            f"{max_changes} changes in one record (split it into shorter records)."
        )
    starts = np.concatenate([[0], change_arr])
    values = levels_arr[np.searchsorted(starts, np.arange(n), side="right") - 1]
    return InputReading(
        values=values,
        measured=True,
        levels=levels_arr,
        change_index=change_arr,
        noise=float(noise_level),
        level_sigma=np.asarray(sigmas),
        spikes=spikes,
        level_drift=np.asarray(drift_shape),
        note=_describe(name, unit, levels_arr, change_arr, noise_level, step, spikes, n, drift),
    )


def _repeated_level_slope(levels, sigmas, middles, same: float, noise: float) -> np.ndarray:
    """(Σ s_k w_k, Σ w_k) in the units of `read_input`'s pooled within-plateau slope (its
    weights are Σ (k − k̄)² per unit noise variance): the slope of the plateau means of each
    level the sequence returns to (plateaus within `same` of each other), about that level's
    mean, against the plateaus' middles [samples]; weighted by each mean's variance. Zeros
    when no level repeats."""
    levels = np.asarray(levels, dtype=np.float64)
    out = np.zeros(2)
    if levels.size < 2:
        return out
    order = np.argsort(levels)
    groups, current = [], [int(order[0])]
    for a, b in zip(order[:-1], order[1:], strict=True):
        if levels[b] - levels[a] <= same:
            current.append(int(b))
        else:
            groups.append(current)
            current = [int(b)]
    groups.append(current)
    for members in groups:
        if len(members) < 2:
            continue
        t = np.asarray([middles[k] for k in members], dtype=np.float64)
        x = levels[members]
        # Each mean's variance is σ_k² = noise²/n_k: weight n_k = (noise/σ_k)², as the
        # within-plateau sums weigh each sample by 1 in units of the noise variance.
        w = np.asarray([(noise / sigmas[k]) ** 2 if sigmas[k] > 0 else 0.0 for k in members])
        if not np.sum(w) > 0:
            continue
        tc = t - np.sum(w * t) / np.sum(w)
        xc = x - np.sum(w * x) / np.sum(w)
        out += (float(np.sum(w * tc * xc)), float(np.sum(w * tc**2)))
    return out


def _share(runs, n) -> float:
    return sum(b - a for a, b in runs) / max(n, 1)


def _describe(name, unit, levels, change, noise, step, spikes, n, drift=0.0) -> str:
    shown = ", ".join(f"{v:.4g}" for v in levels[:8]) + (" …" if levels.size > 8 else "")
    at = ", ".join(str(int(i)) for i in change[:8]) + (" …" if change.size > 8 else "")
    parts = [
        f"{name} read as a measurement (noise {noise:.2g} {unit} per sample"
        + (f", ADC step {step:.2g} {unit}" if step > 0 else "")
        + (f", {spikes} spike samples set aside" if spikes else "")
        + f"): {levels.size} plateaus at {shown} {unit}",
    ]
    if change.size:
        parts.append(f"changes at samples {at} (of {n})")
    if drift:
        parts.append(
            f"the channel drifts by {drift:+.2g} {unit} over the record within its plateaus "
            "(a drift nuisance of the fit moves the levels along it)"
        )
    parts.append(
        "each change time is then fitted to a fraction of a sample, which takes up a delay "
        "between the input and output channels"
    )
    return "; ".join(parts)


@dataclasses.dataclass(frozen=True)
class Clock:
    """The bit clock of a sequence whose changes all fall on one grid (`clock_grid`):
    `period` [samples] one bit, `phase` [samples] the grid's origin, `bits` (J,) each
    change's bit count from the first, `residual` (J,) [samples] each change's index less
    the grid's time for it."""

    period: float
    phase: float
    bits: np.ndarray
    residual: np.ndarray


CLOCK_TOLERANCE = 1.5
"""A sequence is clocked when every change's index lies within this many samples of the
fitted grid (a sampled column shows a change up to one sample late; a measured one's
crossing moves by its noise)."""


def clock_grid(change_index) -> Clock | None:
    """The bit clock of a many-change sequence (a PRBS or random telegraph from a clocked
    generator), or None when its changes are on no common grid.

    The bit length starts as the mean of the shortest intervals (those below 1.5× the
    shortest), each interval is rounded to whole bits, and the grid index ≈ phase +
    period·bits is fitted by least squares, again until the bit counts stop changing. Clocked when every residual is within `CLOCK_TOLERANCE` samples and a bit is at
    least 3 samples long."""
    index = np.asarray(change_index, dtype=float)
    if index.size < 3:
        return None
    gaps = np.diff(index)
    if np.any(gaps <= 0):
        return None
    shortest = 3 - 1e-9  # (a fitted period of exactly 3 comes out 2.9999999999999987)
    period = float(np.mean(gaps[gaps < 1.5 * gaps.min()]))
    counts = None
    bits, intercept = np.zeros(1), 0.0  # (set by the first pass, which always runs)
    for _ in range(20):  # until the bit counts stop changing
        if period < shortest:
            return None
        new = np.maximum(np.round(gaps / period), 1)
        if counts is not None and np.array_equal(new, counts):
            break
        counts = new
        bits = np.concatenate([[0.0], np.cumsum(counts)])
        slope, intercept = np.polyfit(bits, index, 1)
        period = float(slope)
    residual = index - (intercept + period * bits)
    if period < shortest or np.max(np.abs(residual)) > CLOCK_TOLERANCE:
        return None
    return Clock(period=period, phase=float(intercept), bits=bits, residual=residual)


def level_groups(levels, sigmas) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The distinct levels of a measured sequence: (each plateau's group (J+1,), each
    group's level [V] as the inverse-variance mean of its plateaus, each group's standard
    error [V]). In order of level, a plateau within 10 standard errors (its own or the
    group's largest) of the group's mean so far joins it: a DAC puts out the same value
    each time."""
    levels = np.asarray(levels, dtype=float)
    sigmas = np.maximum(np.asarray(sigmas, dtype=float), 1e-15)
    order = np.argsort(levels)
    group = np.zeros(levels.size, dtype=int)
    current, members = 0, [order[0]]
    for k in order[1:]:
        # Against the group's mean so far (not its last member: no chains of close levels).
        w = 1 / sigmas[members] ** 2
        mean, error = np.sum(w * levels[members]) / np.sum(w), 1 / np.sqrt(np.sum(w))
        if levels[k] - mean > 10 * max(sigmas[k], error, float(np.max(sigmas[members]))):
            current, members = current + 1, []
        members.append(k)
        group[k] = current
    weights = 1 / sigmas**2
    total = np.bincount(group, weights)
    means = np.bincount(group, weights * levels) / total
    return group, means, 1 / np.sqrt(total)


@dataclasses.dataclass(frozen=True)
class StepInputs:
    """A step record with its inputs read as piecewise-constant sequences (`read_inputs`):
    `data` the record the diagnosis fits (the measured columns replaced by their plateaus),
    `notes` what was read (empty for clean inputs), `level_sigma` the RMS standard error of
    the test-voltage levels [V] (0 for a clean column), `level_sigmas` each test level's
    standard error [V] in order (None for a clean column)."""

    data: StepData
    notes: tuple
    level_sigma: float
    level_sigmas: np.ndarray | None = None
    level_drift: np.ndarray | None = None


def read_inputs(data: StepData, *, max_changes: int | None = None) -> StepInputs:
    """`read_input` on the record's `u_test` (and `a_in`), the record rebuilt with their
    plateaus; `DataError` (naming the column) for an input without plateaus."""
    u = read_input(data.u_test, name="u_test", unit="V", max_changes=max_changes)
    a = None
    if data.a_in is not None:
        a = read_input(data.a_in, name="a_in", unit="g", max_changes=max_changes)
    readings = [r for r in (u, a) if r is not None and r.measured]
    if not readings:
        return StepInputs(data=data, notes=(), level_sigma=0.0)
    rebuilt = StepData(
        t=data.t,
        u_test=u.values,
        u_out=data.u_out,
        notes=tuple(data.notes),
        a_in=None if a is None else a.values,
        input_delay=data.input_delay,
    )
    sigma = float(np.sqrt(np.mean(u.level_sigma**2))) if u.measured else 0.0
    return StepInputs(
        data=rebuilt,
        notes=tuple(r.note for r in readings),
        level_sigma=sigma,
        level_sigmas=u.level_sigma if u.measured else None,
        level_drift=u.level_drift if u.measured else None,
    )
