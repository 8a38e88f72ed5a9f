"""Each candidate of the step diagnosis judged on its own (host side): its entry in the
ranking (held-out gap, credibility, evidence and the slack of that evidence), whether its
noise model explains the free-run errors (`NOISE_VARIANCE_FACTOR`), whether it explains
the record deterministically, and whether a nested effect's fit ended below the nominal
model's maximised likelihood (`nested_failed`: a solver failure, never an effect with a
large negative evidence).
"""

from __future__ import annotations

import math

import numpy as np

from .. import openworld
from .fit import GAIN_SIGMA, REFIT_FIELDS
from .layout import W
from .state import StepRecord


NOISE_VARIANCE_FACTOR = 4.0
"""A noise model explains the free-run errors when their mean square is within this factor
of the variance it predicts (RMS within 2×)."""


def _fit_entry(
    rec: StepRecord,
    effects_all,
    candidate,
    w,
    prediction,
    innovations,
    log_v,
    converged,
    prior_prediction,
    u_out,
):
    train = ~rec.held
    n_train = int(np.sum(train))
    z = np.asarray(w[W.REFIT])
    z_gain = float(w[W.GAIN])
    rss = float(np.sum(innovations[train] ** 2))
    rss = max(rss, 1e-300)
    log_like = (
        -0.5 * n_train * math.log(rss / n_train)
        - 0.5 * float(log_v)
        - 0.5 * float(np.sum(z**2))
        - 0.5 * z_gain**2
    )
    effect = effects_all[candidate - 1] if candidate else None
    gain = rec.polarity * math.exp(GAIN_SIGMA * z_gain)
    context = rec.host.candidate(innovation_variance=rss / n_train, test_gain=gain * rec.k_test)
    params = {}
    if effect is not None:
        params = effect.physical(w[W.effect(effect.n_params)], context)
    error = u_out - prediction
    return {
        "effect": "nominal" if effect is None else effect.name,
        "object": effect,
        "stochastic": bool(effect is not None and effect.stochastic),
        "k": 0 if effect is None else effect.n_params,
        "w": w,
        "z": z,
        "z_gain": z_gain,
        "gain": gain,
        "log_likelihood": log_like,
        "innovation_variance": rss / n_train,
        "prediction": prediction,
        "prior_prediction": prior_prediction,
        "error": error,
        "innovations": innovations,
        "converged": bool(converged),
        "params": params,
    }


def fit_entries(rec: StepRecord, effects_all, candidates, outputs, u_out):
    w, prediction, innovations, log_v, converged, steps, prior, decrement, objective, trained = (
        np.asarray(o) for o in outputs
    )
    n = rec.n  # the record's blocks, without the padding
    prediction, innovations, prior, u_out = (
        prediction[:, :n],
        innovations[:, :n],
        prior[:, :n],
        u_out[:n],
    )
    entries = []
    for c, candidate in enumerate(candidates):
        entry = _fit_entry(
            rec,
            effects_all,
            int(candidate),
            w[c],
            prediction[c],
            innovations[c],
            log_v[c],
            converged[c],
            prior[c],
            u_out,
        )
        entry["steps"] = int(steps[c])
        entry["decrement"] = float(decrement[c])
        entry["objective"] = float(objective[c])
        entry["w_trained"] = trained[c]
        entries.append(entry)
    return entries


NESTED_TOLERANCE = 1e-6
"""An effect's maximised penalised log-likelihood may fall below the nominal's by this share
of the nominal's objective (and at least `NESTED_ABSOLUTE`) before its fit counts as failed:
the nominal model is the effect at z = 0, so a fit that ends lower stopped in the wrong
basin (round-off and the solver's tolerance aside)."""


NESTED_ABSOLUTE = 1e-3
"""The least shortfall [in ln L units] that counts as a failed nested fit."""


def nested_shortfall(fit, nominal_fit) -> float:
    """How far `fit`'s maximised penalised log-likelihood (−½ the solver's objective: the
    training residuals, the priors of the refit, the nuisances and the effect) ends below
    the nominal fit's (≤ 0: not below). The reported ln L, which leaves out the change
    times' and the effect's own priors, may differ from it by those terms."""
    return 0.5 * (float(fit["objective"]) - float(nominal_fit["objective"]))


def nested_failed(fit, nominal_fit) -> bool:
    """Whether a nested fit ended below the nominal's penalised likelihood beyond
    round-off (`NESTED_TOLERANCE`)."""
    scale = 0.5 * abs(float(nominal_fit["objective"]))
    return nested_shortfall(fit, nominal_fit) > max(NESTED_TOLERANCE * scale, NESTED_ABSOLUTE)


def nested_losers(fits) -> list[str]:
    """The candidates of one record (`fits[0]` the nominal) whose fit lost to the nominal."""
    return [f["effect"] for f in fits[1:] if nested_failed(f, fits[0])]


def _assess(fit, rec: StepRecord, nominal_fit=None):
    """Held-out and training gaps of one fit against the noise floor (its own noise model
    for a stochastic effect), credibility, and whether it explains the record."""
    held, sigma = rec.held, rec.sigma
    e = fit["error"]
    floor_var = sigma**2
    if fit["stochastic"]:
        white, correlated = (
            fit["params"]["sigma_white_V"] ** 2,
            fit["params"]["sigma_correlated_V"] ** 2,
        )
        floor_var = white + correlated
    ms_train = float(np.mean(e[~held] ** 2))
    ms_held = float(np.mean(e[held] ** 2)) if np.any(held) else 0.0
    fit["ms_train"], fit["ms_held"] = ms_train, ms_held
    fit["ms_held_one_step"] = float(np.mean(fit["innovations"][held] ** 2))
    fit["model_noise_variance"] = floor_var
    fit["gap_train"] = openworld.excess(ms_train, floor_var)
    fit["gap_held"] = openworld.excess(ms_held, floor_var)
    limit = openworld.FLOOR_FACTOR * sigma
    explains = fit["gap_train"] <= limit and fit["gap_held"] <= limit
    if fit["stochastic"]:
        # A noise explains the record when its one-step errors are white and the free-run
        # errors are of the size it predicts: their mean square within a factor
        # `NOISE_VARIANCE_FACTOR` of σ_w² + σ_s² on both parts (a loose check — a fit of
        # the deterministic part takes some low-frequency noise with it on the training
        # part; the predictability test is what refuses deterministic misfits).
        fit["one_step_whiteness"] = openworld.whiteness(fit["innovations"][held])
        ratios = [float(np.mean(part**2)) / max(floor_var, 1e-300) for part in (e[~held], e[held])]
        fit["free_run_over_noise_variance"] = ratios
        consistent = all(1 / NOISE_VARIANCE_FACTOR <= r <= NOISE_VARIANCE_FACTOR for r in ratios)
        fit["variance_consistent"] = bool(consistent)
        explains = fit["one_step_whiteness"]["white"] and consistent
    fit["explains"] = bool(explains)
    out = [
        REFIT_FIELDS[i]
        for i in range(4)
        if rec.prior_sigma[i] > 0 and abs(fit["z"][i]) > openworld.PRIOR_LIMIT
    ]
    if abs(fit["z_gain"]) > openworld.PRIOR_LIMIT:
        out.append("test_winding_gain")
    fit["out_of_prior"] = out
    # A candidate fit that stopped short of its minimum only understates its likelihood (its
    # evidence is a lower bound): it stays credible. The nominal refit must converge for
    # `none` (evaluate), and its shortfall is taken off every effect's evidence.
    fit["plausible"] = bool(not out)
    return fit


def evidence_slack(fit, rec: StepRecord, n_train: int) -> float:
    """How much 2 ln L a fit that stopped short of its minimum could still gain.

    The Newton decrement D is the decrease of the cost ½Σ(a/σ)² (σ the noise floor the fit
    scales by) that a full Gauss–Newton step predicts. The log-likelihood profiles the
    noise variance, ln L = −(n/2) ln(RSS/n), so the same decrease is worth
    2Δln L = −n ln(1 − 2Dσ²/RSS): about 2D when the fit is at the floor (RSS ≈ nσ²), and
    2D·σ²/(RSS/n) — far less — when it misses by a wide margin (a linear loop refitted to a
    record that hits its stops predicted D ≈ 5e3, worth 2Δln L ≈ 0.03). Infinite when the
    step would remove the whole residual: then nothing can be significant against it."""
    sigma = float(rec.sigma)
    rss = max(float(fit["innovation_variance"]) * n_train, 1e-300)
    share = 2 * float(fit["decrement"]) * sigma**2 / rss
    if share >= 1:
        return math.inf
    return -n_train * math.log1p(-share)


def explains_deterministically(fit, rec: StepRecord) -> bool:
    if fit["stochastic"]:
        return False
    e, held, sigma = fit["error"], rec.held, rec.sigma
    limit = openworld.FLOOR_FACTOR * sigma
    return (
        openworld.excess(float(np.mean(e[~held] ** 2)), sigma**2) <= limit
        and openworld.excess(float(np.mean(e[held] ** 2)), sigma**2) <= limit
    )
