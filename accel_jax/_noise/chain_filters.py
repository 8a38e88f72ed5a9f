"""The low-pass shapes of a sensor's signal chain, as gains on the spectrum of the noise they
filter: the Butterworth low-pass (`models.ButterworthLowPass`), the Bessel low-pass
(`BesselLowPass`), the moving average of M samples (`MovingAverage`, an FIR boxcar at
the logged rate) and the decimating average (`DecimatingAverage`, a CIC decimator).
`low_pass_gain` evaluates the one a traced code names (`code`), so that one compiled fit
serves every shape (the code travels in the structure's mask).

The Bessel low-pass of order N is the analog filter B_N(0)/B_N(κ_N s) (B_N the reverse
Bessel polynomial, κ_N placing its −3 dB point at s = j) taken to discrete time by the
bilinear transform with the corner prewarped, as `scipy.signal.bessel(N, f_b,
norm="mag", fs=1/Δ)` designs it: its power gain is 1/Q_N(κ_N² r²) with r = tan(ω/2)/tan(π
f_b Δ) and Q_N(ω²) = |B_N(jω)|²/B_N(0)², a polynomial in ω² with positive coefficients, so
that f_b is the filter's −3 dB point (a Bessel filter designed by its phase or delay has
its −3 dB point elsewhere: the fit reports where the gain is one half). The moving average
of M samples has the power gain (sin(Mω/2)/(M sin(ω/2)))², nulls at multiples of 1/(MΔ);
its −3 dB point (`moving_average_corner`) is a function of M alone.

A decimating average (`DecimatingAverage`: a CIC or sinc^K decimation filter) is a cascade
of K moving averages of R samples at a converter's rate R/Δ, every R-th output logged. The
filter's impulse response h (the K-fold convolution of R-sample boxcars, Σ h = 1) spans
K(R − 1) + 1 fast samples, so the logged noise is a moving average of order K − 1: its
autocorrelation ρ_j = R Σ_m h_m h_{m+jR} vanishes beyond lag K − 1, and its power gain on
white noise at the fast rate (the R images of the logged band folded onto it) is
ρ_0 + 2 Σ_{j=1}^{K−1} ρ_j cos jω, 1 at ω = 0 (each of h's R polyphase sums is 1/R). One
stage (K = 1) gives block means, exactly white: nothing to fit.
"""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike

from .._params import _as_float
from .models import ButterworthLowPass, _frequencies, _positive_fields
from .record import Scalar

BESSEL_ORDERS = (2, 3, 4)
MAX_TAPS = 64
"""The longest moving average the selection tries."""

BESSEL_CODE = 10
"""`code` of a Bessel low-pass of order N: 10 + N (a Butterworth one's is N, 1–4)."""
MOVING_AVERAGE_CODE = 100
"""`code` of a moving average of M samples: 100 + M."""
DECIMATION_STAGES = (2, 3, 4)
"""The decimating averages' numbers of stages K the selection tries."""
MAX_RATIO = 32
"""The largest decimation ratio R of a decimating average."""
DECIMATION_CODE = 1000
"""`code` of a decimating average of K stages and ratio R: 1000 + 100 K + R."""


def _bessel_power_polynomial(order: int) -> tuple[np.ndarray, float]:
    """(c_0..c_N with Q_N(x) = Σ c_k x^k = |B_N(j√x)|²/B_N(0)², κ_N² with Q_N(κ_N²) = 2)."""
    fact = math.factorial
    a = [
        fact(2 * order - k) / (2 ** (order - k) * fact(k) * fact(order - k))
        for k in range(order + 1)
    ]  # B_N(s) = Σ a_k s^k
    p = np.polynomial.Polynomial(a)
    q = p * np.polynomial.Polynomial([a_k * (-1) ** k for k, a_k in enumerate(a)])  # B(s)B(−s)
    # even in s; with s² = −x: Q(x) = Σ q_{2k} (−1)^k x^k / a_0²
    c = np.array([q.coef[2 * k] * (-1) ** k for k in range(order + 1)]) / a[0] ** 2
    roots = np.polynomial.Polynomial(c - np.eye(order + 1)[0] * 2).roots()
    kappa2 = float(min(r.real for r in roots if abs(r.imag) < 1e-9 and r.real > 0))
    return c, kappa2


def _bessel_table() -> np.ndarray:
    """Per order 2–4 (rows), the coefficients of Q_N(κ_N² r²) in r² (x = κ² r²), padded."""
    table = np.zeros((len(BESSEL_ORDERS), max(BESSEL_ORDERS) + 1))
    for i, order in enumerate(BESSEL_ORDERS):
        c, kappa2 = _bessel_power_polynomial(order)
        table[i, : order + 1] = c * kappa2 ** np.arange(order + 1)
    return table


_BESSEL = _bessel_table()


class BesselLowPass(eqx.Module):
    """A sensor's output low-pass of the Bessel kind (maximally flat group delay), order N
    (2–4; the bilinear transform), −3 dB point f_b (module docstring). A gain on the
    spectrum of the noise it filters. **Fields:** `corner_frequency`: f_b [Hz], where the
    power gain is one half; `order`: N (default 2)."""

    corner_frequency: Scalar = eqx.field(converter=_as_float)
    order: int = eqx.field(static=True, default=2)

    def __check_init__(self):
        _positive_fields(self, {"corner_frequency": "Hz"})
        if self.order not in BESSEL_ORDERS:
            raise ValueError(f"BesselLowPass order must be 2, 3 or 4, got {self.order!r}.")

    @staticmethod
    def discrete_gain(omega, corner, order: ArrayLike = 2) -> Array:
        """H(ω) at `corner` = π f_b Δ ∈ (0, π/2] for |ω| ≤ π and order N ∈ {2, 3, 4} (traced
        or not)."""
        r2 = ButterworthLowPass.squared_ratio(omega, corner)
        row = jnp.asarray(_BESSEL)[jnp.clip(jnp.asarray(order) - 2, 0, 2).astype(int)]
        q = row[-1]
        for k in range(row.shape[0] - 2, -1, -1):  # Horner in r²
            q = q * r2 + row[k]
        return 1 / q

    def gain(self, omega, sample_interval) -> Array:
        corner = math.pi * self.corner_frequency * sample_interval
        return self.discrete_gain(omega, corner, self.order)


class MovingAverage(eqx.Module):
    """The mean of the last M samples at the logged rate (an FIR boxcar: a converter's
    averaging, a logger's running mean), power gain (sin(Mω/2)/(M sin(ω/2)))². A gain on the
    spectrum of the noise it filters. **Fields:** `taps`: M (2–`MAX_TAPS`)."""

    taps: int = eqx.field(static=True)

    def __check_init__(self):
        if not (isinstance(self.taps, int) and 2 <= self.taps <= MAX_TAPS):
            raise ValueError(
                f"MovingAverage taps must be an integer 2..{MAX_TAPS}, got {self.taps!r}."
            )

    @property
    def corner_frequency(self) -> float:
        """The −3 dB point in cycles per sample (multiply by the sample rate for Hz)."""
        return moving_average_corner(self.taps)

    @staticmethod
    def discrete_gain(omega, taps) -> Array:
        """H(ω) of M = `taps` samples (traced or not) for |ω| ≤ π (1 at ω = 0)."""
        f = _frequencies(omega)
        taps = jnp.asarray(taps, f.omega.dtype)
        small = jnp.abs(f.half_sin) < 1e-12
        ratio = jnp.sin(taps * f.omega / 2) / (taps * jnp.where(small, 1.0, f.half_sin))
        return jnp.where(small, 1.0, ratio**2)

    def gain(self, omega, sample_interval) -> Array:
        del sample_interval  # a function of ω per sample alone
        return self.discrete_gain(omega, self.taps)


def decimation_correlation(stages: int, ratio: int) -> np.ndarray:
    """ρ_0..ρ_{K−1} of a decimating average (module docstring): the logged noise's
    autocorrelation per unit white variance at the logged rate."""
    h = np.ones(1)
    for _ in range(stages):
        h = np.convolve(h, np.ones(ratio) / ratio)
    padded = np.concatenate([h, np.zeros(stages * ratio)])
    lags = [padded[j * ratio : j * ratio + h.size] for j in range(stages)]
    return np.array([ratio * float(h @ lag) for lag in lags])


def _decimation_table() -> np.ndarray:
    """ρ_0, 2ρ_1, …, 2ρ_{K−1} (padded) per stages K (rows from 1) and ratio R (columns from 1)."""
    table = np.zeros((max(DECIMATION_STAGES) + 1, MAX_RATIO + 1, max(DECIMATION_STAGES)))
    for stages in range(1, max(DECIMATION_STAGES) + 1):
        for ratio in range(1, MAX_RATIO + 1):
            rho = decimation_correlation(stages, ratio)
            table[stages, ratio, : rho.size] = rho * np.where(np.arange(rho.size) > 0, 2.0, 1.0)
    return table


_DECIMATION = _decimation_table()


class DecimatingAverage(eqx.Module):
    """A converter's decimation filter: K cascaded moving averages of R samples at R times
    the logged rate, every R-th output logged (a CIC or sinc^K decimator). A gain on the
    spectrum of the noise it filters, the folded images included (module docstring).
    **Fields:** `stages`: K (2–4); `ratio`: R (2–`MAX_RATIO`)."""

    stages: int = eqx.field(static=True)
    ratio: int = eqx.field(static=True)

    def __check_init__(self):
        if self.stages not in DECIMATION_STAGES:
            raise ValueError(
                f"DecimatingAverage stages must be 2, 3 or 4, got {self.stages!r}."
            )
        if not (isinstance(self.ratio, int) and 2 <= self.ratio <= MAX_RATIO):
            raise ValueError(
                f"DecimatingAverage ratio must be an integer 2..{MAX_RATIO}, got {self.ratio!r}."
            )

    @property
    def corner_frequency(self) -> float:
        """The filter's own −3 dB point (`decimation_corner`) in cycles per logged sample
        (multiply by the sample rate for Hz)."""
        return decimation_corner(self.stages, self.ratio)

    @staticmethod
    def discrete_gain(omega, stages, ratio) -> Array:
        """The power gain of K = `stages`, R = `ratio` (traced or not) for |ω| ≤ π."""
        f = _frequencies(omega)
        k = jnp.clip(jnp.asarray(stages), 1, max(DECIMATION_STAGES)).astype(int)
        r = jnp.clip(jnp.asarray(ratio), 1, MAX_RATIO).astype(int)
        row = jnp.asarray(_DECIMATION, f.omega.dtype)[k, r]
        out = row[0] * jnp.ones_like(f.omega)
        for j in range(1, row.shape[0]):
            out = out + row[j] * jnp.cos(j * f.omega)
        return out

    def gain(self, omega, sample_interval) -> Array:
        del sample_interval  # a function of ω per sample alone
        return self.discrete_gain(omega, self.stages, self.ratio)


def decimation_corner(stages: int, ratio: int) -> float:
    """The decimation filter's own −3 dB point (as its data sheet gives it: where the K
    cascaded boxcars pass half the power at the converter's rate, the folded images left
    out), in cycles per logged sample: R times the −3 dB point of a moving average of R
    samples raised to the power K (bisection to 1e-12; → 0.3195 for K = 2 and many
    samples)."""
    # the gain falls monotonically to its first null
    return ratio * _half_power(lambda f: _boxcar_power(ratio, f) ** stages, 1e-12, 1.0 / ratio)


@functools.cache  # a constant of (K, R), asked for each fitted corner of every selection
def folded_corner(stages: int, ratio: int) -> float:
    """Where the logged response of a decimating average (its folded images included)
    passes half the power, in cycles per logged sample (bisection to 1e-12): what a
    low-pass fitted to the record in its place reports; 0.5 for K = 2, R = 2."""
    rho = _DECIMATION[stages, ratio]

    def gain(f):
        return sum(c * math.cos(2 * math.pi * j * f) for j, c in enumerate(rho))

    return 0.5 if gain(0.5) >= 0.5 else _half_power(gain, 0.0, 0.5)


def _boxcar_power(taps: int, f: float) -> float:
    """(sin(π M f)/(M sin(π f)))²: the power gain of a moving average of M samples at f
    cycles per sample."""
    return (math.sin(math.pi * taps * f) / (taps * math.sin(math.pi * f))) ** 2


def _half_power(gain, lo: float, hi: float) -> float:
    """Where a gain falling monotonically over [lo, hi] passes one half (bisection, 60
    halvings)."""
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if gain(mid) > 0.5 else (lo, mid)
    return 0.5 * (lo + hi)


def moving_average_corner(taps: int) -> float:
    """The −3 dB point of a moving average of `taps` samples, in cycles per sample
    (bisection on its gain to 1e-12; 0.25 for two samples, → 0.4430/M for many)."""
    # the gain falls monotonically to its first null
    return _half_power(lambda f: _boxcar_power(taps, f), 1e-9, min(0.5, 1.0 / taps))


def nearest_taps(corner_per_sample: float) -> int:
    """The moving average whose −3 dB point lies nearest `corner_per_sample` (cycles per
    sample): a start for the taps from a fitted corner."""
    taps = range(2, MAX_TAPS + 1)
    return min(taps, key=lambda m: abs(math.log(moving_average_corner(m) / corner_per_sample)))


def code_kind(code: float) -> tuple[str, int]:
    """(shape, N or M) of a low-pass `code`: ("butterworth", N), ("bessel", N),
    ("moving_average", M) or ("decimating_average", 100 K + R)."""
    code = int(round(float(code)))
    if code >= DECIMATION_CODE:
        return "decimating_average", code - DECIMATION_CODE
    if code >= MOVING_AVERAGE_CODE:
        return "moving_average", code - MOVING_AVERAGE_CODE
    if code >= BESSEL_CODE:
        return "bessel", code - BESSEL_CODE
    return "butterworth", code


def low_pass(code: float, corner_frequency: float):
    """The low-pass module of a concrete `code` and corner f_b [Hz] (unused by a moving
    average, whose M sets its corner)."""
    kind, n = code_kind(code)
    if kind == "decimating_average":
        return DecimatingAverage(*divmod(n, 100))
    if kind == "moving_average":
        return MovingAverage(n)
    if kind == "bessel":
        return BesselLowPass(corner_frequency, order=n)
    return ButterworthLowPass(corner_frequency, order=n)


def low_pass_gain(omega, corner, code) -> Array:
    """The power gain of the low-pass a (traced) `code` names, at `corner` = π f_b Δ (a
    moving average or a decimating average: its M, or K and R, from the code, `corner`
    unused). One branch runs (`lax.switch`; under `vmap` all four, then a select)."""
    omega = _frequencies(omega)
    code = jnp.asarray(code)
    branch = jnp.where(code >= MOVING_AVERAGE_CODE, 2, jnp.where(code >= BESSEL_CODE, 1, 0))
    branch = jnp.where(code >= DECIMATION_CODE, 3, branch)
    stages_ratio = code - DECIMATION_CODE
    return jax.lax.switch(
        branch,
        (
            lambda: ButterworthLowPass.discrete_gain(omega, corner, code),
            lambda: BesselLowPass.discrete_gain(omega, corner, code - BESSEL_CODE),
            lambda: MovingAverage.discrete_gain(omega, code - MOVING_AVERAGE_CODE),
            lambda: DecimatingAverage.discrete_gain(
                omega, jnp.floor(stages_ratio / 100), jnp.mod(stages_ratio, 100)
            ),
        ),
    )
