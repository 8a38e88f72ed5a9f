"""Record validation, the sample autocorrelation (11), and what the other modules share:
`_validate_record` and `_sample_interval` check a record and its sampling interval (a
`ValueError` on concrete input, a runtime error when traced), `autocorrelation` is the
paper's autocovariance estimator R_k by FFT, and the shared pieces are the array aliases
`Scalar` and `Series`, the log-parameter clip `_LOG_CLIP` of the fits, and the fit outcome
`NoiseFitResult` with `_throw`, which raises on a failed fit when asked to.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._params import _concrete, _shown

Scalar = Float[Array, ""]
Series = Float[Array, " n"]

# Clip of the log-parameters during fits: keeps exp() finite (tier 3, never NaN) when a
# component's variance wanders to zero.
_LOG_CLIP = 60.0


class NoiseFitResult(eqx.Enumeration):
    """Outcome of a noise-model fit; `successful` or the reason it failed."""

    successful = ""
    no_positive_lags = (
        "No lag j ≥ 1 has a positive normalised autocorrelation r_j: the record looks white; "
        "rule (15)/(21) needs r_j > 0. Use a white-noise model or more samples per τ."
    )
    no_zero_crossing = (
        "The autocorrelation has no zero within the lags given, so β = π/(2 τ_β) (19) is "
        "undefined: ask for more lags or use the Gauss-Markov model."
    )
    not_converged = "The optimiser did not converge within max_steps."


def _throw(result, value, throw):
    if throw:
        value = result.error_if(value, result != NoiseFitResult.successful)
    return value


def _validate_record(name: str, record, *, max_lag: int | None = None, min_samples: int = 8):
    record = jnp.asarray(record)
    if record.ndim != 1:
        raise ValueError(
            f"{name}: the record must be 1-D (one channel), got shape {record.shape}; vmap "
            f"over a batch of records instead."
        )
    n = record.shape[0]
    if max_lag is not None:
        if int(max_lag) < 1:
            raise ValueError(f"{name}: max_lag must be ≥ 1, got {max_lag!r}.")
        if n < 2 * (int(max_lag) + 1):
            raise ValueError(
                f"{name}: a record of {n} samples is too short for {max_lag} lags; at least "
                f"2·(max_lag + 1) = {2 * (int(max_lag) + 1)} samples are needed (R_k is "
                "averaged over N − k products, which must stay at least half the record)."
            )
    if n < min_samples:
        raise ValueError(f"{name}: the record has {n} samples; at least {min_samples} are needed.")
    if not jnp.issubdtype(record.dtype, jnp.floating):
        record = record.astype(jnp.result_type(float))
    concrete = _concrete(record)
    if concrete is not None:
        if not np.all(np.isfinite(concrete)):
            bad = int(np.argmax(~np.isfinite(concrete)))
            raise ValueError(
                f"{name}: sample {bad} of the record is {float(concrete[bad])}; the record must be "
                "finite (drop or interpolate missing samples first)."
            )
        if np.ptp(concrete) == 0:
            raise ValueError(
                f"{name}: the record is constant ({float(concrete[0])} in every sample): its "
                "autocorrelation is zero and no noise model can be identified. Check that the "
                "channel is connected and not saturated or quantised to one level."
            )
    else:
        record = eqx.error_if(
            record, ~jnp.all(jnp.isfinite(record)), f"{name}: the record contains NaN or inf."
        )
        record = eqx.error_if(
            record, jnp.max(record) == jnp.min(record), f"{name}: the record is constant."
        )
    return record


def _sample_interval(name: str, sample_interval):
    concrete = _concrete(sample_interval)
    if concrete is not None and not (
        np.ndim(concrete) == 0 and np.isfinite(concrete) and concrete > 0
    ):
        raise ValueError(
            f"{name}: sample_interval must be a positive number, got "
            f"{_shown(concrete)} s."
        )
    return sample_interval


def autocorrelation(record: ArrayLike, max_lag: int) -> Series:
    """Sample autocovariance R_k of eq. (11), k = 0..max_lag, by FFT.

        R_k = 1/(N − k) Σ_{i=1}^{N−k} (x_i − m)(x_{i+k} − m),   m = mean of the record

    (the unbiased-by-count estimator the paper uses; the mean is the record's own). Zero-
    padding to at least 2N makes the FFT's circular correlation the linear one.

    **Arguments:**

    - `record`: x, shape (N,), any unit u; N ≥ 2(max_lag + 1).
    - `max_lag`: the largest lag k (static int).

    **Returns:** R, shape (max_lag + 1,), in u². Jit/vmap/grad-safe; precision follows the
    record (float32 rounding is ~1e-7 R_0). Bad input (too short, constant, NaN) raises a
    `ValueError` (concrete record) or a runtime error (traced record).
    """
    x = _validate_record("autocorrelation", record, max_lag=max_lag)
    n = x.shape[0]
    size = 1 << (2 * n - 1).bit_length()
    centred = x - jnp.mean(x)
    spectrum = jnp.fft.rfft(centred, n=size)
    raw = jnp.fft.irfft(spectrum * jnp.conj(spectrum), n=size)[: max_lag + 1]
    return raw / (n - jnp.arange(max_lag + 1, dtype=x.dtype))
