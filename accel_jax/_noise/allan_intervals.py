"""The Allan deviation as navigation engineers read it (IEEE Std 952 / 1554): the
overlapping ADEV with confidence intervals from equivalent degrees of freedom.

The intervals use allantools (an established implementation, not re-derived here): at each
τ = mΔ the dominant power-law noise is identified by the lag-1 autocorrelation method
(`allantools.autocorr_noise_id`; Riley & Greenhall), the equivalent degrees of freedom of the
overlapping ADEV by Greenhall's algorithm (`allantools.edf_greenhall`), and the interval by
the χ² distribution (`allantools.confidence_interval`). The deviation itself is
`allan_deviation`'s (the same estimator as `allantools.oadev`, checked in the tests).
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import math

import numpy as np

from .allan import allan_deviation
from .record import _sample_interval, _validate_record

ONE_SIGMA = math.erf(1 / math.sqrt(2))
"""The confidence of a ±1σ interval, 0.6827."""

ALPHA_NAMES = {
    2: "white PM",
    1: "flicker PM",
    0: "white FM",
    -1: "flicker FM",
    -2: "random walk FM",
}
"""Power-law noise S_y(f) ∝ f^α by α (phase-noise terms; for a rate record "white FM" is
the white rate noise N, "flicker FM" the bias instability B, "random walk FM" the rate
random walk K)."""


@dataclasses.dataclass(frozen=True)
class AllanDeviation:
    """Overlapping Allan deviation with confidence intervals (`allan_deviation_intervals`).

    **Fields** (arrays over τ): `taus` [s]; `deviation` σ(τ) [record unit]; `lower`,
    `upper` the interval at `confidence`; `edf` the equivalent degrees of freedom; `alpha`
    the identified power-law exponent (`ALPHA_NAMES`; NaN where too few samples to tell,
    then white FM is assumed for the EDF; below −2, drift-like, the EDF is random-walk FM's);
    `n_samples` the record's length.
    """

    taus: np.ndarray
    deviation: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    edf: np.ndarray
    alpha: np.ndarray
    confidence: float
    n_samples: int


def octave_cluster_sizes(n_samples: int, min_clusters: int = 8) -> list[int]:
    """m = 1, 2, 4, … while the record holds at least `min_clusters` non-overlapping
    clusters of 2m samples (the usual octave spacing of an ADEV plot)."""
    sizes, m = [], 1
    while 2 * m * min_clusters <= n_samples:
        sizes.append(m)
        m *= 2
    return sizes


def allan_deviation_intervals(
    record, sample_interval: float, cluster_sizes=None, *, confidence: float = ONE_SIGMA
) -> AllanDeviation:
    """Overlapping Allan deviation of a rate record with χ² confidence intervals from
    Greenhall's equivalent degrees of freedom for the noise identified at each τ.

    **Arguments:** `record` x (N samples of a rate, e.g. accelerometer output [g]);
    `sample_interval` Δ [s]; `cluster_sizes` the m's (default `octave_cluster_sizes`);
    `confidence` of the interval (default ±1σ, 0.683).

    **Returns:** an `AllanDeviation`. Host-side (NumPy, float64; the deviation by the jitted
    `allan_deviation` in float64). Bad input raises `ValueError`.
    """
    import allantools
    import jax

    with jax.enable_x64(True):  # float64 whatever the caller's setting (restored after)
        x = np.asarray(_validate_record("allan_deviation_intervals", record), np.float64)
    _sample_interval("allan_deviation_intervals", sample_interval)
    if not 0 < confidence < 1:
        raise ValueError(
            f"allan_deviation_intervals: confidence must be in (0, 1), got {confidence}."
        )
    n = x.size
    sizes = octave_cluster_sizes(n) if cluster_sizes is None else [int(m) for m in cluster_sizes]
    if not sizes:
        raise ValueError(f"allan_deviation_intervals: a record of {n} samples is too short.")
    with jax.enable_x64(True):
        taus, deviation = allan_deviation(x, float(sample_interval), sizes)
    taus, deviation = np.asarray(taus, float), np.asarray(deviation, float)
    edf, alpha, lower, upper = [], [], [], []
    for m, dev in zip(sizes, deviation, strict=True):
        try:  # allantools prints (not warns) when it cannot tell: keep it off the terminal
            with contextlib.redirect_stdout(io.StringIO()):
                found = allantools.autocorr_noise_id(x, m, data_type="freq", dmin=0, dmax=2)
            a = int(found[0])
            alpha.append(float(a))
        except NotImplementedError:  # too few clusters at this τ for the lag-1 test
            a = 0
            alpha.append(math.nan)
        # The ADEV (d = 2) is defined for α > −3 (Greenhall's algorithm asserts α + 2d > 1):
        # a steeper identified noise (drift-like, α ≤ −3) takes the EDF of random-walk FM.
        a_edf = min(max(a, -2), 2)
        e = float(allantools.edf_greenhall(alpha=a_edf, d=2, m=m, N=n, overlapping=True))
        lo, hi = allantools.confidence_interval(dev, e, confidence)
        edf.append(e)
        lower.append(float(lo))
        upper.append(float(hi))
    return AllanDeviation(
        taus=taus,
        deviation=deviation,
        lower=np.asarray(lower),
        upper=np.asarray(upper),
        edf=np.asarray(edf),
        alpha=np.asarray(alpha),
        confidence=float(confidence),
        n_samples=n,
    )
