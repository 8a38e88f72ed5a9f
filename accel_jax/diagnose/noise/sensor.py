"""The noise kind beyond its three library noises: the effects real sensors show
(`accel_jax.select_sensor_noise`: output grid, periodic lines, the sensor's low-pass,
flicker, start-up transient, on top of Gauss–Markov, exponential-cosine and random walk),
combined with the exact time-domain diagnosis (`entry`, `verdict`).

**When it runs.** The exact diagnosis (Kalman likelihood, one effect at a time) decides on
records up to `EXACT_LIMIT` samples. The forward selection (Whittle likelihood, effects
added while significant) runs as well when that verdict is `unexplained`, `cannot_tell` or
`random_walk` (a step in the level has a walk's spectrum; the selection's level-shift test
tells them apart), when a model-free screen sees a step in the level
(`level_shift_screen`: one the exact verdict took into a Gauss–Markov process or white
noise), when the record's values are far from Gaussian (`detect_non_gaussian`: a random
telegraph noise has a Gauss–Markov spectrum), when its spectrum changes between its halves
(`detect_spectral_change`: a line that moves, a vibration that starts or stops), or when the
record lies on an output grid
coarse enough to name; beyond
`EXACT_LIMIT` samples it alone decides (the exact filter of 10⁶ samples × candidates takes
minutes, the Whittle selection seconds).

**The verdict.** When the selection names an effect outside the three, or several effects,
the verdict is the composite it names (`bandlimit+sinusoid+quantization`, with
`+unexplained` when its held-out test fails); otherwise the exact verdict stands (on short
records the exact likelihood is the sharper one). The selection's steps, parameters and
held-out test are in `where["sensor_effects"]`, the Allan deviation with its ±1σ
intervals in `where["allan"]`.
"""

from __future__ import annotations

import math

import numpy as np

from ..._noise import allan_deviation_intervals, detect_quantization, select_sensor_noise
from ..._noise.sensor import SensorNoiseSelection
from ..._noise.sensor_model import DEVIANCE_VARIANCE
from ..._noise.sensor_screens import (
    QUANTIZATION_SHARE,
    detect_non_gaussian,
    detect_saturation,
    detect_spectral_change,
    grid_noise_share,
    level_shift_screen,
)
from ..._noise.sensor_text import (
    level_shift_sentence,
    low_pass_ties_sentence,
    low_pass_words,
    non_gaussian_sentence,
    saturation_sentence,
    spectral_change_sentence,
    white_floor_sentence,
)
from ..base import DiagnosisResult

EXACT_LIMIT = 20_000
"""Records longer than this are diagnosed by the forward selection alone."""

CLASSIC = ("gauss_markov", "exp_cosine", "random_walk")


def needs_selection(x: np.ndarray, verdict: str | None) -> bool:
    """Whether the forward selection should run on this record (module docstring)."""
    if verdict is None or verdict in ("unexplained", "cannot_tell"):
        return True
    if verdict == "random_walk":
        # A step in the level has a random walk's 1/f² spectrum: the selection's
        # level-shift test (time domain) tells them apart.
        return True
    if level_shift_screen(x)["significant"]:
        # A step the one-effect diagnosis took into a Gauss–Markov process or white noise
        # (a model-free screen; the selection's test judges it against the fitted model).
        return True
    if detect_spectral_change(x)["significant"]:
        # The spectrum changes between the record's halves (a line that moves, a vibration
        # that starts or stops): every exact model is stationary, and its verdict names
        # the record's average spectrum; the selection's residual test says so.
        return True
    grid = detect_quantization(x)
    if detect_saturation(x, grid):
        # A clipped record: the exact diagnosis has no word for a rail; the selection does.
        return True
    if detect_non_gaussian(x, grid)["significant"]:
        # Values not Gaussian (two levels, heavy tails): the exact diagnosis, Gaussian by
        # construction, names their spectrum; the selection's residual test says so.
        return True
    return grid_noise_share(x, grid) >= QUANTIZATION_SHARE


def allan_summary(x: np.ndarray, dt: float) -> dict:
    adev = allan_deviation_intervals(x, dt)
    return {
        "tau_s": adev.taus.tolist(),
        "adev_g": adev.deviation.tolist(),
        "lower_1sigma_g": adev.lower.tolist(),
        "upper_1sigma_g": adev.upper.tolist(),
        "edf": adev.edf.tolist(),
    }


def selection_summary(sel: SensorNoiseSelection) -> dict:
    return {
        "verdict": sel.verdict,
        "effects": list(sel.effects),
        "unexplained": sel.unexplained,
        "steps": sel.steps,
        "parameters": sel.parameters,
        "held_out": sel.held_out.to_dict(),
        "quantization": sel.quantization,
        "method": "forward selection on the debiased Whittle likelihood of the differenced "
        "record (training: first 2/3; held out: last 1/3)",
    }


def _capitalised(sentence: str) -> str:
    """A sentence of `sensor`'s (lower case, for the CLI's lists) as the next sentence here."""
    return ". " + sentence[0].upper() + sentence[1:]


def _chain_sentences(held) -> str:
    """The low-pass shapes the record cannot tell from the named one, and a white floor
    gone into a coloured process (a fit failure)."""
    text = ""
    if held.low_pass_ties:
        text += _capitalised(low_pass_ties_sentence(held.low_pass_ties))
    if held.white_floor and held.white_floor["collapsed"]:
        text += _capitalised(white_floor_sentence(held.white_floor))
    return text


def _describe(sel: SensorNoiseSelection) -> str:
    parts = []
    for step in sel.steps[1:]:
        name = step["added"]
        detail = ""
        p = sel.parameters
        if name in ("bandlimit", "filter_floor"):
            band = p["bandlimit"]
            after = band.get("white_after_filter_sigma")
            after = "" if after is None else f", white noise after it σ {after:.3g} g"
            detail = f" ({low_pass_words(band)}, −3 dB at {band['corner_Hz']:.3g} Hz{after})"
        elif name == "flicker":
            detail = f" (B = {p['flicker']['bias_instability_B']:.3g} g)"
        elif name == "gauss_markov":
            gm = p["gauss_markov"]
            detail = f" (σ {gm['sigma']:.3g} g, τ_c {gm['correlation_time_s']:.3g} s)"
        elif name == "exp_cosine":
            ec = p["exp_cosine"]
            detail = f" ({ec['angular_frequency_rad_per_s'] / (2 * math.pi):.3g} Hz)"
        elif name == "startup_transient":
            st = p["startup_transient"]
            detail = f" ({st['amplitude']:.3g} g, τ {st['time_constant_s']:.3g} s)"
        parts.append(f"+ {name}{detail}: 2 ln B = {step['evidence']:.0f}")
    lines = p.get("sinusoid", []) if (p := sel.parameters) else []
    if lines:
        parts.append("lines at " + ", ".join(f"{line['frequency_Hz']:.4g} Hz" for line in lines))
    if sel.quantization is not None and "quantization" in sel.effects:
        parts.append(f"output grid {sel.quantization['step']:.3g} g")
    text = "forward selection: " + "; ".join(parts) if parts else "forward selection: nothing"
    held = sel.held_out
    bursts = held.bursts
    if bursts:
        at = ", ".join(f"{b['start_s']:.4g} s" for b in bursts[:5])
        text += (
            f". {len(bursts)} impulsive event(s) (first differences beyond 8 robust σ; at "
            f"{at}; peak {max(b['peak'] for b in bursts):.3g} g) that no Gaussian effect makes"
        )
    for shift in held.level_shifts:
        text += _capitalised(level_shift_sentence(shift))
    if held.more_level_shifts:
        text += f". More steps than the {len(held.level_shifts)} taken out"
    for rail in held.saturation:
        text += _capitalised(saturation_sentence(rail))
    text += _chain_sentences(held)
    gaussian = held.non_gaussian
    if gaussian.get("significant") and not bursts:
        text += _capitalised(non_gaussian_sentence(gaussian))
    change = held.spectral_change
    if change.get("significant"):
        duration = sel.n_samples * sel.sample_interval
        text += _capitalised(spectral_change_sentence(change, duration))
    drift = held.drift
    if drift and held.drifting and not bursts and held.z <= 4.0:
        text += (
            f". The level drifts {drift['slope_per_s']:.3g} g/s ({drift['t']:.0f} standard "
            "errors over block means), which no named effect makes"
        )
    if held.z > 4.0:
        text += (
            f". What it leaves is unexplained: the held-out spectrum stays {held.z:.1f} "
            "standard errors above the final model's"
        )
    else:
        text += f". The held-out spectrum fits the final model ({held.z:+.1f} standard errors)"
    if (
        sel.unexplained
        and not bursts
        and held.z <= 4.0
        and not held.level_shifts
        and not held.saturation
        and not gaussian.get("significant")
        and not change.get("significant")
    ):
        text += " (unexplained)"
    return text + "."


def combine(result: DiagnosisResult, sel: SensorNoiseSelection) -> DiagnosisResult:
    """The exact diagnosis `result` with the selection: the composite verdict when the
    selection names an effect beyond the three or several effects."""
    result.where["sensor_effects"] = selection_summary(sel)
    beyond = [e for e in sel.effects if e not in CLASSIC]
    held = sel.held_out
    if (
        beyond
        or len(sel.effects) > 1
        or held.level_shifts
        or held.saturation
        or held.non_gaussian.get("significant")
        or held.spectral_change.get("significant")
    ):
        previous = result.verdict
        result.verdict = sel.verdict
        result.tied = []
        result.explained_fraction = sel.steps[-1]["explained_fraction"]
        result.reason = (
            _describe(sel) + f" (the exact one-effect diagnosis alone said {previous}; the "
            "explained fraction is of the held-out excess spectral deviance)"
        )
    return result


def from_selection(x: np.ndarray, t: np.ndarray, dt: float, sel: SensorNoiseSelection, welch):
    """A `DiagnosisResult` of a long record from the selection alone."""
    steps = sel.steps
    held = sel.held_out
    before = steps[0]["held_out_z"] * math.sqrt(DEVIANCE_VARIANCE * held.bins)
    after = held.excess_deviance
    sd = math.sqrt(DEVIANCE_VARIANCE * held.bins)
    ranking = [
        {
            "effect": step["added"],
            "evidence": step["evidence"],
            "gap_shrink": step["explained_fraction"],
            "significant": True,
            "explains": bool(i == len(steps) - 1 and not sel.unexplained),
            "stochastic": step["added"] not in ("sinusoid", "startup_transient"),
            "held_out_gain": step["held_out_gain"],
        }
        for i, step in enumerate(steps[1:], start=1)
    ]
    split = int(round(2 / 3 * x.size))
    level = float(np.mean(x[:split]))
    white = sel.parameters["white_sigma"]
    freqs, psd = welch(x - level, dt)
    shrink = 1 - max(after, 0.0) / before if before > 0 else 0.0
    return DiagnosisResult(
        kind="noise",
        verdict=sel.verdict,
        tied=[],
        ranking=ranking,
        gap={
            "unit": "deviance",
            "before": max(before, 0.0),
            "after": max(after, 0.0),
            "shrink": shrink,
            "shrink_std": sd / before if before > 0 else float("inf"),
            "model_after": sel.verdict,
            "held_out": f"the last {x.size - split} of {x.size} samples (their periodogram)",
            "metric": "held-out Whittle deviance in excess of its expectation under the model",
        },
        where={
            "frequency": {
                # the short-term floor: half the variance of the first difference (the
                # fitted white σ_w can be ~0 when a fast Gauss–Markov noise takes its place)
                "noise_floor_g2_per_Hz": float(np.var(np.diff(x[:split]))) * dt,
                "frequency_Hz": freqs.tolist(),
                "psd_g2_per_Hz": psd.tolist(),
            },
            "noise_sigma_g": white,
            "sensor_effects": selection_summary(sel),
        },
        refit={
            "parameters": {},
            "nominal_fit": {"white_sigma_g": white, "level_g": level},
            "description": f"white noise σ_w = {white:.4g} g (Whittle fit, training part) "
            f"about the level {level:.9g} g",
            "parameter_error": False,
        },
        traces={"t": t, "measured": x, "level": level, "split": split},
        notes=[
            f"a record of {x.size} samples (> {EXACT_LIMIT}) is diagnosed by the Whittle "
            "forward selection alone (the exact time-domain filter is its check on shorter "
            "records)"
        ],
        explained_fraction=steps[-1]["explained_fraction"],
        remaining_gap={
            "deviance": max(after, 0.0),
            "noise_floor_deviance": sd,
            "over_floor": held.z,
            "model": sel.verdict,
        },
        reason=_describe(sel),
    )


def run_selection(x: np.ndarray, dt: float) -> SensorNoiseSelection:
    return select_sensor_noise(x, dt)
