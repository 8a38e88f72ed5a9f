"""The vibration acting on the accelerometer (docs/models.md §3): `VibrationEnvironment` (a
sinusoid of one frequency on each axis plus zero-mean stationary Gaussian random vibration),
`BandSpectrum` and `random_rms` (the random part's RMS from band PSDs with the η(f) factors
of the paper's Table 1), and the per-axis vector converters they share.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._params import _concrete, _shown
from .._static import _as_float

AXES = ("OA (a1)", "PA (a2)", "IA (a3)")
"""Axis order of every per-axis vector here: the paper's numbering 1, 2, 3."""


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


def random_rms(
    psd: ArrayLike,
    band_width: ArrayLike,
    eta: ArrayLike = 1.0,
    *,
    paper: bool = True,
    eta_squared: bool = False,
):
    """RMS random vibration from band PSDs with the mounting/sensor response factors η.

    **Arguments:**

    - `psd`: S_j [g²/Hz] per band.
    - `band_width`: Δf_j [Hz] per band.
    - `eta`: η(f_j) [1] per band (the paper's Table 1: the BINS mount and the sensor's own
      frequency response).
    - `paper`: True gives the paper's σ = sqrt((1/n) Σ_j η_j S_j Δf_j) (the mean over the n
      bands); False gives the variance-additive σ = sqrt(Σ_j η_j S_j Δf_j).
    - `eta_squared`: η is an amplitude-response factor (the mount's and the sensor's
      frequency response, the paper's Fig. 4), so physically it scales the PSD as η²:
      True uses η_j² S_j Δf_j. False (default) applies η linearly, as the paper does — its
      Table 1 column reproduces with PSDs inside the printed ranges only that way (the
      tolerance-limits study shows both).

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
    power = (eta**2 if eta_squared else eta) * psd * band_width
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
        maybe = {n: _concrete(getattr(self, n)) for n in ("f_low", "f_high", "psd", "eta")}
        if any(v is None for v in maybe.values()):
            return
        values = {n: v for n, v in maybe.items() if v is not None}  # all of them
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

    def rms(self, *, paper: bool = True, eta_squared: bool = False) -> Array:
        """σ [g]: the paper's sqrt((1/n) Σ η S Δf) (`paper=True`) or the variance-additive
        sqrt(Σ η S Δf) (`paper=False`); η² in place of η with `eta_squared=True` (η as an
        amplitude response); see `random_rms`."""
        eta = jnp.broadcast_to(self.eta, self.psd.shape)
        return random_rms(self.psd, self.band_width, eta, paper=paper, eta_squared=eta_squared)

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
