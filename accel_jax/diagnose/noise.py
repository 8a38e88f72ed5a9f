"""The `noise` kind: a static record, its nominal model (white noise) and its effects.

**Nominal model** (what a white-noise assumption means, docs/models.md §4): the indicated
acceleration of a static sensor is an unknown constant level plus white noise,

    a_out(t_k) = ℓ + σ_w w_k                                                          [g].

The level has a diffuse prior in every model (the record's mean is not known in advance),
so that all candidates are compared on the same terms, by the exact Gaussian likelihood of
the record conditional on its first sample, log p(x_2..x_N | x_1), as
`accel_jax._noise.log_likelihood` defines it.

**Effects** (each adds one process of `accel_jax._noise` to the white noise and is exactly
the nominal model when its amplitude is zero):

- `gauss_markov`: + first-order Gauss–Markov noise, R(τ) = σ² e^{−|τ|/τ_c};
- `exp_cosine`: + exponential-cosine noise, R(τ) = σ² e^{−α|τ|} cos βτ (the paper's
  "structured residual" model, Chernodarov et al. (16));
- `random_walk`: the level itself walks, ℓ_{k+1} = ℓ_k + √(qΔ) w_k (at q = 0 it is the
  nominal constant level, exactly).

An exponential-cosine noise at β = 0 is a Gauss–Markov noise, and a Gauss–Markov noise whose
τ_c outgrows the record looks like a random walk; those nested pairs are told apart by a
likelihood-ratio test when the evidence alone ties (`rank_candidates(nested=...)`).

**Fit**: exact maximum likelihood on the training part (the first `1 − HELD_OUT_FRACTION`
of the record): a Whittle (frequency-domain) fit of the differenced record gives the start,
then BFGS (optimistix) on the exact likelihood polishes it. The likelihood is the Kalman
filter of the state-space forms of `accel_jax._noise` (state: level, the two components of
the exponential-cosine rotation — a Gauss–Markov noise is its β = 0 case), written out for
this three-state model with a scalar observation so that a batch of records × candidates
runs as one fused loop (the generic `accel_jax._kalman.kalman_filter` gives the same
numbers — the tests check it against `accel_jax._noise.log_likelihood` — about ten times
slower). Parameters are scaled so that zero is reachable: the effect's standard deviation is
z·s₀ (s₀ the record's RMS), the random walk's increment RMS z·s₀.

**Held out**: the last `HELD_OUT_FRACTION` of the record. The filter with the training fit
runs over the whole record, and the one-step prediction errors (innovations) of the
held-out part are the held-out errors: the gap is the RMS innovation above the noise floor
(the innovation variance the best model leaves on the training part).

Float64 throughout (log-likelihoods of thousands of samples compared to within a unit).
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from .._data import DataError, NoiseData, NominalDevice
from .._noise import initial_model
from .._sweep import even_chunk_size, sweep
from . import noise_sensor, openworld
from .base import (
    NESTED_LEVEL,
    CandidateFit,
    DiagnosisResult,
    _resolve_nested,
    held_out_gap,
    ljung_box,
    rank_candidates,
    require_float64,
)
from .noise_effects import _SLOT, STARTS
from .noise_fit import _bands, _effects, _fit_record, model_intervals

EXACT_LIMIT = noise_sensor.EXACT_LIMIT

HELD_OUT_FRACTION = 1 / 3
"""The last third of the record is held out."""


NESTED = {"exp_cosine": "gauss_markov", "gauss_markov": "random_walk"}
"""An exponential-cosine noise at β = 0 is a Gauss–Markov noise; a Gauss–Markov noise with
τ_c → ∞ (σ² ∝ τ_c) is a random walk."""


BATCH_CHUNK = 64
"""Records fitted per compiled call (a vmapped batch runs until its slowest fit stops)."""


# --------------------------------------------------------------------------------------
# Host side: context, evidence, localisation
# --------------------------------------------------------------------------------------


def _context(data: NoiseData, effects) -> dict:
    x = np.asarray(data.a_out, dtype=np.float64)
    n = x.size
    split = int(round((1 - HELD_OUT_FRACTION) * n))
    train = x[:split]
    if np.ptp(train) == 0:
        raise DataError(
            f"noise record: a_out is constant ({float(train[0])!r} g) over the training part "
            f"(first {split} samples); no noise to diagnose (a disconnected or saturated channel?)."
        )
    level = float(np.mean(train))
    scale = float(np.std(train))
    dt = float(data.sample_period)
    normalised = (x - level) / scale
    initial = {}
    for effect in effects:
        try:
            initial[effect.name] = initial_model(effect.structure, normalised[:split], dt)
        except ValueError as error:
            raise DataError(f"noise record: {error}") from None
    host = {"initial_models": initial, "dt": dt}
    guesses = np.zeros((1 + len(effects), STARTS, 1 + _SLOT))  # nominal: σ_w = s₀ (z = 0)
    for i, effect in enumerate(effects, start=1):
        guess = effect.initial_guess(host)
        guesses[i, :, 0] = math.log(float(initial[effect.name].components[0].sigma))
        guesses[i, 0, 1 : 1 + effect.n_params] = guess
        guesses[i, 1:, 1 : 1 + effect.n_params] = effect.alternative_starts(guess)
    return {
        "normalised": normalised,
        "split": split,
        "level": level,
        "scale": scale,
        "dt": dt,
        "duration": float(data.t[-1] - data.t[0]),
        "guesses": guesses,
    }


def _welch(x: np.ndarray, dt: float):
    n = x.size
    length = int(min(512, 2 ** np.floor(np.log2(max(n // 4, 16)))))
    window = np.hanning(length)
    hop = length // 2
    frames = [x[i : i + length] for i in range(0, n - length + 1, hop)]
    spectra = [np.abs(np.fft.rfft((f - f.mean()) * window)) ** 2 for f in frames]
    psd = 2 * dt * np.mean(spectra, axis=0) / np.sum(window**2)
    return np.fft.rfftfreq(length, dt), psd


def _localise(residual: np.ndarray, innovations: np.ndarray, sigma: float, host: dict) -> dict:
    """Where the nominal model's residual departs from white noise: its spectrum against the
    white floor (by frequency band), its autocorrelation (Ljung–Box), and its level and
    spread over segments of the record (a random walk wanders, a stationary noise not)."""
    dt = host["dt"]
    freqs, psd = _welch(residual, dt)
    floor = 2 * sigma**2 * dt
    f, p = freqs[1:], psd[1:]
    edges = np.geomspace(f[0], f[-1], 9)
    bands = []
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        inside = (f >= lo) & (f <= hi)
        if np.any(inside):
            bands.append(
                {
                    "band_Hz": [float(lo), float(hi)],
                    "psd_over_floor": float(np.mean(p[inside]) / floor),
                }
            )
    above = p > 2 * floor
    segments = []
    n = residual.size
    for k in range(8):
        part = residual[k * n // 8 : (k + 1) * n // 8]
        segments.append(
            {
                "t_start_s": float(k * n // 8 * dt),
                "mean_g": float(np.mean(part)),
                "rms_g": float(np.sqrt(np.mean(part**2))),
                "held_out": bool(k * n // 8 >= host["split"]),
            }
        )
    whiteness = ljung_box(innovations, lags=20)
    return {
        "frequency": {
            "noise_floor_g2_per_Hz": floor,
            "bands": bands,
            "peak_excess_Hz": float(f[np.argmax(p / floor)]),
            "peak_excess_ratio": float(np.max(p) / floor),
            "fraction_of_bins_above_2x_floor": float(np.mean(above)),
            "frequency_Hz": freqs.tolist(),
            "psd_g2_per_Hz": psd.tolist(),
        },
        "whiteness": whiteness,
        "time": {"segments": segments},
        "noise_sigma_g": sigma,
    }


def _postprocess(data: NoiseData, host: dict, effects, outputs) -> DiagnosisResult:
    zs, nus, ss, log_liks, converged, steps = (np.asarray(o) for o in outputs)
    split, scale, dt = host["split"], host["scale"], host["dt"]
    n = nus.shape[1]
    names = ["nominal"] + [e.name for e in effects]
    context = {"scale": scale, "dt": dt, "duration": host["duration"]}
    fits = []
    # Log-likelihoods in the record's unit: the normalisation by s₀ shifts every model by
    # the same −(n_terms) ln s₀.
    unit_shift = -(split - 1) * math.log(scale)
    for i, name in enumerate(names):
        innovation = nus[i] * scale
        params = {}
        if i:
            params = effects[i - 1].physical(zs[i, 1 : 1 + effects[i - 1].n_params], context)
        params["white_sigma_g"] = math.exp(float(zs[i, 0])) * scale
        fits.append(
            CandidateFit(
                effect=name,
                n_effect_params=0 if i == 0 else effects[i - 1].n_params,
                log_likelihood=float(log_liks[i]) + unit_shift,
                n_train=split,
                held_out_ms=float(np.mean(innovation[split:] ** 2)),
                held_out_errors=innovation[split:],
                train_ms=float(np.mean(innovation[1:split] ** 2)),
                params=params,
                converged=bool(converged[i]),
            )
        )
    _, ranking, _ = rank_candidates(fits[0], fits[1:], nested=NESTED)
    by_name = {f.effect: f for f in fits}
    # Open world: a model explains the record when its held-out one-step errors, each
    # scaled by the variance the model predicts for it, are white with unit variance (to
    # 3 standard errors), and no periodic line of its training errors continues into the
    # held-out ones. The line test runs on each model's own standardised one-step errors,
    # whose null is white: on the raw record a slow Gauss–Markov wander alone would pass
    # for a low-frequency line (a τ = 50 s record at 1 Hz did: a 0.0011 Hz "line" that
    # predicted over 20 % of the held-out part).
    n_test = n - split
    assessed = {}
    for i, name in enumerate(names):
        predicted = ss[i, split:] * scale**2
        scaled = by_name[name].held_out_errors / np.sqrt(predicted)
        test = openworld.whiteness(scaled)
        ratio = float(np.mean(scaled**2))
        # The predicted variance comes from the fit to the training part: both parts'
        # sampling errors count (2/n each for a variance), not the held-out part's alone.
        spread = math.sqrt(2 / max(n_test, 1) + 2 / max(split, 1))
        consistent = abs(ratio - 1) <= 3 * spread
        standardised = nus[i] / np.sqrt(np.maximum(ss[i], np.finfo(float).tiny))
        line = openworld.predictability(
            standardised[1:],
            split - 1,
            dt,
            np.zeros(0, int),
            np.zeros(0),
            1,
            tests=("periodic",),
            line_z=openworld.LINE_Z,
        )
        assessed[name] = {
            "floor": float(np.mean(predicted)),
            "whiteness": test,
            "variance_ratio": ratio,
            "predictable": line,
            "explains": bool(test["white"] and consistent and not line["deterministic"]),
        }
    for entry in ranking:
        own = assessed[entry["effect"]]
        before = openworld.excess(fits[0].held_out_ms, own["floor"])
        after = openworld.excess(by_name[entry["effect"]].held_out_ms, own["floor"])
        entry.update(
            {
                "stochastic": True,
                "explains": own["explains"],
                # A fit that stopped short of its maximum only understates its evidence
                # (a lower bound), as in the step kind: it stays credible. (Whether the
                # exp-cosine fit of a near-undamped line reaches its tolerance within the
                # step limit depended on the batch it ran in.)
                "plausible": bool(np.isfinite(entry["evidence"])),
                "one_step_whiteness": own["whiteness"],
                "variance_ratio": own["variance_ratio"],
                "deterministic_misfit": own["predictable"]["deterministic"],
                "explained_fraction": openworld.explained_fraction(before, after),
            }
        )
    nominal_status = {
        "explains": assessed["nominal"]["explains"],
        "white": assessed["nominal"]["whiteness"]["white"],
        "plausible": bool(converged[0]),
    }
    decision = openworld.decide(
        nominal_status,
        ranking,
        resolve_tie=lambda a, b: _resolve_nested(a, b, fits[1:], NESTED, NESTED_LEVEL),
    )
    verdict, tied = decision["verdict"], decision["tied"]
    shown = decision["chosen"] or decision["best_partial"]
    chosen = shown or "nominal"
    # The noise floor is the shown model's own predicted innovation variance on the
    # held-out part (the filter's S_k): what remains above it is what the model did not
    # expect. (A floor estimated on the training part would add the sampling mismatch of
    # two segments' variances, as large as the excess being measured.)
    floor = assessed[chosen]["floor"]
    for entry in ranking:
        g = held_out_gap(fits[0].held_out_errors, by_name[entry["effect"]].held_out_errors, floor)
        entry["gap_shrink"] = g["shrink"]
        entry["fit_steps"] = int(steps[names.index(entry["effect"])])
    after = by_name[chosen].held_out_errors
    gap = held_out_gap(fits[0].held_out_errors, after, floor)
    gap["unit"] = "g"
    gap["model_after"] = chosen
    gap["held_out"] = f"the last {n - split} of {n} samples (one-step prediction errors)"
    gap["metric"] = (
        "held-out RMS one-step prediction error in excess of the chosen model's predicted "
        "innovation variance"
    )
    fraction = next((e["explained_fraction"] for e in ranking if e["effect"] == shown), 0.0)
    remaining = gap["after"]
    remaining_gap = {
        "g": remaining,
        "noise_floor_g": math.sqrt(floor),
        "over_floor": remaining / math.sqrt(floor) if floor > 0 else float("inf"),
        "model": chosen,
        "whiteness_p_value": assessed[chosen]["whiteness"]["p_value"],
    }
    line = assessed[chosen]["predictable"]
    if line["deterministic"]:
        # A line is a gap the RMS hardly shows: its amplitude, in g, beside the RMS gap.
        remaining_gap["periodic_line"] = {
            "frequency_Hz": line["frequency_Hz"],
            "rms_g": line["periodic_rms"] * math.sqrt(floor),
            "z": line["periodic_z"],
        }
    predictable = assessed[chosen]["predictable"]
    reason = _reason(decision, assessed, ranking, predictable, remaining, floor, chosen)

    white_sigma = fits[0].params["white_sigma_g"]
    x = np.asarray(data.a_out)
    residual = x - host["level"]
    refit = {
        "parameters": {},
        "nominal_fit": {"white_sigma_g": white_sigma, "level_g": host["level"]},
        "model": "a_out = level + σ_w w (white noise about a constant level; no prior)",
        "parameter_error": False,
        "converged": bool(converged[0]),
        "description": (
            f"the nominal model (white noise alone) has σ_w = {white_sigma:.4g} g about the "
            f"level {host['level']:.7g} g (fitted on the training part)"
        ),
    }
    chosen_index = names.index(chosen)
    # The numbers a Kalman filter needs: the shown model's parameters with intervals.
    model = model_intervals(
        zs[chosen_index],
        host["normalised"],
        split,
        jnp.asarray(chosen_index),
        effects[chosen_index - 1] if chosen_index else None,
        context,
    )
    model["model"] = "white" if chosen_index == 0 else f"white+{chosen}"
    refit["model_parameters"] = model
    where = _localise(residual, nus[0], white_sigma, host)
    traces = {
        "t": np.asarray(data.t),
        "measured": x,
        "level": host["level"],
        "innovations_before": nus[0] * scale,
        "innovations_after": nus[chosen_index] * scale,
        "best_name": chosen,
        "split": split,
    }
    where["predictability"] = predictable
    return DiagnosisResult(
        kind="noise",
        verdict=verdict,
        tied=tied,
        ranking=ranking,
        gap=gap,
        where=where,
        refit=refit,
        traces=traces,
        notes=list(getattr(data, "notes", ())),
        explained_fraction=fraction,
        remaining_gap=remaining_gap,
        reason=reason,
    )


def _reason(decision, assessed, ranking, predictable, remaining, floor, chosen) -> str:
    verdict = decision["verdict"]
    sigma = math.sqrt(floor)
    entry = {e["effect"]: e for e in ranking}
    if verdict == "none":
        return (
            "the held-out record is white noise about its level (Ljung–Box p = "
            f"{assessed['nominal']['whiteness']['p_value']:.2g}) and no effect is significant."
        )
    if verdict == "cannot_tell":
        a, b = decision["tied"]
        return (
            f"{a} and {b} both whiten the held-out record and their evidence differs by "
            f"{abs(entry[a]['evidence'] - entry[b]['evidence']):.1f} (< 6 on the 2 ln B scale)."
        )
    if verdict != "unexplained":
        return (
            f"with {verdict} the held-out one-step prediction errors are white (Ljung–Box p = "
            f"{assessed[verdict]['whiteness']['p_value']:.2g}) at the variance it predicts; "
            f"evidence 2 ln B = {entry[verdict]['evidence']:.1f} over white noise."
        )
    parts = []
    if predictable["deterministic"]:
        parts.append(
            f"a periodic line at {predictable['frequency_Hz']:.4g} Hz continues from the "
            f"training part into the held-out one-step errors of {chosen} (projection "
            f"{predictable['periodic_z']:.1f} standard errors, {predictable['periodic']:.1%} "
            "of their mean square): deterministic, not one of the library's noises"
        )
    elif abs(predictable["periodic_z"]) >= openworld.LINE_Z and predictable["frequency_Hz"]:
        # A line of the training part whose continuation is anti-correlated (or far off)
        # with the held-out part: a real spectral line whose phase or frequency wanders.
        parts.append(
            f"a spectral line at {predictable['frequency_Hz']:.4g} Hz in the training part "
            f"does not carry its phase into the held-out part (projection "
            f"{predictable['periodic_z']:.1f} standard errors): a wandering line"
        )
    if decision["best_partial"]:
        best = decision["best_partial"]
        own = assessed[best]
        if not own["whiteness"]["white"]:
            p_value = own["whiteness"]["p_value"]
            short = f"its one-step errors are not white (Ljung–Box p = {p_value:.2g})"
        elif own["predictable"]["deterministic"]:
            short = "it leaves the line"
        else:
            short = (
                f"its one-step errors are {math.sqrt(own['variance_ratio']):.3g}× the size it "
                "predicts"
            )
        parts.append(
            f"the best library effect, {best}, explains {entry[best]['explained_fraction']:.0%} "
            f"of the excess, but {short}; {remaining:.3g} g above its {sigma:.3g} g floor "
            "remains"
        )
    elif not any(e["significant"] for e in ranking):
        nominal = assessed["nominal"]
        p_value = nominal["whiteness"]["p_value"]
        if nominal["predictable"]["deterministic"]:
            why = "the line is not one of the library's noises"
        elif nominal["whiteness"]["white"]:
            why = (
                f"the held-out record is white (Ljung–Box p = {p_value:.2g}) but its variance "
                f"is {nominal['variance_ratio']:.3g}× the training part's"
            )
        else:
            why = (
                "the record is not white noise (Ljung–Box p = "
                f"{nominal['whiteness']['p_value']:.2g})"
            )
        parts.append(why + " and no library effect is significant")
    else:
        parts.append(
            "no library noise leaves white one-step prediction errors (best: "
            f"{chosen}, Ljung–Box p = {assessed[chosen]['whiteness']['p_value']:.2g})"
        )
    return "; ".join(parts) + "."


def diagnose_noise(
    datasets: list[NoiseData], nominal: NominalDevice | None = None
) -> list[DiagnosisResult]:
    """Diagnose static noise records (docs/models.md §5, `noise` kind).

    Records of one length are fitted together (one compilation, every candidate of every
    record vmapped, in chunks of `BATCH_CHUNK` records): Whittle start and exact maximum
    likelihood on the first 2/3 of each record, evidence (2 ln B, BIC scale) against white
    noise, the held-out gap on the last third, and the localisation of the white-noise
    residual in frequency, lag and time. The effects real sensors show beyond those three
    noises (output grid, lines, low-pass, flicker, start-up transient) come from the forward
    selection of `noise_sensor.py`, which alone diagnoses records longer than `EXACT_LIMIT`
    samples; every result carries the Allan deviation with ±1σ intervals
    (`where["allan"]`).

    **Arguments:**

    - `datasets`: validated `NoiseData` records (e.g. from `read_csv`).
    - `nominal`: ignored (the servo device has no parameter in this kind's nominal model);
        accepted for the common `diagnose` interface.

    **Returns:** one `DiagnosisResult` per record, in order. Float64 (needs x64 enabled;
    a `ValueError` otherwise).
    """
    require_float64("log-likelihoods of thousands of samples are compared to within a unit")
    del nominal
    effects = _effects()
    exact = [i for i, d in enumerate(datasets) if np.asarray(d.a_out).size <= EXACT_LIMIT]
    hosts = {i: _context(datasets[i], effects) for i in exact}
    results: list[DiagnosisResult | None] = [None] * len(datasets)
    groups: dict[tuple[int, int], list[int]] = {}
    for i, host in hosts.items():
        groups.setdefault((host["normalised"].size, host["split"]), []).append(i)
    candidates = jnp.arange(1 + len(effects))
    for (n, split), indices in groups.items():
        records = jnp.asarray(np.stack([hosts[i]["normalised"] for i in indices]))
        guesses = jnp.asarray(np.stack([hosts[i]["guesses"] for i in indices]))
        mask = jnp.asarray((np.arange(n) < split).astype(np.float64))
        band, n_bands = _bands((n - 1) // 2)
        outputs = sweep(
            _fit_record,
            records,
            mask,
            guesses,
            candidates,
            jnp.asarray(band.astype(np.int32)),
            jnp.zeros(n_bands),
            in_axes=(0, None, 0, None, None, None),
            chunk_size=even_chunk_size(len(indices), BATCH_CHUNK),
            desc="diagnose noise",
        )
        outputs = [np.asarray(o) for o in outputs]
        for j, i in enumerate(indices):
            results[i] = _postprocess(datasets[i], hosts[i], effects, [o[j] for o in outputs])
    # Beyond the three noises: the forward selection where the exact verdict leaves it open,
    # on a coarse output grid, and alone on long records (noise_sensor.py).
    done: list[DiagnosisResult] = []
    for data, result in zip(datasets, results, strict=True):
        x = np.asarray(data.a_out, dtype=np.float64)
        dt = float(data.sample_period)
        if result is None:
            try:
                selection = noise_sensor.run_selection(x, dt)
            except ValueError as error:
                raise DataError(f"noise record: {error}") from None
            result = noise_sensor.from_selection(x, np.asarray(data.t), dt, selection, _welch)
            result.notes = [*result.notes, *getattr(data, "notes", ())]
        elif noise_sensor.needs_selection(x, result.verdict):
            result = noise_sensor.combine(result, noise_sensor.run_selection(x, dt))
        result.where["allan"] = noise_sensor.allan_summary(x, dt)
        done.append(result)
    return done
