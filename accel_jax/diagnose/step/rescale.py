"""A nested fit whose reported ln L ended below its nominal's, fitted again where the two
likelihoods agree (`retry_at_residual_scale`).

The solver maximises a penalised likelihood with the noise fixed at σ_ref (`StepFit.objective`);
the evidence compares the profiled one, the noise variance estimated (`StepFit.log_likelihood`).
From the nominal optimum a nested fit cannot end below the nominal's objective, but where the
nominal fit's residual RMS σ̂ lies far from σ_ref the two weigh the residual against the
priors differently, and the nested fit can end below the nominal's reported ln L: at a fixed
σ_ref far below σ̂ a unit of residual is worth more than a unit of prior, and a fit that
trades a measured input's levels or the device's prior for a little residual gains in the
objective and loses in ln L. With σ_ref = σ̂ the two agree to first order: for a fit whose
objective (residual sum RSS over 2σ̂², plus penalty P) ends at or below the nominal's,
ΔlnL ≥ n/2 (r − 1 − ln r) ≥ 0, r the ratio of the two RSS, when σ̂² = RSS_nominal / n (the
reported ln L also leaves out the change times' and the effect's own priors, so not exactly).

Seen in the measured-input harness's 100-per-class draw at 01ff127: 305 fits flagged on
2,200 rankings (`fit_failed`), none below the nominal's objective. On a lag record with a
measured input (record 122) the nominal, 219 × the floor off, bent the input's levels by
thousands of their σ and the drift fit, from there, ended 26,626 below its ln L; on a
band-pass record (710, 4,400 × the floor off) the stop fits at the floor ended 7,005 and
7,070 below the nominal's fit there.
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .assess import log_likelihood_shortfall, nested_failed, reported_below
from .batch import fit_grouped
from .model import REFIT_BOUND
from .starts import nominal_start
from .state import Baseline, StepFit, StepRecord

RESCALED_NOTE = "refitted at σ̂, the residual RMS of the nominal fit that each is judged against"
"""Part of a record's note where a candidate was refitted by `retry_at_residual_scale`."""


def _losers(fits: list[StepFit]) -> list[int]:
    """The candidates (indices into `fits`, the nominal first) whose reported ln L ended
    below the nominal's (`assess.reported_below`) though their objective did not: the two
    likelihoods' disagreement, not the solver's failure (`assess.nested_failed`). None
    where the nominal's refit rests past `model.REFIT_BOUND`: there the bound's penalty,
    in the objective and not in the reported ln L at any scale, is what a nested fit
    trades (`verdict._at_bound_note`), and counting that trade as evidence would credit
    an effect for easing a device far outside its prior."""
    if any(abs(z) > REFIT_BOUND for _, z in fits[0].device_shifts()):
        return []
    return [
        k for k, f in enumerate(fits) if k > 0
        and reported_below(f, fits[0]) and not nested_failed(f, fits[0])
    ]


def retry_at_residual_scale(
    fits: list[list[StepFit]],
    records: list[StepRecord],
    effects,
    stages: list[tuple[object, list[int]]],
    nominal,
    floor: dict,
) -> None:
    """Fit each candidate of `_losers` again with σ_ref the residual RMS σ̂ of the nominal
    fit it is judged against (`assess.baseline`: the record's nominal fit, or on a record
    of `floor` — `entry._reweight_far_records` — the nominal's fit at the floor for the later
    fits), from its own optimum and from the optimum of the nominal's refit at that scale,
    which becomes its baseline (`StepFit.baseline`). The refit replaces the old one where
    it ends less far below that baseline's reported ln L (and not below its objective); the
    record's note says so. `stages`: (compiled fit, its candidates — 1-based indices into
    `effects`, 0 the nominal) in the order of a record's fits, the linear stage first.
    `fits` and `records` updated in place."""
    index = {e.name: j for j, e in enumerate(effects, start=1)}
    index["nominal"] = 0
    linear_fn, linear = stages[0]
    # Two rounds: the candidates judged against the record's nominal fit, then those judged
    # against the nominal's fit at the floor (one record's fits are one batch row). The
    # losers are those of the fits as they came (a refit of the first round is not fitted
    # again in the second).
    losers = {
        i: [(k, fits[i][k].baseline is not None) for k in _losers(fits[i])]
        for i, rec in enumerate(records) if not rec.domain_problems
    }
    for at_floor in (False, True):
        wanted: dict[int, tuple[StepFit, list[int]]] = {}
        for i, found in losers.items():
            mine = [k for k, judged_at_floor in found if judged_at_floor == at_floor]
            if mine:
                wanted[i] = (floor[i][1] if at_floor else fits[i][0], mine)
        if not wanted:
            continue
        scaled = list(records)
        for i, (base, _) in wanted.items():
            sigma_hat = math.sqrt(max(float(base.innovation_variance), 0.0))
            ctx = eqx.tree_at(lambda c: c.sigma_ref, records[i].ctx, jnp.asarray(sigma_hat))
            scaled[i] = dataclasses.replace(records[i], ctx=ctx)
        # The nominal and the linear candidates at σ̂: each from its own optimum and from
        # the baseline's optimum with the effect off (the same compiled program as the first
        # fits: σ_ref and the starts are data).
        starts = {}
        for i, (base, _) in wanted.items():
            guesses = np.array(records[i].guesses_linear)
            for row, candidate in enumerate(linear):
                own = [f for f in fits[i] if index[f.effect] == candidate]
                guesses[row, 0, :] = own[0].w_trained if own else nominal_start(base.w_trained)
                guesses[row, 1, :] = nominal_start(base.w_trained)
            starts[i] = guesses
        refits = fit_grouped(
            linear_fn, nominal, scaled, starts, linear, effects, "diagnose step (at σ̂)"
        )
        new = {i: {f.effect: f for f in again} for i, again in refits.items()}
        # The later stages' losers, from their own optimum and the nominal refit's.
        for fn, members in stages[1:]:
            names = {effects[c - 1].name for c in members}
            stage_starts = {}
            for i, (_, mine) in wanted.items():
                if not any(fits[i][k].effect in names for k in mine):
                    continue
                at_nominal = nominal_start(new[i]["nominal"].w_trained)
                rows = []
                for candidate in members:
                    own = [f for f in fits[i] if index[f.effect] == candidate]
                    rows.append([own[0].w_trained if own else at_nominal, at_nominal])
                stage_starts[i] = np.asarray(rows, dtype=np.float64)
            if not stage_starts:
                continue
            for i, again in fit_grouped(
                fn, nominal, scaled, stage_starts, members, effects, "diagnose step (at σ̂)"
            ).items():
                new[i].update({f.effect: f for f in again})
        for i, (base, mine) in wanted.items():
            nominal_at = new[i]["nominal"]
            kept, before = [], []
            for k in mine:
                old = fits[i][k]
                shortfall = log_likelihood_shortfall(old, fits[i][0])
                candidate = dataclasses.replace(
                    new[i][old.effect], baseline=Baseline.of(nominal_at)
                )
                if nested_failed(candidate, nominal_at):
                    continue
                if log_likelihood_shortfall(candidate, nominal_at) < shortfall:
                    fits[i][k] = candidate
                    kept.append(old.effect)
                    before.append(shortfall)
            if kept:
                sigma_ref = float(np.asarray(records[i].ctx.sigma_ref))
                sigma_hat = float(np.asarray(scaled[i].ctx.sigma_ref))
                records[i] = records[i].with_note(
                    f"{', '.join(kept)} {RESCALED_NOTE} (σ̂ = {sigma_hat / sigma_ref:.3g} × "
                    f"this record's σ_ref): at σ_ref the reported ln L of each had ended up to "
                    f"{max(before):.4g} below that nominal's, the solver weighing the residual "
                    "against the priors otherwise than the likelihood the evidence compares"
                )
