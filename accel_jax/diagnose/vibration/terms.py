"""The term library of the discovery of a missing term in a vibration table (`discover`),
and each term's column of the table's linear model: the exact expectation of the term over
the row's vibration.

A term is a function s(a1, a2, a3) [g^degree] times a coefficient c [ppm/g^(degree−1)],
added to the indicated acceleration a_F (docs/models.md §3 eq. (1)); a row's mean output
gains c·E[s] (ppm of 1 g). The library holds the library effects' own coefficients (so
that a pair of them, or an effect left out of the effect library, can be found) and terms
beyond the static transfer function of the papers:

- input axis: k2 a3² … k5 a3⁵ and ½ A1 |a3| (the library's), k6 a3⁶, k7 a3⁷, |a3|·a3;
- cross axes: m31 a3 a1, m32 a3 a2 (the library's), a1², a2², a1 a2, a3 a1².

Each column is zero where the term is (c = 0: the nominal model, exactly). The row's
vibration is the table's (`accel_jax._data.VibrationData`): along the input axis a3 = a_in
+ b3 sin θ + σ ξ (θ uniform, ξ standard normal), on the output and pendulum axes the
in-phase sinusoids a1 = b1 sin θ, a2 = b2 sin θ. Expectations:

- a3⁶, a3⁷: `N_PHASE` equispaced phases × `N_HERMITE` Gauss–Hermite nodes, exact for the
  polynomial (trigonometric degree 7 < `N_PHASE`, 2·`N_HERMITE` − 1 ≥ 7);
- |a3|·a3: for σ > 0 the Gaussian average in closed form at each phase,
  E[Z|Z|] = (μ² + σ²)(2Φ(μ/σ) − 1) + 2μσ φ(μ/σ), averaged over the phases (smooth in θ);
  for σ = 0 the phase average in closed form (`mean_abs_square_sine`);
- a1², a2², a1 a2, a3 a1²: b1²/2, b2²/2, b1 b2/2, a_in b1²/2 (E sin² θ = ½, E sin³ θ = 0).

The library's own terms take the table's design columns (`table.prepare`: the same
expectation as the effects' fits). Float64, host side (NumPy): the columns are computed
once per table.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import numpy as np
from scipy.special import ndtr

from ..._data import VibrationData
from ..._vibration.expectation import mean_abs_sine

N_PHASE = 512
"""Phases of the expectations over the sinusoid (exact for the polynomial terms; the
|a3|·a3 term's Gaussian average converges exponentially in it)."""

N_HERMITE = 8
"""Gauss–Hermite nodes over the random part (exact to degree 15)."""


class VibrationTerm(NamedTuple):
    """One candidate term: `name`; `formula` in words; `unit` of its coefficient; `degree`
    of s in g; `library` the effect-library coefficient it is (None: outside the library's
    static transfer function); `cross` whether it needs cross-axis vibration."""

    name: str
    formula: str
    unit: str
    degree: int
    library: str | None = None
    cross: bool = False


TERMS = (
    VibrationTerm("asymmetry", "½ A1 |a3|", "ppm", 1, "asymmetry"),
    VibrationTerm("k2", "k2 a3²", "ppm/g", 2, "k2"),
    VibrationTerm("k3", "k3 a3³", "ppm/g²", 3, "k3"),
    VibrationTerm("k4", "k4 a3⁴", "ppm/g³", 4, "k4"),
    VibrationTerm("k5", "k5 a3⁵", "ppm/g⁴", 5, "k5"),
    VibrationTerm("k6", "k6 a3⁶", "ppm/g⁵", 6),
    VibrationTerm("k7", "k7 a3⁷", "ppm/g⁶", 7),
    VibrationTerm("abs_square", "c |a3| a3", "ppm/g", 2),
    VibrationTerm("m31", "m31 a3 a1", "ppm/g", 2, "m31", True),
    VibrationTerm("m32", "m32 a3 a2", "ppm/g", 2, "m32", True),
    VibrationTerm("oa_square", "c a1²", "ppm/g", 2, None, True),
    VibrationTerm("pa_square", "c a2²", "ppm/g", 2, None, True),
    VibrationTerm("oa_pa", "c a1 a2", "ppm/g", 2, None, True),
    VibrationTerm("ia_oa_square", "c a3 a1²", "ppm/g²", 3, None, True),
)
"""The vibration tables' term library (see the module docstring)."""


def mean_abs_square_sine(a, b) -> np.ndarray:
    """The phase average of (a + b sin θ)|a + b sin θ| (b ≥ 0), in closed form: sign(a)
    (a² + b²/2) where the sinusoid does not cross zero (b ≤ |a|), else a² + b²/2 − I/π with
    I = ∫ (a + b sin θ)² dθ over the phases where it is negative: with θ₀ = arcsin(a/b)
    and L = π − 2θ₀, I = a² L − 4ab cos θ₀ + b² (L/2 + sin 2θ₀ / 2)."""
    a, b = np.broadcast_arrays(np.asarray(a, float), np.asarray(b, float))
    square = a**2 + b**2 / 2
    crosses = b > np.abs(a)
    safe = np.where(crosses, b, 1.0)
    theta0 = np.arcsin(np.where(crosses, a / safe, 0.0))
    length = np.pi - 2 * theta0
    negative = (
        a**2 * length
        - 4 * a * safe * np.cos(theta0)
        + safe**2 * (length / 2 + np.sin(2 * theta0) / 2)
    )
    return np.where(crosses, square - negative / np.pi, np.sign(a) * square)


def _gauss_abs_square(mu, sigma) -> np.ndarray:
    """E[Z|Z|] for Z ~ N(μ, σ²), σ > 0."""
    z = mu / sigma
    density = np.exp(-0.5 * z**2) / math.sqrt(2 * math.pi)
    return (mu**2 + sigma**2) * (2 * ndtr(z) - 1) + 2 * mu * sigma * density


def _input_axis(data: VibrationData):
    """(a_in, b3, σ) of every row."""
    return (
        np.asarray(data.a_in, float),
        np.asarray(data.vib_amp, float),
        np.asarray(data.vib_rms, float),
    )


def _cross(data: VibrationData, name: str) -> np.ndarray:
    column = getattr(data, name)
    return np.zeros(len(data.a_in)) if column is None else np.asarray(column, float)


@functools.cache
def _hermite() -> tuple[np.ndarray, np.ndarray]:
    nodes, weights = np.polynomial.hermite_e.hermegauss(N_HERMITE)
    return nodes, weights / weights.sum()


def _polynomial(data: VibrationData, degree: int) -> np.ndarray:
    a, b, sigma = _input_axis(data)
    theta = 2 * np.pi * np.arange(N_PHASE) / N_PHASE
    nodes, weights = _hermite()
    x = a[:, None, None] + b[:, None, None] * np.sin(theta)[None, :, None]
    x = x + sigma[:, None, None] * nodes[None, None, :]
    return np.mean(np.sum(x**degree * weights, axis=-1), axis=-1)


def _abs_square(data: VibrationData) -> np.ndarray:
    a, b, sigma = _input_axis(data)
    theta = 2 * np.pi * np.arange(N_PHASE) / N_PHASE
    mu = a[:, None] + b[:, None] * np.sin(theta)[None, :]
    safe = np.where(sigma > 0, sigma, 1.0)[:, None]
    gauss = np.mean(_gauss_abs_square(mu, safe), axis=-1)
    return np.where(sigma > 0, gauss, mean_abs_square_sine(a, b))


def new_columns(data: VibrationData) -> dict[str, np.ndarray]:
    """E[s] per row [g^degree] of every term outside the library (`TERMS` with `library`
    None)."""
    a = np.asarray(data.a_in, float)
    b1, b2 = _cross(data, "vib_amp_oa"), _cross(data, "vib_amp_pa")
    return {
        "k6": _polynomial(data, 6),
        "k7": _polynomial(data, 7),
        "abs_square": _abs_square(data),
        "oa_square": b1**2 / 2,
        "pa_square": b2**2 / 2,
        "oa_pa": b1 * b2 / 2,
        "ia_oa_square": a * b1**2 / 2,
    }


def term_columns(data: VibrationData, design: np.ndarray, coefficients) -> np.ndarray:
    """Every term's column, rows × `TERMS`: the library's from `design` (the table's design
    matrix over `coefficients`, per ppm), the others from `new_columns`."""
    new = new_columns(data)
    index = {c: j for j, c in enumerate(coefficients)}
    return np.stack(
        [design[:, index[t.library]] if t.library else new[t.name] for t in TERMS], axis=1
    )


def condition_columns(a_in, b3, sigma, b1=0.0, b2=0.0) -> np.ndarray:
    """Every term's E[s] at test conditions (a_in, b3, σ on the input axis; b1, b2 the
    in-phase cross-axis amplitudes; scalars or arrays of one shape) [g^degree], conditions ×
    `TERMS` (a scalar condition: `TERMS` alone): what a term does at a condition no table
    row holds (`discover`'s consequences and separating rows)."""
    a, b, s, c1, c2 = np.broadcast_arrays(
        *(np.atleast_1d(np.asarray(x, float)) for x in (a_in, b3, sigma, b1, b2))
    )
    data = VibrationData(
        a_in=a,
        vib_amp=b,
        vib_freq=np.full(a.shape, 50.0),
        vib_rms=s,
        a_out=np.zeros(a.shape),
        vib_amp_oa=c1,
        vib_amp_pa=c2,
    )
    new = new_columns(data)
    library = {
        "asymmetry": 0.5 * _mean_abs(a, b, s),
        **{f"k{n}": _polynomial(data, n) for n in (2, 3, 4, 5)},
        "m31": 0.5 * b * c1,
        "m32": 0.5 * b * c2,
    }
    out = np.stack([library[t.name] if t.library else new[t.name] for t in TERMS], axis=-1)
    return out[0] if np.ndim(a_in) == 0 else out


def _mean_abs(a, b, sigma) -> np.ndarray:
    """E|a3| per condition: where σ > 0 the folded normal's mean at each phase averaged over
    the phases, else the sinusoid's closed form (`mean_abs_sine`)."""
    theta = 2 * np.pi * np.arange(N_PHASE) / N_PHASE
    mu = a[:, None] + b[:, None] * np.sin(theta)[None, :]
    safe = np.where(sigma > 0, sigma, 1.0)[:, None]
    z = mu / safe
    folded = safe * math.sqrt(2 / math.pi) * np.exp(-0.5 * z**2) + mu * (2 * ndtr(z) - 1)
    return np.where(sigma > 0, np.mean(folded, axis=-1), np.asarray(mean_abs_sine(a, b)))
