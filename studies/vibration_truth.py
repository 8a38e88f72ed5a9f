"""An independent truth simulator of vibration (shaker / tumble) test tables, for a blind
test of a diagnosis that looks for terms missing from an accelerometer's static model.
Written from the physics alone, with NumPy/SciPy and none of the package's vibration code;
only the output container, `accel_jax.VibrationData`, is the package's.

Physics. At each instant the device indicates (all accelerations in g)

    a_F = a0 + (1 + δ) a3 + ½ A1 |a3| + Σ_{n=2..5} k_n a3ⁿ + m31 a3 a1 + m32 a3 a2 + EXTRA

with a3, a1, a2 the accelerations along the input (IA), output (OA) and pendulum (PA) axes.
A row is one test condition held for one record: a3(t) = a_in + b3 sin(ωt + φ) + r(t),
a1(t) = b1 sin(ωt + φ), a2(t) = b2 sin(ωt + φ) (in phase; the random part r only on IA).
The table's `a_out` is the record's sample mean of a_F, plus the row's noise, quantised.
EXTRA, by the record's class (c in ppm of the unit given):
  none: 0;  k6: c a3⁶ [ppm/g⁵];  k7: c a3⁷ [ppm/g⁶];  abs_square: c |a3| a3 [ppm/g];
  oa_square: c a1² [ppm/g];  pa_square: c a2²;  oa_pa: c a1 a2;  ia_oa_square: c a3 a1²
  [ppm/g²];  k2_k6: k2 a3² + c a3⁶;  frequency_dependent (no static term describes it):
  c a3_dyn², a3_dyn = a_in + G(f) (b3 sin + r), G(f) = 1/√((1 − (f/f_r)²)² + (f/(Q f_r))²),
  f the row's `vib_freq`, f_r ~ U(150, 600) Hz, Q ~ U(2, 10). G scales the random part too
  (at the row's f: a simplification, a real resonance would filter the random spectrum).
Independently of the class, 30 % of records carry a standard k2 and/or k3 (k2 only, k3
only or both, equally likely), |k| log-uniform in 0.3–10 ppm/g^(n−1), random sign; "k2_k6"
always has its k2 drawn so. A1, k4, k5, m31, m32 are zero in the draws (the simulator
supports them). Bias a0 ~ U(−1.5e-3, 1.5e-3) g; δ ~ N(0, 100 ppm).

Conventions randomised per record:
- Plan: input levels one of five_level {−1, −½, 0, ½, 1}, seven_level {±1, ±0.7, ±0.3, 0},
  three_level {−1, 0, 1}, tumble_45 (cos of 0°, 45°, …, 315°: duplicates included),
  tumble_30 (cos of 0°, 30°, …, 180°), the cosines rounded to 1e-6 g. A static row (no
  vibration) at every level. Sine amplitudes b3: 2–4 of {0.5, 1, 2, 3, 4, 5, 6, 8, 10} g;
  random RMS s: 1–3 of {1, …, 6} g, or none (25 %); vibration at every level (60 %) or
  only at {−1, 0, 1}. Sine and random never share a row. Inclined rows (80 %; always for
  the OA/PA classes, whose effect needs them): a shaker axis at 30°, 45° or 60° from IA
  towards OA, and one towards PA, amplitude A (1–2 values in 2–6 g): b3 = A cos, b1 (or
  b2) = A sin; 40 % (always for oa_pa) add a diagonal row b3 = b1 = b2 = A/√3; at every
  level (50 %) or at {−1, 0, 1}.
- Repeats: 80 % of plans repeat every condition (half of those) or a random 30–70 % of them
  (the other half) 2 or 3 times in all; a repeat is a new record (new phase, new random
  samples, new noise) at the same frequency. 20 %: no repeats.
- Row noise σ log-uniform 1e-6 … 1e-5 g (Gaussian, independent per row); a_out quantised
  to an LSB from {0, 1e-7, 5e-7} g. `vib_freq` ~ U(20, 500) Hz per condition (all rows;
  only frequency_dependent uses it). Row order shuffled in 50 % of records.
- Records: samples per row N ∈ {4096, 8192, 16384}, a whole number of sine cycles M ∈
  16…128 (per record), start phase U(0, 2π) per row. Random part: "white" (independent
  Gaussian samples) or "bandlimited" (white through a Butterworth low-pass of order 1–4,
  cut-off 0.05–0.5 of Nyquist, 2000-sample burn-in); in both the sample mean is removed and
  the record rescaled to RMS s exactly (so E[r] = 0 and E[r²] = s² hold per row; higher
  sample moments scatter as a finite Gaussian record's do).
  `draw(..., random="quantile")` instead uses Gaussian quantiles at N evenly spaced
  probabilities (white: random order; bandlimited: put in the filtered record's rank
  order), whose sample moments are fixed (odd ones 0): not what the brief asked, an option.
- Effect size: the effect's per-row contribution (per unit c) after the least-squares fit of
  a0 + δ a_in over the rows has RMS ρ; c = ±snr σ / ρ with snr log-uniform in 3…100 (the
  truth's `snr` is the achieved ratio, exactly). For k2_k6 the scaling is on the a3⁶ part.
The truth also gives `record_scatter_g`: the RMS over rows of the clean (noise-free) table
minus its expectation (exact sine moments, Gaussian r by Gauss–Hermite quadrature): the
finite records' own scatter, which adds to σ: it is 0 but on random rows, where a3³, a3⁶
and a3⁷ average to a finite record's sample moments, not the Gaussian ones.
"""

from __future__ import annotations

import zlib

import numpy as np
from scipy.signal import butter, lfilter
from scipy.special import ndtri

from accel_jax import VibrationData

CLASSES = ("none", "k6", "k7", "abs_square", "oa_square", "pa_square", "oa_pa",
           "ia_oa_square", "k2_k6", "frequency_dependent")
OUT_OF_TERMS = ("frequency_dependent",)
TERM_OF_CLASS = {"k6": ("k6",), "k7": ("k7",), "abs_square": ("abs_square",),
                 "oa_square": ("oa_square",), "pa_square": ("pa_square",), "oa_pa": ("oa_pa",),
                 "ia_oa_square": ("ia_oa_square",), "k2_k6": ("k2", "k6")}
TERMS = ("asymmetry", "k2", "k3", "k4", "k5", "k6", "k7", "m31", "m32", "abs_square",
         "oa_square", "pa_square", "oa_pa", "ia_oa_square", "frequency_dependent")
"""Coefficient names (ppm units); the regressor of each is in `_term_values`."""

def _cosines(degrees):
    """A dividing head's inputs: cos of each tilt, rounded to 1e-6 g (no −0)."""
    return tuple(float(np.round(np.cos(np.radians(d)), 6)) + 0.0 for d in degrees)


PLANS = {
    "five_level": (-1.0, -0.5, 0.0, 0.5, 1.0),
    "seven_level": (-1.0, -0.7, -0.3, 0.0, 0.3, 0.7, 1.0),
    "three_level": (-1.0, 0.0, 1.0),
    "tumble_45": _cosines(range(0, 360, 45)),
    "tumble_30": _cosines(range(0, 181, 30)),
}
SINE_GRID = (0.5, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0)
RMS_GRID = (1.0, 2.0, 3.0, 4.0, 5.0, 6.0)
SNR_RANGE = (3.0, 100.0)
_CROSS = {"oa_square", "pa_square", "oa_pa", "ia_oa_square"}


def resonance_gain(f, f_r, q):
    """|G(f)| of a second-order resonance (unit static gain)."""
    x = np.asarray(f, float) / f_r
    return 1.0 / np.sqrt((1.0 - x**2) ** 2 + (x / q) ** 2)


def _term_values(a3, a1, a2, a3_dyn):
    """The instantaneous regressor of every term (and "a3", the scale-factor regressor)."""
    p, powers = a3.copy(), {}
    for n in range(2, 8):
        p = p * a3
        powers[f"k{n}"] = p
    return {"a3": a3, "asymmetry": 0.5 * np.abs(a3), **powers, "m31": a3 * a1, "m32": a3 * a2,
            "abs_square": np.abs(a3) * a3, "oa_square": a1 * a1, "pa_square": a2 * a2,
            "oa_pa": a1 * a2, "ia_oa_square": a3 * a1 * a1, "frequency_dependent": a3_dyn**2}


def row_average(a_in, b3=0.0, b1=0.0, b2=0.0, s=0.0, *, samples=4096, cycles=16, phase=0.0,
                unit_random=None, gain=1.0):
    """The sample mean of every regressor over one row's record: `samples` samples over
    `cycles` whole sine cycles from start phase `phase`; `unit_random` the random part's
    shape (zero mean, unit RMS, length `samples`), scaled by `s`; `gain` = G(f)."""
    sine = np.sin(2 * np.pi * cycles * np.arange(samples) / samples + phase)
    rand = s * unit_random if s else 0.0
    vib = b3 * sine + rand
    vals = _term_values(a_in + vib, b1 * sine, b2 * sine, a_in + gain * vib)
    return {k: float(np.mean(np.broadcast_to(v, sine.shape))) for k, v in vals.items()}


def row_expectation(a_in, b3=0.0, b1=0.0, b2=0.0, s=0.0, *, gain=1.0, phases=64, nodes=80):
    """The expectation of every regressor: a uniform phase grid (exact for polynomials of
    degree < `phases` in sin) times probabilists' Gauss–Hermite nodes for r ~ N(0, s²)."""
    th = 2 * np.pi * np.arange(phases) / phases
    x, w = np.polynomial.hermite_e.hermegauss(nodes) if s else (np.zeros(1), np.ones(1))
    sine, r = np.sin(th)[:, None], s * x[None, :]
    weight = np.broadcast_to(w[None, :] / w.sum() / phases, (phases, len(x))).ravel()
    vib = b3 * sine + r
    vals = _term_values(a_in + vib, b1 * sine + 0 * r, b2 * sine + 0 * r, a_in + gain * vib)
    return {k: float(np.dot(np.broadcast_to(v, (phases, len(x))).ravel(), weight))
            for k, v in vals.items()}


def indicated(means, coefficients, bias=0.0, scale_factor_error=0.0):
    """a_out without noise: the row's mean indicated acceleration [g] from its regressor
    means and the coefficients in ppm units (names in TERMS)."""
    out = bias + (1.0 + scale_factor_error) * means["a3"]
    return out + 1e-6 * sum(c * means[k] for k, c in coefficients.items() if c)


def unit_random(rng, samples, kind, order=2, cutoff=0.2, mode="gaussian"):
    """A zero-mean, unit-RMS random record: "white" or "bandlimited" (Butterworth low-pass of
    `order`, cut-off `cutoff` × Nyquist); mode "gaussian" (samples) or "quantile"."""
    if kind == "white":
        x = rng.standard_normal(samples)
    else:
        b, a = butter(order, cutoff)
        x = lfilter(b, a, rng.standard_normal(samples + 2000))[2000:]
    if mode == "quantile":  # the quantiles, in x's rank order
        q, x = ndtri((np.arange(samples) + 0.5) / samples), x.copy()
        x[np.argsort(x)] = q
    x = x - x.mean()
    return x / np.sqrt(np.mean(x**2))


def _residual_rms(effect, a_in):
    """RMS over rows of `effect` after its least-squares fit by a0 + δ a_in."""
    basis = np.column_stack([np.ones_like(a_in), a_in])
    coef, *_ = np.linalg.lstsq(basis, effect, rcond=None)
    return float(np.sqrt(np.mean((effect - basis @ coef) ** 2)))


def _loguniform(rng, lo, hi):
    return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))


def _plan(rng, cls):
    """The test plan: conditions (a_in, b3, b1, b2, s) with their frequencies, and a summary."""
    name = str(rng.choice(list(PLANS)))
    levels = PLANS[name]
    amps = sorted(float(a) for a in rng.choice(SINE_GRID, rng.integers(2, 5), replace=False))
    rms = ([] if rng.random() < 0.25 else
           sorted(float(a) for a in rng.choice(RMS_GRID, rng.integers(1, 4), replace=False)))
    vib_levels = levels if rng.random() < 0.6 else (-1.0, 0.0, 1.0)
    inclined = cls in _CROSS or rng.random() < 0.8
    diagonal = inclined and (cls == "oa_pa" or rng.random() < 0.4)
    incl_amps = sorted(float(a) for a in np.round(rng.uniform(2, 6, rng.integers(1, 3)), 1))
    angle = float(rng.choice([30.0, 45.0, 60.0]))
    incl_levels = levels if rng.random() < 0.5 else (-1.0, 0.0, 1.0)
    cond = [(a, 0.0, 0.0, 0.0, 0.0) for a in levels]
    cond += [(a, b, 0.0, 0.0, 0.0) for a in vib_levels for b in amps]
    cond += [(a, 0.0, 0.0, 0.0, s) for a in vib_levels for s in rms]
    if inclined:
        c, sn = np.cos(np.radians(angle)), np.sin(np.radians(angle))
        for a in incl_levels:
            for A in incl_amps:
                cond += [(a, A * c, A * sn, 0.0, 0.0), (a, A * c, 0.0, A * sn, 0.0)]
                if diagonal:
                    cond.append((a, A / np.sqrt(3), A / np.sqrt(3), A / np.sqrt(3), 0.0))
    freq = rng.uniform(20.0, 500.0, len(cond))
    u = rng.random()
    count = 1 if u < 0.2 else int(rng.integers(2, 4))
    mode = "none" if u < 0.2 else ("all" if u < 0.6 else "subset")
    times = np.full(len(cond), count)
    if mode == "subset":
        times = np.where(rng.random(len(cond)) < rng.uniform(0.3, 0.7), count, 1)
    idx = np.repeat(np.arange(len(cond)), times)
    summary = {"plan": name, "levels": list(levels), "sine_amplitudes": amps, "random_rms": rms,
               "vibration_levels": list(vib_levels), "inclined": inclined,
               "inclined_amplitudes": incl_amps if inclined else [],
               "inclined_angle_deg": angle if inclined else None, "diagonal": diagonal,
               "repeats": {"mode": mode, "count": count}}
    return np.array(cond)[idx], freq[idx], summary


def draw(seed: int, cls: str, *, random: str = "gaussian"):
    """One vibration table of class `cls` and its truth (JSON-serialisable)."""
    if cls not in CLASSES:
        raise ValueError(f"unknown class {cls!r}; one of {CLASSES}")
    rng = np.random.default_rng([int(seed), zlib.crc32(cls.encode())])
    cond, freq, plan = _plan(rng, cls)
    samples = int(rng.choice([4096, 8192, 16384]))
    cycles = int(rng.integers(16, 129))
    kind = str(rng.choice(["white", "bandlimited"]))
    order, cutoff = int(rng.integers(1, 5)), float(rng.uniform(0.05, 0.5))
    lsb = float(rng.choice([0.0, 1e-7, 5e-7]))
    sigma = _loguniform(rng, 1e-6, 1e-5)
    bias, delta = float(rng.uniform(-1.5e-3, 1.5e-3)), float(rng.normal(0.0, 100e-6))
    coef = dict.fromkeys(TERMS, 0.0)
    if rng.random() < 0.3 or cls == "k2_k6":
        which = ["k2"] if cls == "k2_k6" else [["k2"], ["k3"], ["k2", "k3"]][rng.integers(3)]
        for k in which:
            coef[k] = float(rng.choice([-1, 1])) * _loguniform(rng, 0.3, 10.0)
    f_r, q = (float(rng.uniform(150, 600)), float(rng.uniform(2, 10))) \
        if cls == "frequency_dependent" else (None, None)
    gain = resonance_gain(freq, f_r, q) if f_r else np.ones(len(freq))
    means, expect = [], []
    for (a, b3, b1, b2, s), g in zip(cond, gain, strict=True):
        unit = unit_random(rng, samples, kind, order, cutoff, random) if s else None
        means.append(row_average(a, b3, b1, b2, s, samples=samples, cycles=cycles,
                                 phase=rng.uniform(0, 2 * np.pi), unit_random=unit, gain=g))
        expect.append(row_expectation(a, b3, b1, b2, s, gain=g))
    a_in = cond[:, 0]
    term = {"k2_k6": "k6"}.get(cls, cls)
    snr = None
    if cls != "none":
        rho = _residual_rms(np.array([m[term] for m in means]) * 1e-6, a_in)
        snr = _loguniform(rng, *SNR_RANGE)
        coef[term] = float(rng.choice([-1, 1])) * snr * sigma / rho
        snr = abs(coef[term]) * rho / sigma  # achieved (= the drawn value)
    clean = np.array([indicated(m, coef, bias, delta) for m in means])
    ideal = np.array([indicated(m, coef, bias, delta) for m in expect])
    a_out = clean + rng.normal(0.0, sigma, len(clean))
    if lsb:
        a_out = np.round(a_out / lsb) * lsb
    order_rows = rng.permutation(len(a_out)) if rng.random() < 0.5 else np.arange(len(a_out))
    col = lambda v: np.ascontiguousarray(np.asarray(v, float)[order_rows])  # noqa: E731
    data = VibrationData(
        a_in=col(a_in), vib_amp=col(cond[:, 1]), vib_freq=col(freq), vib_rms=col(cond[:, 4]),
        a_out=col(a_out), vib_amp_oa=col(cond[:, 2]) if plan["inclined"] else None,
        vib_amp_pa=col(cond[:, 3]) if plan["inclined"] else None)
    scatter = clean - ideal
    truth = {"class": cls, "seed": int(seed), "random_mode": random, **coef,
             "terms": [k for k, v in coef.items() if v], "bias_g": bias,
             "scale_factor_error": delta, "row_noise_g": sigma, "snr": snr, **plan,
             "samples": samples, "cycles": cycles,
             "random_kind": kind if plan["random_rms"] else None,
             "filter": {"order": order, "cutoff": cutoff}
             if kind == "bandlimited" and plan["random_rms"] else None,
             "lsb": lsb, "f_r": f_r, "Q": q, "shuffled": bool(np.any(np.diff(order_rows) != 1)),
             "rows": int(len(a_out)),
             "record_scatter_g": float(np.sqrt(np.mean(scatter**2))),
             "record_scatter_max_g": float(np.max(np.abs(scatter)))}
    return data, truth


def draw_many(seed: int, cls: str, count: int, **kw):
    """`count` records; the i-th is draw(s_i, cls) with s_i = truth["seed"], derived from
    (seed, i), so any one can be redrawn alone."""
    seeds = [int(np.random.SeedSequence([int(seed), i]).generate_state(1)[0])
             for i in range(count)]
    return [draw(s, cls, **kw) for s in seeds]
