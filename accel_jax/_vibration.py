"""Vibration error of a navigation accelerometer (SPEC.md §3): exact expectation,
the paper's closed forms (3)-(5), (19), (20), a time-domain Monte Carlo check, the shaker
estimator (16) and the in-flight compensation algorithm (17)-(20).

The vibration error is the mean indicated acceleration under vibration minus the indicated
acceleration without it, δ_V = E[a_F(a + v)] − a_F(a), for the static transfer function of
`accel_jax._static` (in g). Vibration: a sinusoid of one frequency on each axis (amplitude,
phase) plus zero-mean stationary Gaussian random vibration (RMS per axis, correlation
between axes; band PSDs with the η(f) factors of the paper's Table 1 via `random_rms`).

Precision: vibration errors are ppm-level differences of O(1 g) numbers: evaluate in
float64 (float32 leaves ~0.1 ppm of rounding per evaluation and more after the subtraction).
The functions keep the caller's dtype and do not change JAX's settings.
"""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import erf
from jaxtyping import Array, ArrayLike, Float

from ._params import _concrete, _shown
from ._static import StaticTransferFunction, _as_float, basic_error, indicated_acceleration

AXES = ("OA (a1)", "PA (a2)", "IA (a3)")
"""Axis order of every per-axis vector here: the paper's numbering 1, 2, 3."""

ASYMMETRY_SINE_FACTOR = 0.673
"""The paper's factor in A1·(0.673 b − 0.5 a) (eqs. 4, 19); the exact sine average of |a3|
with a = 0 gives 2/π ≈ 0.637 (see `mean_abs_sine`)."""
ASYMMETRY_RANDOM_FACTOR = 0.125
"""The paper's factor in 0.125·A1·σ (eqs. 13, 20); the exact Gaussian value with a = 0 is
½·sqrt(2/π) ≈ 0.399."""


def _vec3(value) -> Array:
    array = _as_float(value)
    if array.ndim == 0:  # one value for every axis
        return jnp.full(3, array)
    if array.shape[-1] != 3:
        raise ValueError(
            f"VibrationEnvironment: per-axis values need 3 entries (OA, PA, IA), got shape "
            f"{array.shape}: {array!r}."
        )
    return array


def _corr3(value) -> Array:
    array = _as_float(value)
    if array.ndim == 0:  # one ρ for every pair of axes
        return (1 - array) * jnp.eye(3, dtype=array.dtype) + array
    return array


class VibrationEnvironment(eqx.Module):
    """Vibration acting on the accelerometer: a sinusoid plus Gaussian random vibration.

    On axis i (1 = OA, 2 = PA, 3 = IA, stored in that order):

        v_i(t) = b_i sin(2π f t + φ_i) + r_i(t),
        r(t) zero-mean stationary Gaussian, Var r_i = σ_i², Corr(r_i, r_j) = ρ_ij.

    Only the distribution of v(t) at one instant matters for the mean output of a static
    transfer function; the frequency and the random band are used by the time-domain
    synthesis (`synthesize_vibration`) only.

    **Fields:**

    - `sine_amplitude`: b_i [g], shape (3,), ≥ 0.
    - `sine_phase`: φ_i [rad], shape (3,).
    - `sine_frequency`: f [Hz] > 0.
    - `random_std`: σ_i [g], shape (3,), ≥ 0.
    - `random_correlation`: ρ [1], shape (3, 3), symmetric, unit diagonal, |ρ_ij| ≤ 1.
    - `random_band`: (f_low, f_high) [Hz] of the flat-spectrum synthesis, 0 < f_low < f_high.
    """

    sine_amplitude: Float[Array, 3] = eqx.field(converter=_vec3, default=0.0)
    sine_phase: Float[Array, 3] = eqx.field(converter=_vec3, default=0.0)
    sine_frequency: Float[Array, ""] = eqx.field(converter=_as_float, default=30.0)
    random_std: Float[Array, 3] = eqx.field(converter=_vec3, default=0.0)
    random_correlation: Float[Array, "3 3"] = eqx.field(converter=_corr3, default=0.0)
    random_band: Float[Array, 2] = eqx.field(converter=_as_float, default=(20.0, 2000.0))

    def __check_init__(self):
        def check(name, ok, what, unit):
            value = _concrete(getattr(self, name))
            if value is None:
                return
            if not np.all(np.isfinite(value)) or not ok(value):
                raise ValueError(f"VibrationEnvironment.{name} {what}, got {value!r} {unit}.")

        check(
            "sine_amplitude",
            lambda v: v.shape[-1:] == (3,) and np.all(v >= 0),
            "must be 3 non-negative amplitudes (use the phase for the sign)",
            "g",
        )
        check("sine_phase", lambda v: v.shape[-1:] == (3,), "must have 3 phases", "rad")
        check("sine_frequency", lambda v: np.all(v > 0), "must be positive", "Hz")
        check(
            "random_std",
            lambda v: v.shape[-1:] == (3,) and np.all(v >= 0),
            "must be 3 non-negative RMS values",
            "g",
        )
        check(
            "random_correlation",
            lambda v: (
                v.shape[-2:] == (3, 3)
                and np.allclose(v, np.swapaxes(v, -1, -2))
                and np.allclose(np.diagonal(v, axis1=-2, axis2=-1), 1.0)
                and np.all(np.abs(v) <= 1 + 1e-12)
            ),
            "must be a symmetric 3×3 correlation matrix with unit diagonal and |ρ| ≤ 1",
            "",
        )
        check(
            "random_band",
            lambda v: v.shape[-1:] == (2,) and np.all((v[..., 0] > 0) & (v[..., 1] > v[..., 0])),
            "must be (f_low, f_high), 0 < f_low < f_high",
            "Hz",
        )

    @property
    def random_covariance(self) -> Array:
        """Σ_ij = ρ_ij σ_i σ_j [g²]."""
        s = self.random_std
        return self.random_correlation * s[..., :, None] * s[..., None, :]


def random_rms(psd: ArrayLike, band_width: ArrayLike, eta: ArrayLike = 1.0, *, paper: bool = True):
    """RMS random vibration from band PSDs with the mounting/sensor response factors η.

    **Arguments:**

    - `psd`: S_j [g²/Hz] per band.
    - `band_width`: Δf_j [Hz] per band.
    - `eta`: η(f_j) [1] per band (the paper's Table 1: the BINS mount and the sensor's own
      frequency response).
    - `paper`: True gives the paper's σ = sqrt((1/n) Σ_j η_j S_j Δf_j) (the mean over the n
      bands); False gives the variance-additive σ = sqrt(Σ_j η_j S_j Δf_j).

    **Returns:** σ [g]. (The paper's Table 1 quotes 1.4 for Cyclone-4, which is the mean
    square (1/n) Σ η S Δf ≈ 1.4 g² itself; its RMS is ≈ 1.18 g. See the study.)
    """
    psd, band_width, eta = (jnp.asarray(x) for x in (psd, band_width, eta))
    for name, value in (("psd", psd), ("band_width", band_width), ("eta", eta)):
        concrete = _concrete(value)
        if concrete is not None and not np.all(concrete >= 0):
            unit = {"psd": "g²/Hz", "band_width": "Hz", "eta": ""}[name]
            raise ValueError(
                f"random_rms: {name} must be non-negative, got {_shown(concrete)} {unit}."
            )
    power = eta * psd * band_width
    total = jnp.sum(power)
    return jnp.sqrt(total / power.size) if paper else jnp.sqrt(total)


def _vec(value) -> Array:
    return jnp.atleast_1d(_as_float(value))


class BandSpectrum(eqx.Module):
    """Random vibration along one axis given by its power spectral density in frequency
    bands, with the mounting/sensor response factors η of the paper's Table 1:

        σ² = Σ_j η_j S_j Δf_j  (variance-additive),   σ_paper = sqrt((1/n) Σ_j η_j S_j Δf_j).

    Bands are [f_low_j, f_high_j], in ascending order and non-overlapping (adjacent bands
    may share an edge), so that every frequency is counted once.

    **Fields:**

    - `f_low`, `f_high`: band edges [Hz], shape (n,), 0 ≤ f_low_j < f_high_j ≤ f_low_{j+1}.
    - `psd`: S_j [g²/Hz] ≥ 0, the (mean) PSD in each band.
    - `eta`: η_j [1] ≥ 0 (default 1: no mount/sensor response weighting).
    """

    f_low: Float[Array, " n"] = eqx.field(converter=_vec)
    f_high: Float[Array, " n"] = eqx.field(converter=_vec)
    psd: Float[Array, " n"] = eqx.field(converter=_vec)
    eta: Float[Array, " n"] = eqx.field(converter=_vec, default=1.0)

    def __check_init__(self):
        values = {n: _concrete(getattr(self, n)) for n in ("f_low", "f_high", "psd", "eta")}
        if any(v is None for v in values.values()):
            return
        lo, hi, psd, eta = (values[n] for n in ("f_low", "f_high", "psd", "eta"))
        n = lo.shape[-1]
        for name, v in values.items():
            if v.ndim != 1 or v.shape[0] not in ((n, 1) if name == "eta" else (n,)):
                raise ValueError(
                    f"BandSpectrum.{name} must be 1-D with one entry per band ({n} bands from "
                    f"f_low), got shape {v.shape}: {v!r}."
                )
            if not np.all(np.isfinite(v)):
                raise ValueError(f"BandSpectrum.{name} must be finite, got {_shown(v)}.")
        for name, v, unit in (("psd", psd, "g²/Hz"), ("eta", eta, ""), ("f_low", lo, "Hz")):
            if np.any(v < 0):
                raise ValueError(
                    f"BandSpectrum.{name} must be non-negative, got {_shown(v)} {unit}."
                )
        bad = np.flatnonzero(~(hi > lo))
        if bad.size:
            j = int(bad[0])
            raise ValueError(
                f"BandSpectrum: band {j} is empty or reversed, [{float(lo[j])!r}, "
                f"{float(hi[j])!r}] Hz; each band needs f_low < f_high."
            )
        unordered = np.flatnonzero(np.diff(lo) <= 0)
        if unordered.size:
            j = int(unordered[0])
            raise ValueError(
                f"BandSpectrum: bands are not in ascending order (band {j + 1} starts at "
                f"{float(lo[j + 1])!r} Hz, band {j} at {float(lo[j])!r} Hz); sort the bands by "
                "frequency."
            )
        overlap = np.flatnonzero(lo[1:] < hi[:-1])
        if overlap.size:
            j = int(overlap[0])
            raise ValueError(
                f"BandSpectrum: bands {j} [{float(lo[j])!r}, {float(hi[j])!r}] Hz and {j + 1} "
                f"[{float(lo[j + 1])!r}, {float(hi[j + 1])!r}] Hz overlap; split the spectrum so "
                "that every frequency belongs to one band."
            )

    @property
    def band_width(self) -> Array:
        """Δf_j = f_high_j − f_low_j [Hz]."""
        return self.f_high - self.f_low

    @property
    def band(self) -> Array:
        """(lowest, highest) frequency covered [Hz] (for `VibrationEnvironment.random_band`)."""
        return jnp.stack([self.f_low[0], self.f_high[-1]])

    def rms(self, *, paper: bool = True) -> Array:
        """σ [g]: the paper's sqrt((1/n) Σ η S Δf) (`paper=True`) or the variance-additive
        sqrt(Σ η S Δf) (`paper=False`); see `random_rms`."""
        eta = jnp.broadcast_to(self.eta, self.psd.shape)
        return random_rms(self.psd, self.band_width, eta, paper=paper)

    @classmethod
    def cyclone4(cls) -> BandSpectrum:
        """The paper's Table 1 (Cyclone-4 random vibration along IA): octave bands 20-640 Hz,
        PSD at the midpoint of each printed range (0.0165, 0.0185, 0.045, 0.095, 0.12 g²/Hz),
        η = 1.6, 1.8, 0.4, 0.1, 0.05. `rms()` gives 1.16 g (1.18 g from the table's printed
        per-band column); the paper prints σ_V3 = 1.4, which is the mean square
        (1/n) Σ η S Δf ≈ 1.35-1.40 g² itself (see the tolerance-limits study)."""
        return cls(
            f_low=(20.0, 40.0, 80.0, 160.0, 320.0),
            f_high=(40.0, 80.0, 160.0, 320.0, 640.0),
            psd=(0.0165, 0.0185, 0.045, 0.095, 0.12),
            eta=(1.6, 1.8, 0.4, 0.1, 0.05),
        )


# --- exact expectation ------------------------------------------------------------------


def mean_abs_sine(a: ArrayLike, amplitude: ArrayLike) -> Array:
    """Exact time average of |a + b sin θ| over θ (closed form), b ≥ 0:

    |a|                                             if b ≤ |a|
    (2/π) (sqrt(b² − a²) + a·arcsin(a/b))           otherwise          [g]
    """
    a = jnp.asarray(a)
    b = jnp.asarray(amplitude)
    crosses = b > jnp.abs(a)
    b_safe = jnp.where(crosses, b, 1.0)
    r = jnp.where(crosses, a / b_safe, 0.0)
    value = (2 / math.pi) * (b_safe * jnp.sqrt(1 - r**2) + a * jnp.arcsin(r))
    return jnp.where(crosses, value, jnp.abs(a))


def mean_abs_gauss(mean: ArrayLike, std: ArrayLike) -> Array:
    """Exact E|μ + σ Z|, Z ~ N(0, 1) (folded normal): σ sqrt(2/π) e^{−μ²/2σ²} + μ erf(μ/σ√2);
    |μ| at σ = 0 (gradient-safe there)."""
    mu = jnp.asarray(mean)
    sigma = jnp.asarray(std)
    positive = sigma > 0
    s = jnp.where(positive, sigma, 1.0)
    value = s * math.sqrt(2 / math.pi) * jnp.exp(-0.5 * (mu / s) ** 2) + mu * erf(
        mu / (s * math.sqrt(2))
    )
    return jnp.where(positive, value, jnp.abs(mu))


def _phase_grid(n_phase: int, dtype) -> Array:
    return 2 * jnp.pi * jnp.arange(n_phase, dtype=dtype) / n_phase


def _hermite(n: int, dtype):
    nodes, weights = np.polynomial.hermite_e.hermegauss(n)
    return jnp.asarray(nodes, dtype), jnp.asarray(weights / weights.sum(), dtype)


def _check_orders(n_phase: int, n_hermite: int) -> None:
    if not isinstance(n_phase, int) or n_phase < 6:
        raise ValueError(
            f"n_phase must be an int ≥ 6 (exact phase average of the degree-5 polynomial), "
            f"got {n_phase!r}."
        )
    if not isinstance(n_hermite, int) or n_hermite < 3:
        raise ValueError(
            f"n_hermite must be an int ≥ 3 (Gauss-Hermite exact to degree 2n−1 ≥ 5), "
            f"got {n_hermite!r}."
        )


def mean_abs_input(env: VibrationEnvironment, a3: ArrayLike, *, n_phase: int = 512) -> Array:
    """E|a3 + v3| [g] under `env`: the exact Gaussian average (folded normal) at each of
    `n_phase` equispaced phases, averaged over the phase; the closed form `mean_abs_sine`
    when σ3 = 0. The phase average converges exponentially in n_phase·σ3/b3 (smooth
    integrand); 512 phases give < 1e-12 relative error for σ3/b3 ≥ 0.05."""
    a3 = jnp.asarray(a3)
    b3 = env.sine_amplitude[2]
    s3 = env.random_std[2]
    theta = _phase_grid(n_phase, jnp.result_type(a3, b3))
    mu = a3[..., None] + b3 * jnp.sin(theta + env.sine_phase[2])
    gauss = jnp.mean(mean_abs_gauss(mu, s3), axis=-1)
    return jnp.where(s3 > 0, gauss, mean_abs_sine(a3, b3))


def mean_indicated_acceleration(
    tf: StaticTransferFunction,
    env: VibrationEnvironment,
    a3: ArrayLike,
    a1: ArrayLike = 0.0,
    a2: ArrayLike = 0.0,
    *,
    n_phase: int = 512,
    n_hermite: int = 6,
) -> Array:
    """Exact expectation of the indicated acceleration a_F (eq. 1) under vibration.

    The polynomial part in a3 (k2..k5) by `n_phase` equispaced phases × `n_hermite`
    Gauss-Hermite nodes in the random part of a3 — both exact for a degree-5 polynomial
    (trigonometric degree 5 < n_phase; 2·n_hermite − 1 ≥ 5). The asymmetry term ½A1|a3|
    by `mean_abs_input` (exact in the Gaussian part, exponentially convergent in phase).
    The cross terms by the exact second moments:
    E[a3 a_i] = a3 a_i + ½ b3 b_i cos(φ3 − φ_i) + ρ_3i σ3 σ_i. Linear terms are unchanged
    by zero-mean vibration.

    **Arguments:**

    - `tf`: transfer-function coefficients; `env`: the vibration.
    - `a3`, `a1`, `a2`: the steady (mean) apparent accelerations [g]; broadcast together.
    - `n_phase`, `n_hermite`: quadrature orders (Python ints, static).

    **Returns:** E[a_F] [g]. jit/vmap/grad-safe in every argument. float64 advised.
    """
    _check_orders(n_phase, n_hermite)
    a3, a1, a2 = jnp.broadcast_arrays(*(jnp.asarray(x) for x in (a3, a1, a2)))
    dtype = jnp.result_type(a3, env.sine_amplitude, tf.k2)
    b, phi, sigma = env.sine_amplitude, env.sine_phase, env.random_std
    theta = _phase_grid(n_phase, dtype)
    nodes, weights = _hermite(n_hermite, dtype)
    # a3 on the (…, phase, node) grid
    x = a3[..., None, None] + b[2] * jnp.sin(theta + phi[2])[:, None] + sigma[2] * nodes[None, :]
    poly = tf.k2 * x**2 + tf.k3 * x**3 + tf.k4 * x**4 + tf.k5 * x**5
    poly_mean = jnp.mean(jnp.sum(poly * weights, axis=-1), axis=-1)
    rho = env.random_correlation
    cross1 = (
        a3 * a1 + 0.5 * b[2] * b[0] * jnp.cos(phi[2] - phi[0]) + rho[2, 0] * sigma[2] * sigma[0]
    )
    cross2 = (
        a3 * a2 + 0.5 * b[2] * b[1] * jnp.cos(phi[2] - phi[1]) + rho[2, 1] * sigma[2] * sigma[1]
    )
    return (
        tf.bias
        + (1 + tf.scale_factor_error) * a3
        + 0.5 * tf.asymmetry * mean_abs_input(env, a3, n_phase=n_phase)
        + poly_mean
        + tf.m1 * a1
        + tf.m2 * a2
        + tf.m31 * cross1
        + tf.m32 * cross2
    )


def vibration_error(
    tf: StaticTransferFunction,
    env: VibrationEnvironment,
    a3: ArrayLike,
    a1: ArrayLike = 0.0,
    a2: ArrayLike = 0.0,
    *,
    n_phase: int = 512,
    n_hermite: int = 6,
) -> Array:
    """Exact vibration error δ_V = E[a_F(a + v)] − a_F(a) [g] (see
    `mean_indicated_acceleration`; same arguments). Linear in the coefficients of `tf`, so
    `jax.grad` with respect to `tf` gives exact sensitivities. float64 advised (ppm-level)."""
    return mean_indicated_acceleration(
        tf, env, a3, a1, a2, n_phase=n_phase, n_hermite=n_hermite
    ) - indicated_acceleration(tf, a3, a1, a2)


# --- the paper's closed forms -----------------------------------------------------------


def paper_deterministic_error(
    tf: StaticTransferFunction,
    env: VibrationEnvironment,
    a3: ArrayLike,
    *,
    k5_quartic: float = 1.875,
) -> Array:
    """The paper's deterministic-vibration error, eq. (19) (= eqs. 4-5 with σ = 0) [g]:

        A1 (0.673 b3 − 0.5 a) + ½ k2 b3² + 1.5 k3 a b3² + k4 (3 a² b3² + 0.375 b3⁴)
        + k5 (5 a³ b3² + 1.875 a b3⁴) + ½ m31 b3 b1 + ½ m32 b3 b2.

    The paper's flights have a > 0; for a < 0 we use |a| in the A1 term (the asymmetry
    term is even in a). With no sinusoid (b3 = 0) the whole expression is 0 (the paper
    applies (19) only to deterministic vibration; literally its A1 term would leave
    −0.5·A1·a). The printed (19) has 1.185 for k5's quartic factor; (5) and the exact average give
    1.875 (pass `k5_quartic=1.185` for the printed one). The cross terms assume in-phase
    sinusoids (the paper's); phases in `env` are ignored here, unlike the exact expectation.
    """
    a = jnp.asarray(a3)
    b3, b1, b2 = env.sine_amplitude[2], env.sine_amplitude[0], env.sine_amplitude[1]
    return (
        # (19) is applied only when a sinusoid is present: its −0.5·A1·a part would
        # otherwise survive at b3 = 0, an error without vibration.
        jnp.where(b3 > 0, tf.asymmetry * (ASYMMETRY_SINE_FACTOR * b3 - 0.5 * jnp.abs(a)), 0.0)
        + 0.5 * tf.k2 * b3**2
        + 1.5 * tf.k3 * a * b3**2
        + tf.k4 * (3 * a**2 * b3**2 + 0.375 * b3**4)
        + tf.k5 * (5 * a**3 * b3**2 + k5_quartic * a * b3**4)
        + 0.5 * tf.m31 * b3 * b1
        + 0.5 * tf.m32 * b3 * b2
    )


def paper_random_error(
    tf: StaticTransferFunction, env: VibrationEnvironment, a3: ArrayLike
) -> Array:
    """The paper's random-vibration error, eq. (20) (= eqs. 4-5 with b = 0) [g]:

    0.125 A1 σ3 + k2 σ3² + 3 k3 a σ3² + k4 (6 a² σ3² + 3 σ3⁴) + k5 (10 a³ σ3² + 15 a σ3⁴)
    + m31 ρ31 σ3 σ1 + m32 ρ32 σ3 σ2.
    """
    a = jnp.asarray(a3)
    s = env.random_std
    rho = env.random_correlation
    s3 = s[2]
    return (
        ASYMMETRY_RANDOM_FACTOR * tf.asymmetry * s3
        + tf.k2 * s3**2
        + 3 * tf.k3 * a * s3**2
        + tf.k4 * (6 * a**2 * s3**2 + 3 * s3**4)
        + tf.k5 * (10 * a**3 * s3**2 + 15 * a * s3**4)
        + tf.m31 * rho[2, 0] * s3 * s[0]
        + tf.m32 * rho[2, 1] * s3 * s[1]
    )


def paper_vibration_error(
    tf: StaticTransferFunction,
    env: VibrationEnvironment,
    a3: ArrayLike,
    *,
    k5_quartic: float = 1.875,
) -> Array:
    """The paper's total vibration error (3): eq. (19) + eq. (20) [g]. The paper adds the
    deterministic and random parts; the exact expectation also has their cross moments
    (e.g. 6·(b²/2)·σ² in E w⁴), which this sum omits."""
    return paper_deterministic_error(tf, env, a3, k5_quartic=k5_quartic) + paper_random_error(
        tf, env, a3
    )


# --- time-domain Monte Carlo ------------------------------------------------------------


def _matrix_sqrt_psd(cov: Array) -> Array:
    # Symmetric square root via eigh: works for singular covariances (axes with σ = 0),
    # where a Cholesky factorisation does not. Not differentiated (Monte Carlo only).
    values, vectors = jnp.linalg.eigh(cov)
    return vectors * jnp.sqrt(jnp.clip(values, 0.0))[..., None, :]


def synthesize_vibration(
    env: VibrationEnvironment, ts: ArrayLike, *, key: Array, n_tones: int = 64
) -> Array:
    """One realisation of v(t) [g], shape (3, len(ts)).

    Sinusoid: b_i sin(2π f (t + t0) + φ_i) with a random start t0 ~ U(0, 1/f) (so a finite
    record is an unbiased sample of the phase average). Random part: `n_tones` equispaced
    frequencies across `random_band` with independent Gaussian cosine/sine amplitudes of
    covariance Σ/n_tones (a spectral synthesis: exactly Gaussian at every instant with
    covariance Σ, flat spectrum over the band), the tones snapped to multiples of 1/T for
    a record of length T (`ts` uniform). Use a record of whole sine periods for the lowest
    variance.
    """
    ts = jnp.asarray(ts)
    k_t0, k_a, k_b = jax.random.split(key, 3)
    dtype = ts.dtype
    t0 = jax.random.uniform(k_t0, (), dtype) / env.sine_frequency
    sine = env.sine_amplitude[:, None] * jnp.sin(
        2 * jnp.pi * env.sine_frequency * (ts + t0)[None, :] + env.sine_phase[:, None]
    )
    f_low, f_high = env.random_band[0], env.random_band[1]
    freqs = f_low + (f_high - f_low) * (jnp.arange(n_tones, dtype=dtype) + 0.5) / n_tones
    # Snap the tones onto the record's Fourier grid (multiples of 1/T): each then averages
    # to exactly zero over the record, which removes the O(σ/sqrt(n)) variance the linear
    # terms of a_F would otherwise add to a ppm-level time average.
    df = 1.0 / (ts.shape[-1] * (ts[-1] - ts[0]) / jnp.maximum(ts.shape[-1] - 1, 1))
    freqs = jnp.maximum(jnp.round(freqs / df), 1.0) * df
    root = _matrix_sqrt_psd(env.random_covariance) / jnp.sqrt(n_tones)
    za = root @ jax.random.normal(k_a, (3, n_tones), dtype)
    zb = root @ jax.random.normal(k_b, (3, n_tones), dtype)
    phase = 2 * jnp.pi * freqs[:, None] * ts[None, :]
    random = za @ jnp.cos(phase) + zb @ jnp.sin(phase)
    return sine + random


def time_domain_vibration_error(
    tf: StaticTransferFunction,
    env: VibrationEnvironment,
    a3: ArrayLike,
    a1: ArrayLike,
    a2: ArrayLike,
    ts: ArrayLike,
    *,
    key: Array,
    n_tones: int = 64,
) -> Array:
    """Time average of a_F(a + v(t)) − a_F(a) over one synthesised record [g] (scalar
    steady accelerations). Its expectation over `key` is the exact `vibration_error`;
    vmap over keys (or use `accel_jax.sweep`) for a Monte Carlo check."""
    v = synthesize_vibration(env, ts, key=key, n_tones=n_tones)
    out = indicated_acceleration(tf, a3 + v[2], a1 + v[0], a2 + v[1])
    return jnp.mean(out) - indicated_acceleration(tf, a3, a1, a2)


# --- shaker test (16) -------------------------------------------------------------------


class ShakerEstimate(eqx.Module):
    """Result of the shaker-test estimator (16).

    **Fields:**

    - `vibration_error`: δ̂_V = (U2 − ½(U1 + U3))/K1 [g].
    - `axis_shift`: |U1 − U3|/K1 [g at 1 g, i.e. rad for a small tilt about the
      horizontal], the paper's axis-stability statistic.
    - `valid`: axis_shift ≤ the tolerance (the paper's 1e-4 rad).
    """

    vibration_error: Array
    axis_shift: Array
    valid: Array


def shaker_vibration_error(
    u_before: ArrayLike,
    u_during: ArrayLike,
    u_after: ArrayLike,
    scale_factor: ArrayLike,
    *,
    axis_tolerance: float = 1e-4,
) -> ShakerEstimate:
    """The shaker estimator (16) with its axis-stability check.

    **Arguments:**

    - `u_before`, `u_during`, `u_after`: output records [V] (any length; their means U1, U2,
      U3 are used) before, during and after vibration, input axis along gravity.
    - `scale_factor`: K1 [V/g] > 0.
    - `axis_tolerance`: the admissible |U1 − U3|/K1 [rad] (paper: 1e-4).

    **Returns:** a `ShakerEstimate`. The mean of U1 and U3 cancels a bias drift linear in
    time exactly; the check bounds what a non-linear drift or a tilt can leave.
    """
    k1 = _concrete(scale_factor)
    if k1 is not None and not np.all(k1 > 0):
        raise ValueError(
            f"shaker_vibration_error: scale_factor K1 must be positive, got {k1!r} V/g."
        )
    u1, u2, u3 = (jnp.mean(jnp.asarray(u), axis=-1) for u in (u_before, u_during, u_after))
    shift = jnp.abs(u1 - u3) / scale_factor
    return ShakerEstimate(
        vibration_error=(u2 - 0.5 * (u1 + u3)) / scale_factor,
        axis_shift=shift,
        valid=shift <= axis_tolerance,
    )


# --- in-flight compensation (17)-(20) ---------------------------------------------------


class CompensationSteps(eqx.Module):
    """The estimates of the compensation algorithm (17)-(20) [g].

    **Fields:**

    - `first`: â(1) = (Û/K1 − a0)/(1 + δ), eq. (17).
    - `after_basic`: â(2) = â(1) − δ_OP(â(1)) without a0, eq. (18).
    - `after_deterministic`: â(3) = â(2) − δ_V,D(â(1)), eq. (19).
    - `after_random`: â(4) = â(3) − δ_V,R(â(1)), eq. (20).
    """

    first: Array
    after_basic: Array
    after_deterministic: Array
    after_random: Array


def compensate_in_flight(
    passport: StaticTransferFunction,
    indicated: ArrayLike,
    env_estimate: VibrationEnvironment,
    a1: ArrayLike = 0.0,
    a2: ArrayLike = 0.0,
    *,
    method: str = "paper",
    k5_quartic: float = 1.875,
    n_phase: int = 512,
) -> CompensationSteps:
    """In-flight compensation of the basic and vibration errors, eqs. (17)-(20).

    **Arguments:**

    - `passport`: the unit's passport coefficients (Table 4).
    - `indicated`: the mean indicated acceleration Û/K1 [g] along the input axis.
    - `env_estimate`: the vibration as estimated by the extra piezo sensors (amplitudes
      b̂_i, RMS σ̂_i).
    - `a1`, `a2`: the cross-axis accelerations [g] (from the other two accelerometers).
    - `method`: "paper" subtracts the closed forms (19), (20); "exact" subtracts the exact
      expectation (sine part, then the rest), both evaluated at â(1) as the paper does.
    - `k5_quartic`: see `paper_deterministic_error`.

    **Returns:** `CompensationSteps` [g]. float64 advised (ppm-level corrections).
    """
    if method not in ("paper", "exact"):
        raise ValueError(f"method must be 'paper' or 'exact', got {method!r}.")
    first = (jnp.asarray(indicated) - passport.bias) / (1 + passport.scale_factor_error)
    after_basic = first - basic_error(passport, first, a1, a2, include_bias=False)
    if method == "paper":
        det = paper_deterministic_error(passport, env_estimate, first, k5_quartic=k5_quartic)
        rnd = paper_random_error(passport, env_estimate, first)
    else:
        sine_only = eqx.tree_at(lambda e: e.random_std, env_estimate, jnp.zeros(3))
        det = vibration_error(passport, sine_only, first, a1, a2, n_phase=n_phase)
        rnd = vibration_error(passport, env_estimate, first, a1, a2, n_phase=n_phase) - det
    after_det = after_basic - det
    return CompensationSteps(first, after_basic, after_det, after_det - rnd)


# --- coefficient fitting from a table of vibration tests --------------------------------

TABLE_COLUMNS = ("a_in", "vib_amp", "vib_freq", "vib_rms", "a_out")
"""Required columns of a `vibration` CSV table: the input-axis acceleration a_in [g], the
sinusoidal vibration amplitude along the input axis vib_amp [g] and its frequency vib_freq
[Hz], the RMS of the random vibration vib_rms [g] (0 if none) and the mean indicated
acceleration a_out [g]. Optional: vib_amp_oa, vib_amp_pa [g], sinusoidal vibration on the
output and pendulum axes in phase with vib_amp (they make m31, m32 identifiable)."""
_OPTIONAL_COLUMNS = ("vib_amp_oa", "vib_amp_pa")
_TABLE_UNITS = {
    "a_in": "g",
    "vib_amp": "g",
    "vib_freq": "Hz",
    "vib_rms": "g",
    "a_out": "g",
    "vib_amp_oa": "g",
    "vib_amp_pa": "g",
}

FIT_PARAMETERS = ("bias", "scale_factor_error", "asymmetry", "k2", "k3", "k4", "k5")
"""The coefficients `fit_coefficients` estimates by default (m31, m32 are added when the
table has cross-axis vibration)."""


def validate_vibration_table(table: dict) -> dict[str, np.ndarray]:
    """Check a test table (a mapping column → 1-D array) and return float64 NumPy columns.

    Raises ValueError naming the column, the offending value and its unit: missing
    columns, unequal lengths, non-finite values, negative amplitudes/RMS, non-positive
    frequency where a sinusoid is applied.
    """
    missing = [c for c in TABLE_COLUMNS if c not in table]
    if missing:
        raise ValueError(
            f"vibration table: missing column(s) {missing}; required {list(TABLE_COLUMNS)}."
        )
    cols = {
        c: np.atleast_1d(np.asarray(table[c], dtype=np.float64))
        for c in TABLE_COLUMNS + tuple(c for c in _OPTIONAL_COLUMNS if c in table)
    }
    lengths = {c: v.shape for c, v in cols.items()}
    if len(set(lengths.values())) != 1 or len(next(iter(lengths.values()))) != 1:
        raise ValueError(f"vibration table: columns must be 1-D of equal length, got {lengths}.")
    for c, v in cols.items():
        bad = ~np.isfinite(v)
        if c in ("vib_amp", "vib_rms") + _OPTIONAL_COLUMNS:
            bad |= v < 0
        if c == "vib_freq":
            bad |= (cols["vib_amp"] > 0) & ~(v > 0)
        if np.any(bad):
            i = int(np.argmax(bad))
            raise ValueError(
                f"vibration table: column {c!r} row {i} has {float(v[i])!r} {_TABLE_UNITS[c]}; "
                "values must be finite, amplitudes/RMS non-negative, frequencies positive "
                "where a sinusoid is applied."
            )
    return cols


def read_vibration_table(path) -> dict[str, np.ndarray]:
    """Read a `vibration` CSV table (header row with the `TABLE_COLUMNS` names, any order)
    and validate it (`validate_vibration_table`)."""
    data = np.genfromtxt(path, delimiter=",", names=True, dtype=np.float64, encoding="utf-8")
    data = np.atleast_1d(data)
    return validate_vibration_table({name: data[name] for name in data.dtype.names})


def write_vibration_table(path, table: dict) -> None:
    """Write a validated test table as CSV (the `vibration` format)."""
    cols = validate_vibration_table(table)
    names = list(cols)
    np.savetxt(
        path,
        np.column_stack([cols[n] for n in names]),
        delimiter=",",
        header=",".join(names),
        comments="",
        fmt="%.17g",
    )


def _row_environment(row: dict) -> VibrationEnvironment:
    zero = jnp.zeros_like(row["vib_amp"])
    amp = jnp.stack([row.get("vib_amp_oa", zero), row.get("vib_amp_pa", zero), row["vib_amp"]])
    rms = jnp.stack([zero, zero, row["vib_rms"]])
    return VibrationEnvironment(sine_amplitude=amp, random_std=rms)


def predict_table(tf: StaticTransferFunction, table: dict, *, n_phase: int = 256) -> Array:
    """Mean indicated acceleration [g] for each row of a test table (exact expectation;
    the frequency column does not enter: δ(ω) is linear and averages out)."""
    rows, n = _padded_rows(table)
    return _predict_rows(tf, rows, n_phase)[:n]


@eqx.filter_jit
def _predict_rows(tf, rows, n_phase):
    def one(row):
        return mean_indicated_acceleration(tf, _row_environment(row), row["a_in"], n_phase=n_phase)

    return jax.vmap(one)(rows)


def _fit_names(table: dict, parameters) -> tuple[str, ...]:
    if parameters is not None:
        unknown = set(parameters) - set(StaticTransferFunction.__dataclass_fields__)
        if unknown:
            raise ValueError(f"fit_coefficients: unknown parameter(s) {sorted(unknown)}.")
        return tuple(parameters)
    names = FIT_PARAMETERS
    if "vib_amp_oa" in table and np.any(np.asarray(table["vib_amp_oa"]) > 0):
        names += ("m31",)
    if "vib_amp_pa" in table and np.any(np.asarray(table["vib_amp_pa"]) > 0):
        names += ("m32",)
    return names


def _tf_from(names, theta, base):
    return eqx.tree_at(
        lambda t: tuple(getattr(t, n) for n in names),
        base,
        tuple(theta[i] * PPM_SCALE for i in range(len(names))),
    )


PPM_SCALE = 1e-6
"""The fit works in ppm-scaled parameters (θ = coefficient / 1e-6) for conditioning."""


def design_matrix(table: dict, parameters=None, *, n_phase: int = 256) -> Array:
    """∂a_out/∂coefficient for every row and fitted coefficient (rows × parameters), in g
    per ppm. The model is linear in the coefficients, so this Jacobian is the whole model."""
    cols = validate_vibration_table(table)
    names = _fit_names(cols, parameters)
    theta0 = jnp.zeros(len(names))
    rows, n = _padded_rows(cols)
    return _design(names, n_phase)(theta0, rows, StaticTransferFunction())[:n]


def _rows(cols: dict) -> dict:
    return {c: jnp.asarray(v) for c, v in cols.items() if c != "a_out"}


_MIN_ROWS = 16


def _padded_rows(cols: dict) -> tuple[dict, int]:
    # Tables are padded to a power-of-two number of rows (at least 16) by repeating the last
    # row, so that tables of different lengths share one compiled model and solver (a study
    # compares many test plans); callers drop (or mask) the padding.
    rows = _rows(cols)
    n = int(jnp.shape(rows["a_in"])[0])
    size = max(_MIN_ROWS, 1 << max(n - 1, 0).bit_length())
    if size > n:
        rows = {c: jnp.concatenate([v, jnp.repeat(v[-1:], size - n)]) for c, v in rows.items()}
    return rows, n


@functools.lru_cache(maxsize=32)
def _residual_fn(names: tuple[str, ...], n_phase: int):
    # One function object per (coefficients, quadrature): optimistix's and jit's caches
    # then reuse the compiled solver for every table of the same shape.
    def residual(theta, args):
        rows, y, mask, base = args  # padded rows (`_padded_rows`); mask = 0 on the padding
        prediction = _predict_rows(_tf_from(names, theta, base), rows, n_phase)
        return mask * (prediction - y) / 1e-6

    return residual


@functools.lru_cache(maxsize=32)
def _design(names: tuple[str, ...], n_phase: int):
    @eqx.filter_jit
    def design(theta, rows, base):
        return jax.jacfwd(lambda th: _predict_rows(_tf_from(names, th, base), rows, n_phase))(theta)

    return design


class Identifiability(eqx.Module):
    """Which coefficients a test plan can separate.

    **Fields:**

    - `names`: the coefficients (static).
    - `unexplained_fraction`: per coefficient, |residual of its design column projected on
      the other columns| / |column| — 0 when the column is a combination of the others
      (not identifiable: e.g. k3 vs the scale factor at ±1 g alone), 1 when orthogonal.
    - `identifiable`: unexplained_fraction > 1e-6.
    - `standard_error_ppm`: per coefficient, the standard error [ppm units] for an output
      noise of `noise` g per row; inf for every coefficient when any one is not
      identifiable (fit fewer coefficients, or extend the plan).
    - `singular_values`: of the design matrix (g per ppm).
    """

    names: tuple[str, ...] = eqx.field(static=True)
    unexplained_fraction: Array
    identifiable: Array
    standard_error_ppm: Array
    singular_values: Array


def identifiability(
    table: dict, parameters=None, *, noise: float = 1e-6, n_phase: int = 256
) -> Identifiability:
    """Identifiability of the coefficients from a test plan (the `a_out` column is not
    used; pass zeros for a plan not yet run). `noise` [g] is the standard deviation of
    each row's mean output. Precision: float64 advised."""
    if not noise > 0:
        raise ValueError(f"identifiability: noise must be positive, got {noise!r} g.")
    cols = validate_vibration_table(table)
    names = _fit_names(cols, parameters)
    J = np.asarray(design_matrix(cols, names, n_phase=n_phase), dtype=np.float64)
    p = J.shape[1]
    frac = np.empty(p)
    for j in range(p):
        others = np.delete(J, j, axis=1)
        coef, *_ = np.linalg.lstsq(others, J[:, j], rcond=None)
        frac[j] = np.linalg.norm(J[:, j] - others @ coef) / max(np.linalg.norm(J[:, j]), 1e-300)
    ident = frac > 1e-6
    se = np.full(p, np.inf)
    if np.all(ident) and J.shape[0] >= p:
        se = noise * np.sqrt(np.diag(np.linalg.inv(J.T @ J)))
    return Identifiability(
        names=names,
        unexplained_fraction=jnp.asarray(frac),
        identifiable=jnp.asarray(ident),
        standard_error_ppm=jnp.asarray(se),
        singular_values=jnp.asarray(np.linalg.svd(J, compute_uv=False)),
    )


class CoefficientFit(eqx.Module):
    """Least-squares estimate of the transfer-function coefficients from a test table.

    **Fields:**

    - `transfer_function`: the fitted `StaticTransferFunction` (others at their initial value).
    - `names`: the fitted coefficients (static).
    - `estimate_ppm`, `standard_error_ppm`: per fitted coefficient [ppm units; bias in ppm
      of g, i.e. µg].
    - `correlation`: their correlation matrix [1].
    - `residual_rms`: RMS of the residuals [g].
    - `result`: the optimistix result code.
    """

    transfer_function: StaticTransferFunction
    names: tuple[str, ...] = eqx.field(static=True)
    estimate_ppm: Array
    standard_error_ppm: Array
    correlation: Array
    residual_rms: Array
    result: object


def fit_coefficients(
    table: dict,
    parameters=None,
    *,
    initial: StaticTransferFunction | None = None,
    noise: float | None = None,
    n_phase: int = 256,
    throw: bool = True,
) -> CoefficientFit:
    """Fit a0, the scale-factor error δ, A1, k2..k5 (and m31, m32 if the table has
    cross-axis vibration) to a table of tests by optimistix Levenberg-Marquardt least
    squares on the exact expectation of the output.

    **Arguments:**

    - `table`: the test table (`read_vibration_table` or a dict of columns) [g, Hz].
    - `parameters`: the coefficient names to fit (default: `FIT_PARAMETERS` + m3i).
    - `initial`: starting / fixed values of the other coefficients (default zeros).
    - `noise`: known standard deviation of a_out [g]; default: estimated from the
      residuals (RSS/(n − p)).
    - `throw`: raise if the solver fails (batch sweeps pass False and read `result`).

    A host-level function (it validates the table with NumPy): call it outside `jit`; the
    solver inside is compiled and cached per (coefficients, table size).

    **Returns:** a `CoefficientFit`. Standard errors from σ² (JᵀJ)⁻¹; a plan in which a
    coefficient is not identifiable (see `identifiability`) gives infinite/NaN errors —
    check it first. float64 advised.
    """
    import optimistix as optx

    cols = validate_vibration_table(table)
    names = _fit_names(cols, parameters)
    n, p = cols["a_in"].shape[0], len(names)
    if n < p:
        raise ValueError(
            f"fit_coefficients: {n} test rows cannot determine {p} coefficients {names}."
        )
    base = StaticTransferFunction() if initial is None else initial
    theta0 = jnp.asarray([float(getattr(base, nm)) / PPM_SCALE for nm in names])
    rows, _ = _padded_rows(cols)
    size = int(jnp.shape(rows["a_in"])[0])
    y = jnp.zeros(size).at[:n].set(jnp.asarray(cols["a_out"]))
    mask = (jnp.arange(size) < n).astype(y.dtype)
    args = (rows, y, mask, base)
    residual = _residual_fn(names, n_phase)
    solver = optx.LevenbergMarquardt(rtol=1e-12, atol=1e-12)
    sol = optx.least_squares(residual, solver, theta0, args, max_steps=256, throw=throw)
    theta = sol.value
    r = residual(theta, args)[:n] * 1e-6
    J = _design(names, n_phase)(theta, rows, base)[:n]  # g per ppm (the model is linear)
    sigma2 = noise**2 if noise is not None else jnp.sum(r**2) / max(n - p, 1)
    cov = sigma2 * jnp.linalg.inv(J.T @ J)
    se = jnp.sqrt(jnp.diag(cov))
    return CoefficientFit(
        transfer_function=_tf_from(names, theta, base),
        names=names,
        estimate_ppm=theta,
        standard_error_ppm=se,
        correlation=cov / jnp.outer(se, se),
        residual_rms=jnp.sqrt(jnp.mean(r**2)),
        result=sol.result,
    )
