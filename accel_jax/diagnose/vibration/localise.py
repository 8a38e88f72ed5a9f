"""Where the nominal refit's residual lies across a table's conditions (`localise`): per
row, by input level, by vibration level, by cross-axis vibration and by frequency, and its
whiteness across rows."""

from __future__ import annotations

import numpy as np

from ..._data import VibrationData
from ..base import ljung_box
from .state import VibrationTable


def _group(keys: np.ndarray, residual: np.ndarray, label: str, unit: str) -> list[dict]:
    out = []
    for value in np.unique(keys):
        rows = keys == value
        out.append(
            {
                label: float(value),
                "rows": int(np.sum(rows)),
                f"mean_residual_{unit}": float(np.mean(residual[rows])),
                f"rms_residual_{unit}": float(np.sqrt(np.mean(residual[rows] ** 2))),
            }
        )
    return out


def localise(
    data: VibrationData, residual: np.ndarray, sigma: float, table: VibrationTable
) -> dict:
    """Where the nominal refit's residual lies: per row, by input level, by vibration level
    (mean square of the input-axis vibration, b²/2 + σ²), by cross-axis vibration and by
    frequency; and its whiteness across rows (in table order and sorted by condition)."""
    a_in = np.asarray(data.a_in)
    power = np.asarray(data.vib_amp) ** 2 / 2 + np.asarray(data.vib_rms) ** 2
    freq = np.asarray(data.vib_freq)
    n = residual.size
    standardised = residual / sigma if sigma > 0 else np.zeros_like(residual)
    rows = [
        {
            "row": i,
            "a_in_g": float(a_in[i]),
            "vib_amp_g": float(data.vib_amp[i]),
            "vib_rms_g": float(data.vib_rms[i]),
            "vib_freq_Hz": float(freq[i]),
            "residual_g": float(residual[i]),
            "standardised": float(standardised[i]),
        }
        for i in range(n)
    ]
    where = {
        "conditions": rows,
        "by_input_level": _group(np.round(a_in, 9), residual, "a_in_g", "g"),
        "by_vibration_level": _group(np.round(power, 9), residual, "vibration_mean_square_g2", "g"),
    }
    for column, axis in (("vib_amp_oa", "OA"), ("vib_amp_pa", "PA")):
        values = getattr(data, column)
        if values is not None:
            where[f"by_cross_axis_{axis}"] = _group(
                np.round(np.asarray(values), 9), residual, f"{column}_g", "g"
            )
    vibrating = np.asarray(data.vib_amp) > 0
    if np.unique(freq[vibrating]).size > 1:
        # Frequency should not matter to a static transfer function (δ(ω) is linear and
        # averages out): a residual that follows it points at dynamics outside the model.
        terciles = np.quantile(freq[vibrating], [1 / 3, 2 / 3])
        band = np.digitize(freq, terciles)
        where["by_vibration_frequency"] = [
            {
                "band": int(b),
                "frequency_range_Hz": [
                    float(freq[vibrating & (band == b)].min()),
                    float(freq[vibrating & (band == b)].max()),
                ],
                "rows": int(np.sum(vibrating & (band == b))),
                "rms_residual_g": float(np.sqrt(np.mean(residual[vibrating & (band == b)] ** 2))),
            }
            for b in range(3)
            if np.any(vibrating & (band == b))
        ]
    order = np.lexsort((power, a_in))
    lags = max(1, min(10, n // 4))
    where["whiteness"] = ljung_box(residual, lags=lags)
    where["whiteness_sorted_by_condition"] = ljung_box(residual[order], lags=lags)
    where["largest_standardised_residual"] = {
        "row": int(np.argmax(np.abs(standardised))),
        "value": float(standardised[np.argmax(np.abs(standardised))]),
    }
    where["noise_sigma_g"] = sigma
    where["not_identifiable"] = dict(table.unavailable)
    return where
