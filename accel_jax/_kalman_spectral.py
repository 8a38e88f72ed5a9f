"""What a smoothed state estimate's autocovariance is expected to be, from the spectra.

A sensor model identified from a filter's smoothed estimates (the paper's batch loop,
docs/models.md §4) is fitted to the autocovariance of x̂_{k|T}, not of x_k. Away from the
ends of a long record the RTS smoother is the two-sided Wiener smoother of the model it
assumes (A):

    x̂(ω) = W(ω) y(ω),   W = S_xy^A (S_yy^A)⁻¹,   S_xx^A = G Q Gᴴ,  G = (e^{iω} I − F)⁻¹,
    S_xy^A = S_xx^A Hᵀ,  S_yy^A = H S_xx^A Hᵀ + R,

so when the data follow another model (T) the estimate's spectrum is W S_yy^T Wᴴ, and its
autocovariance is that spectrum's inverse transform. The smoothing error under A has the
spectrum S_xx^A − W S_yx^A; with A = T the two add up to the state's own autocovariance (the
law of total covariance) — the part the smoothed means leave out. `expected_sample_
autocovariance` then gives the expectation of the estimator `accel_jax.noise.
autocorrelation` applies to a record of finite length (its own mean removed).

`smoothed_autocovariance` computes all three on the host in NumPy float64, whatever JAX's
precision setting (the INS channel's gyro variances are ~1e-15 rad²/s²): an analysis tool
for explaining an identification's bias, not a traced function. The truth may have
undamped modes (the Schuler loop): its observation spectrum diverges there, the Wiener
gain vanishes there, and their product stays finite on a frequency grid that does not
hit the pole; a non-finite result raises.
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import numpy as np
from jaxtyping import ArrayLike

from ._kalman import LinearGaussianModel

_MIN_FFT = 1 << 16


class SmoothedAutocovariance(eqx.Module):
    """Result of `smoothed_autocovariance` for one state, lags k = 0..max_lag (NumPy float64).

    **Fields:**

    Arrays of shape (max_lag + 1,), or (states, max_lag + 1) when several states were asked.

    - `estimate`: the smoothed mean's autocovariance under the truth: E[R̂_k] of the
        sample estimator over `record_length` samples when that was given, else R_k itself.
    - `posterior`: the smoothing error's autocovariance under the assumed model (its
        sample estimator's expectation likewise when `record_length` was given: with the
        true model the two then add up to E[R̂_k] of the state's own record).
    - `record_length`: the record length used (None: the process's own autocovariance).
    - `fft_size`: the frequency grid's size N (lags alias at multiples of N).
    """

    estimate: np.ndarray
    posterior: np.ndarray
    record_length: int | None = eqx.field(static=True)
    fft_size: int = eqx.field(static=True)


def _spectra(model: LinearGaussianModel, size: int):
    """S_xx (f, n, n), S_xy (f, n, m), S_yy (f, m, m) on ω_j = 2πj/N, j = 0..N/2."""
    transition = np.asarray(model.transition, np.float64)
    process = np.asarray(model.process_covariance, np.float64)
    observation = np.asarray(model.observation, np.float64)
    noise = np.asarray(model.observation_covariance, np.float64)
    z = np.exp(2j * np.pi * np.arange(size // 2 + 1) / size)
    n = transition.shape[0]
    gain = np.linalg.inv(z[:, None, None] * np.eye(n) - transition)
    sxx = gain @ process @ np.conj(np.swapaxes(gain, 1, 2))
    sxy = sxx @ observation.T
    syy = observation @ sxy + noise
    return sxx, sxy, syy


def _inverse(half_spectrum: np.ndarray, size: int) -> np.ndarray:
    """R_k = (1/N) Σ_j S(ω_j) e^{iω_j k}, k = 0..N−1, from the real spectrum's half."""
    return np.fft.irfft(np.real(half_spectrum), n=size)


def expected_sample_autocovariance(
    autocovariance: ArrayLike, record_length: int, max_lag: int
) -> np.ndarray:
    """E[R̂_k], k = 0..max_lag, of R̂_k = 1/(n − k) Σ_{i<n−k} (x_i − m)(x_{i+k} − m), m the
    record's mean (the estimator of `accel_jax.noise.autocorrelation`), for a stationary
    record of n = `record_length` samples with autocovariance R_0..R_{n−1}
    (`autocovariance`, at least n values):

        E[(x_i − m)(x_j − m)] = R_{i−j} − c_i − c_j + Var m,   c_i = Cov(x_i, m),

    summed in O(n) with cumulative sums. Its difference from R_k is the estimator's bias,
    about −2τ/n R_0 for a correlation time of τ samples. NumPy float64.
    """
    n, max_lag = int(record_length), int(max_lag)
    r = np.asarray(autocovariance, np.float64)
    if r.ndim != 1 or r.shape[0] < n or not 0 <= max_lag < n - 1:
        raise ValueError(
            "expected_sample_autocovariance: need R_0..R_{n-1} (n = record_length) and "
            f"0 <= max_lag < n - 1, got {r.shape[0] if r.ndim == 1 else r.shape} values, "
            f"n = {n}, max_lag = {max_lag}."
        )
    r = r[:n]
    weights = 1.0 - np.arange(1, n) / n
    var_mean = (r[0] + 2.0 * np.dot(weights, r[1:])) / n
    cumulative = np.cumsum(r)
    i = np.arange(n)
    c = (cumulative[i] + cumulative[n - 1 - i] - r[0]) / n  # (1/n) Σ_l R_{i−l}
    c_sum = np.concatenate([[0.0], np.cumsum(c)])
    lags = np.arange(max_lag + 1)
    count = n - lags
    # Σ_{i<n−k} (c_i + c_{i+k}) = C(n−k) + (C(n) − C(k)), C the prefix sums of c
    cross = c_sum[count] + c_sum[n] - c_sum[lags]
    return r[: max_lag + 1] - cross / count + var_mean


def smoothed_autocovariance(
    assumed: LinearGaussianModel,
    truth: LinearGaussianModel,
    state: int | Sequence[int],
    max_lag: int,
    *,
    record_length: int | None = None,
    fft_size: int | None = None,
) -> SmoothedAutocovariance:
    """The autocovariance of the steady-state smoothed estimate of `state` when the
    smoother assumes `assumed` and the observations follow `truth`, and that of the
    smoothing error under `assumed` (module docstring).

    **Arguments:**

    - `assumed`: the smoother's model (its `state` is the estimated one).
    - `truth`: the model the observations come from; any state size, the same
        observation size as `assumed`.
    - `state`: index of the state in `assumed`, or a sequence of them (the spectra are
        computed once for all).
    - `max_lag`: the largest lag k returned.
    - `record_length`: with it, `estimate` is the expectation of the sample estimator
        over a record of that many samples (`expected_sample_autocovariance`).
    - `fft_size`: N, the frequency grid (default: a power of two ≥ 2^20 and ≥ twice the
        record and the lags); make N/2π much longer than the slowest correlation time.

    **Returns:** `SmoothedAutocovariance`, its arrays of shape (max_lag + 1,) for one state,
    (len(state), max_lag + 1) for a sequence. Bad input raises `ValueError`.
    """
    one = isinstance(state, (int, np.integer))
    states = (int(state),) if one else tuple(int(i) for i in state)
    n_state = np.shape(assumed.transition)[0]
    if not states or not all(0 <= i < n_state for i in states):
        raise ValueError(
            f"smoothed_autocovariance: state must index the assumed model's {n_state} "
            f"states, got {state}."
        )
    if np.shape(assumed.observation)[0] != np.shape(truth.observation)[0]:
        raise ValueError(
            "smoothed_autocovariance: the assumed and true models must observe the same "
            f"number of quantities, got {np.shape(assumed.observation)[0]} and "
            f"{np.shape(truth.observation)[0]}."
        )
    if max_lag < 0 or (record_length is not None and record_length < max_lag + 2):
        raise ValueError(
            "smoothed_autocovariance: need max_lag >= 0 and record_length >= max_lag + 2, "
            f"got max_lag = {max_lag}, record_length = {record_length}."
        )
    longest = max(int(max_lag) + 1, int(record_length or 0))
    default = max(1 << 20, 1 << (2 * longest - 1).bit_length())
    size = int(fft_size) if fft_size is not None else default
    if size < 2 * longest or size % 2:
        raise ValueError(
            f"smoothed_autocovariance: fft_size must be even and >= {2 * longest} (twice "
            f"the record or the lags), got {size}."
        )
    sxx, sxy, syy = _spectra(assumed, size)
    _, _, syy_true = _spectra(truth, size)
    estimates, posteriors = [], []
    for i in states:
        # W = S_xy S_yy⁻¹ for the one state: a row (f, m).
        gain = np.linalg.solve(np.swapaxes(syy, 1, 2), sxy[:, i, :, None])[..., 0]
        estimate = np.einsum("fm,fmp,fp->f", gain, syy_true, np.conj(gain))
        posterior = sxx[:, i, i] - np.einsum("fm,fm->f", gain, np.conj(sxy[:, i, :]))
        r_estimate, r_posterior = _inverse(estimate, size), _inverse(posterior, size)
        if not (np.all(np.isfinite(r_estimate)) and np.all(np.isfinite(r_posterior))):
            raise ValueError(
                "smoothed_autocovariance: the spectra are not finite on the frequency grid "
                "(a pole of the model on it); change fft_size."
            )
        if record_length is not None:
            r_estimate = expected_sample_autocovariance(r_estimate, record_length, max_lag)
            r_posterior = expected_sample_autocovariance(r_posterior, record_length, max_lag)
        estimates.append(r_estimate[: max_lag + 1])
        posteriors.append(r_posterior[: max_lag + 1])
    return SmoothedAutocovariance(
        estimate=estimates[0] if one else np.stack(estimates),
        posterior=posteriors[0] if one else np.stack(posteriors),
        record_length=None if record_length is None else int(record_length),
        fft_size=size,
    )
