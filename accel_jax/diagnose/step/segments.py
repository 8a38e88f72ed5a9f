"""A step record's segments of constant input (host side, NumPy): their edges, the
held-out ones, and times written as the diagnosis writes them."""

from __future__ import annotations

import numpy as np

from ..._data import StepData

HELD_OUT_EVERY = 3
"""Every third segment of constant test voltage is held out (`held_out_samples`)."""

HELD_OUT_FRACTION = 1 / 3
"""A record of fewer than four segments holds out about this much at its end."""


def held_out_samples(u_test: np.ndarray) -> tuple[np.ndarray, str]:
    """The held-out samples of a record, and how they were chosen.

    Every third segment of constant test voltage, from the third on (segments 2, 5, 8, …):
    the held-out part then sees the same kinds of change and the same levels as the fit, so
    it tests the effect, not an extrapolation to a level (or a stop) the fit never saw. A
    record of fewer than four segments holds out its last third instead (from the change
    nearest 2/3 of it, else from 2/3)."""
    n = u_test.shape[0]
    edges = segments(u_test)
    held = np.zeros(n, dtype=bool)
    if edges.size - 1 >= 4:
        for j in range(2, edges.size - 1, HELD_OUT_EVERY):
            held[edges[j] : edges[j + 1]] = True
        return held, f"every {HELD_OUT_EVERY}rd segment from the 3rd (of {edges.size - 1})"
    changes = edges[1:-1]
    target = int(round((1 - HELD_OUT_FRACTION) * n))
    usable = changes[(changes > (changes[0] if changes.size else 0)) & (changes < n - n // 10)]
    usable = usable[usable >= n // 2]
    start = int(usable[np.argmin(np.abs(usable - target))]) if usable.size else target
    held[start:] = True
    return held, "the last third of the record"


def sequence_key(data: StepData) -> np.ndarray:
    """An array that changes exactly where the record's inputs do: u_test, or u_test +
    i·a_in (complex) for a record with an acceleration column (`segments` takes either)."""
    u = np.asarray(data.u_test)
    if getattr(data, "a_in", None) is None:
        return u
    return u + 1j * np.asarray(data.a_in)


def segments(u: np.ndarray) -> np.ndarray:
    """Edges of the constant stretches of `u` (its first sample, each change, its end)."""
    n = u.shape[0]
    return np.concatenate([[0], np.flatnonzero(np.diff(u) != 0) + 1, [n]])


def time_text(seconds: float) -> str:
    """A time [s] to 3 significant figures in s, ms, µs or ns."""
    seconds = float(seconds)
    for unit, factor in (("s", 1.0), ("ms", 1e-3), ("µs", 1e-6)):
        if abs(seconds) >= factor:
            return f"{seconds / factor:.3g} {unit}"
    return f"{seconds * 1e9:.3g} ns"
