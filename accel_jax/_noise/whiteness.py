"""The Ljung–Box whiteness test, once for the library: the noise-model selection tests its
fits' standardised innovations with it, the diagnosis its residuals."""

from __future__ import annotations

import numpy as np


def ljung_box(residual, lags: int = 20, num_parameters: int = 0) -> dict:
    """Ljung–Box (1978) portmanteau test of whiteness.

        Q = n (n + 2) Σ_{k=1}^{L} r_k² / (n − k),   r_k = Σ_{t>k} e_t e_{t−k} / Σ_t e_t²

    on the demeaned residual e (n samples); under whiteness Q ~ χ²(L − p), p =
    `num_parameters` fitted to produce the residual (at least one degree of freedom kept).
    L is `lags`, capped at n // 4.

    **Returns:** `{"statistic": Q, "lags": L, "p_value": P(χ² > Q), "autocorrelation":
    [r_1, …, r_L]}` as Python floats. Host-side NumPy in float64 (the p-value from JAX's
    regularised incomplete gamma function, evaluated in float64 whatever the global
    setting); a constant residual gives Q = 0, p = 1. A non-finite or shorter-than-4 residual
    raises `ValueError`.
    """
    from scipy.special import gammaincc  # on the host: one number, no program to compile

    x = np.asarray(residual, dtype=np.float64)
    if x.ndim != 1 or x.size < 4 or not np.all(np.isfinite(x)):
        raise ValueError(
            "ljung_box: the residual must be a finite 1-D series of at least 4 samples, got "
            f"shape {x.shape}" + ("" if np.all(np.isfinite(x)) else " with non-finite values") + "."
        )
    x = x - x.mean()
    n = x.shape[0]
    lags = int(min(lags, n // 4))
    denominator = np.dot(x, x)
    if denominator == 0:
        return {"statistic": 0.0, "lags": lags, "p_value": 1.0, "autocorrelation": [0.0] * lags}
    rho = np.array([np.dot(x[k:], x[:-k]) / denominator for k in range(1, lags + 1)])
    q = float(n * (n + 2) * np.sum(rho**2 / (n - np.arange(1, lags + 1))))
    dof = max(lags - int(num_parameters), 1)
    p_value = float(gammaincc(dof / 2.0, q / 2.0))
    return {"statistic": q, "lags": lags, "p_value": p_value, "autocorrelation": rho.tolist()}
