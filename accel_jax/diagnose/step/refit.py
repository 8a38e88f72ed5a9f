"""What the step diagnosis reports of its refit (host side): the device parameters' shifts
against the nominal, the known values, each nuisance, and where the residual lies in the
record (`_localise`: by segment, transient against steady part, and how it is spread).
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from ..._servo import scale_factor
from ..base import ljung_box
from .model import REFIT_FIELDS, refitted_device
from .layout import W
from .nuisance import NuisanceTest, change_shifts
from .segments import segments, time_text
from .state import StepFit, RecordView, StepRecord


TRANSIENT_FRACTION = 0.25
"""The first quarter of each constant-input segment counts as transient, the rest as steady."""


def _describe_where(residual, rec, data, sigma) -> str:
    """Where a residual lies, in words: the segments whose RMS is largest."""
    u = np.asarray(data.u_test)
    t = np.asarray(data.t)
    edges = segments(u)
    parts = []
    for start, stop in zip(edges[:-1], edges[1:], strict=True):
        cut = start + max(1, int(TRANSIENT_FRACTION * (stop - start)))
        for label, a, b in (("transient", start, cut), ("steady", cut, stop)):
            if b > a:
                parts.append((float(np.sqrt(np.mean(residual[a:b] ** 2))), label, start, b - a))
    if not parts:
        return ""
    total = float(np.sqrt(np.mean(residual**2)))
    worst = sorted(parts, reverse=True)[:3]
    transient = sum(p[0] ** 2 * p[3] for p in parts if p[1] == "transient")
    steady = sum(p[0] ** 2 * p[3] for p in parts if p[1] == "steady")
    kind = "in the transients after the changes" if transient > steady else "in the steady states"
    at = ", ".join(
        f"{time_text(t[p[2]] - t[0])} (U_test {u[p[2]]:+.3g} V)" for p in worst if p[0] > 2 * sigma
    )
    where = f"largest {kind}"
    if at:
        where += f": segments starting at {at}"
    return where + f" (RMS {total:.3g} V over the record)"


def _parameter_shifts(nominal, fit: StepFit, rec: StepRecord) -> dict:
    parameters = {}
    for j, field in enumerate(REFIT_FIELDS):
        if rec.prior_sigma[j] == 0:
            continue
        value0 = float(getattr(nominal.params, field))
        value = value0 * math.exp(rec.prior_sigma[j] * fit.z[j])
        parameters[field] = {
            "nominal": value0,
            "refitted": value,
            "shift_relative": value / value0 - 1,
            "shift_sigma": float(fit.z[j]),
        }
    return parameters


KNOWN_FIELDS = (
    ("torquer_time_constant", "T_dm"),
    ("filter_time_constant", "T_f"),
    ("pendulum_mass", "m"),
    ("pendulum_length", "l"),
    ("pickoff_gain", "k_dp"),
    ("amplifier_gain", "k_y"),
)
"""Values of the nominal device the step diagnosis takes as known (never refitted), as
listed in its summary (the lags: an effect is a departure from them)."""


def _known_values(nominal, rec) -> dict:
    known = {}
    for field, symbol in KNOWN_FIELDS:
        known[field] = {"symbol": symbol, "value": float(getattr(nominal.params, field))}
    refitted = {
        f: float(rec.prior_sigma[j])
        for j, f in enumerate(REFIT_FIELDS)
        if rec.prior_sigma[j]
    }
    for j, field in enumerate(REFIT_FIELDS):
        if not rec.prior_sigma[j]:
            known[field] = {"symbol": field, "value": float(getattr(nominal.params, field))}
    return {"known": known, "refitted_prior_relative_sigma": refitted}


def _known_text(nominal) -> str:
    lags = ", ".join(
        f"{symbol} {time_text(float(getattr(nominal.params, field)))}"
        if float(getattr(nominal.params, field)) > 0
        else f"{symbol} 0"
        for field, symbol in KNOWN_FIELDS[:2]
    )
    return f"taken as known from the nominal device: {lags} (a lag effect departs from these)"


def _refit_report(
    nominal,
    nominal_fit: StepFit,
    by_name: dict[str, StepFit],
    shown,
    rec: StepRecord,
    sigma,
    verdict,
    nuisance_test: NuisanceTest,
):
    """The refit as the summary shows it: the device's values under the model the verdict
    names (or the first of a tie; the nominal model when it names none), and beside them
    the nominal model's own refit, labelled as such: the refit a model without the effect
    needs is not the device's state; the nuisances judged together (`nuisance_test`,
    `nuisance.nuisance_test`'s) last."""
    model_fit = by_name.get(shown) if shown else None
    if model_fit is None:
        model_fit = nominal_fit
    parameters = _parameter_shifts(nominal, model_fit, rec)
    w = nominal_fit.w
    ctx_scale = float(rec.ctx.scale)
    shifts = change_shifts(np.asarray(w), rec.ctx)[: rec.change_index.size]
    measured = np.asarray(nominal_fit.prediction) + nominal_fit.error
    rms_prior = float(np.sqrt(np.mean((measured - nominal_fit.prior_prediction) ** 2)))
    rms_refit = float(np.sqrt(np.mean(nominal_fit.error**2)))

    def scale_factor_of(fit: StepFit) -> float:
        z, prior_sigma = jnp.asarray(fit.z), jnp.asarray(rec.prior_sigma)
        return float(scale_factor(refitted_device(nominal.params, z, prior_sigma)))

    scale_factors = {
        "nominal_refit": scale_factor_of(nominal_fit),
        "with_effect": scale_factor_of(by_name.get(shown) or nominal_fit),
        "prior": float(scale_factor(nominal.params)),
    }
    return {
        "parameters": parameters,
        "model": shown if model_fit is not nominal_fit else "nominal",
        "nominal_model_parameters": _parameter_shifts(nominal, nominal_fit, rec),
        "nominal_model_out_of_prior": list(nominal_fit.out_of_prior),
        "nominal_device": _known_values(nominal, rec),
        "converged": nominal_fit.converged,
        "credible": nominal_fit.plausible,
        "out_of_prior": list(nominal_fit.out_of_prior),
        "nuisances": {
            "test_winding_polarity": "reversed" if rec.polarity < 0 else "as the nominal",
            "test_winding_gain": abs(nominal_fit.gain),
            "test_winding_gain_sigma": nominal_fit.z_gain,
            "external_moment_V": ctx_scale * float(w[W.MOMENT]),
            "external_moment_Nm": ctx_scale * float(w[W.MOMENT]) * rec.host.torquer_gain,
            "initial_displacement_V": ctx_scale * float(w[W.DV]),
            "initial_velocity_V": ctx_scale * float(w[W.DW]),
            "change_time_shift_samples": [float(x) for x in shifts],
            "adc_step_V": rec.floor.adc_step,
        },
        "rms_before_refit_V": rms_prior,
        "rms_after_refit_V": rms_refit,
        "gap_closed_by_refit": 1 - rms_refit / rms_prior if rms_prior > 0 else 0.0,
        "description": "J, μ, c, k_dm refitted under their prior; the nuisances (test winding "
        "polarity and gain, offset, initial state, change times) fitted in every model; "
        + _known_text(nominal),
        "scale_factor_V_per_mps2": scale_factors,
        "scale_factor_shift_by_effect": (
            scale_factors["with_effect"] / scale_factors["nominal_refit"] - 1
        ),
        "parameter_error": bool(
            verdict == "none" and rms_prior > 3 * sigma and rms_refit < 1.5 * sigma
        ),
        "nuisance_test": nuisance_test.to_dict(),
    }


def _localise(data: RecordView, residual: np.ndarray, sigma: float, rec: StepRecord) -> dict:
    """Where the nominal refit's residual lies: per input segment (transient vs steady
    state), in frequency against the white-noise floor, and its whiteness."""
    u = np.asarray(data.u_test)
    n = u.shape[0]
    dt = rec.dt
    edges = segments(u)
    conditions = []
    transient_sq, transient_n, steady_sq, steady_n = 0.0, 0, 0.0, 0
    for start, stop in zip(edges[:-1], edges[1:], strict=True):
        cut = start + max(1, int(TRANSIENT_FRACTION * (stop - start)))
        r_t, r_s = residual[start:cut], residual[cut:stop]
        transient_sq += float(np.sum(r_t**2))
        transient_n += r_t.size
        steady_sq += float(np.sum(r_s**2))
        steady_n += r_s.size
        conditions.append(
            {
                "t_start_s": float(data.t[start]),
                "u_test_V": float(u[start]),
                "held_out": bool(rec.held[min(start, rec.held.size - 1)]),
                "rms_transient_V": float(np.sqrt(np.mean(r_t**2))),
                "rms_steady_V": float(np.sqrt(np.mean(r_s**2))) if r_s.size else None,
            }
        )
    # Welch periodogram (Hann, 50 % overlap) against the white floor 2σ²dt [V²/Hz].
    length = int(min(256, 2 ** np.floor(np.log2(max(n // 4, 16)))))
    window = np.hanning(length)
    hop = length // 2
    frames = [residual[i : i + length] for i in range(0, n - length + 1, hop)]
    spectra = [np.abs(np.fft.rfft((f - f.mean()) * window)) ** 2 for f in frames]
    psd = 2 * dt * np.mean(spectra, axis=0) / np.sum(window**2)
    freqs = np.fft.rfftfreq(length, dt)
    floor = 2 * sigma**2 * dt
    above = psd[1:] > 4 * floor
    band = freqs[1:][above]
    return {
        "time": {
            "rms_transient_V": float(np.sqrt(transient_sq / max(transient_n, 1))),
            "rms_steady_V": float(np.sqrt(steady_sq / max(steady_n, 1))),
            "transient_fraction_of_segment": TRANSIENT_FRACTION,
        },
        "conditions": conditions,
        "frequency": {
            "noise_floor_V2_per_Hz": floor,
            "peak_excess_Hz": float(freqs[1:][np.argmax(psd[1:] / floor)]),
            "peak_excess_ratio": float(np.max(psd[1:]) / floor),
            "fraction_of_bins_above_4x_floor": float(np.mean(above)),
            "band_above_4x_floor_Hz": [float(band.min()), float(band.max())] if band.size else None,
            "frequency_Hz": freqs.tolist(),
            "psd_V2_per_Hz": psd.tolist(),
        },
        "whiteness": ljung_box(residual),
        "noise_sigma_pilot_V": sigma,
    }


def _ranges(mask: np.ndarray) -> list[list[int]]:
    """[start, stop) of each run of True in a mask."""
    padded = np.concatenate([[False], mask, [False]]).astype(int)
    edges = np.flatnonzero(np.diff(padded))
    return [[int(a), int(b)] for a, b in zip(edges[::2], edges[1::2], strict=True)]
