"""The `step` kind: a closed-loop test-signal record, its nominal model and its effects.

**Nominal model**: the user's device as given (`NominalDevice`: its torquer lag T_dm and
output filter T_f taken as known, 0 for the idealised loop the identification methods
assume) in the linear closed loop with no stop contact, a constant external moment and
white output noise, simulated exactly by `_simulate.sequence.linear_record`. Refitted: J,
μ, c, k_dm as log-normal deviations from the nominal values, z_i = ln(x_i/x_i⁰)/σ_i,
bounded to |z_i| < `REFIT_BOUND` (so a refit stays inside its prior by construction) with a
standard normal prior on z_i.

**Nuisances** (fitted in every model, never reported as physics): the test winding's
polarity (from the settled levels) and gain (log-normal, 10 %); the output offset (the
constant external moment, which in a linear loop is an output offset); the initial state (a
record may start in a transient); and the time of every test-voltage change to a fraction of
a sample (within ±1 sample of the sample where `u_test` shows it). The noise floor, with the
record's ADC quantisation, is measured without the model (`openworld.noise_floor`).

**Effects** (each `AbstractStepEffect` changes the model through one hook and is the nominal model
at z = 0):

- `torquer_lag`: T_dm other than the nominal device's (inside the loop: changes the
  overshoot as well as the delay);
- `output_filter`: T_f other than the nominal device's (outside the loop: delays the output
  only);
- `stop_saturation`: mechanical stops, upper and lower (`_simulate.sequence.stop_record`);
- `disturbance_drift`: a drifting external moment, M(t) = M + Ṁ t;
- `colored_noise`: correlated output noise, white + first-order Gauss–Markov (AR(1)),
  fitted through its one-step prediction errors (an ARMA(1,1) recursion).

**Held out**: every third segment of constant test voltage, from the third on (the last
third of the record when it has fewer than four segments; `step_record.held_out_samples`).
Interleaving keeps both polarities and every level in training and in the test, so an
effect seen only at one end of the sequence (a one-sided stop contact) cannot hide in the
training part. The models are fitted on the training samples; then only the times of the
held-out changes and the effects' nuisances are fitted on the held-out samples (what no
training data can fix), and the held-out *free-run* simulation error is the gap (one-step
prediction errors are reported beside it).

**Verdict**: `openworld.decide` — `none`, an effect, `cannot_tell` or `unexplained`, after
a domain check (`_domain`) that refuses records the model family cannot describe.

Everything is float64 (enable x64: the fitted change times are ~1e-7 s, and the evidence
compares log-likelihoods of ~1e4 to within ~1).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from .._data import NominalDevice, StepData
from .._sweep import even_chunk_size, sweep
from .base import DiagnosisResult, require_float64
from .step_effects import (
    AbstractStepEffect as AbstractStepEffect,
)
from .step_effects import (
    ColoredNoise as ColoredNoise,
)
from .step_effects import (
    DisturbanceDrift as DisturbanceDrift,
)
from .step_effects import (
    OutputFilter as OutputFilter,
)
from .step_effects import (
    StopSaturation as StopSaturation,
)
from .step_effects import (
    TorquerLag as TorquerLag,
)
from .step_effects import step_effects
from .step_fit import _I_SLOT, _I_TIMING, BATCH_CHUNK, fit_linear, fit_nonlinear
from .step_record import prepare, prior_sigma_of, stack_on_host
from .step_assess import explains_deterministically, fit_entries, nested_losers
from .step_verdict import evaluate


def _run(fn, nominal, preps, indices, guesses_key, candidates, desc):
    """Fit `candidates` of the records `indices` (one length and change count), batched."""
    ctx = stack_on_host([preps[i]["ctx"] for i in indices])
    u_out = stack_on_host([preps[i]["u_out"] for i in indices])
    guesses = jnp.asarray(np.stack([preps[i][guesses_key] for i in indices]))
    outputs = sweep(
        fn,
        nominal.params,
        jnp.asarray(prior_sigma_of(nominal)),
        ctx,
        u_out,
        guesses,
        jnp.asarray(candidates),
        in_axes=(None, None, 0, 0, 0, None),
        chunk_size=even_chunk_size(len(indices), BATCH_CHUNK),
        desc=desc,
    )
    return [np.asarray(o) for o in outputs]


def _fit_grouped(fn, nominal, preps, indices, key, candidates, effects, desc) -> dict:
    """Fit `candidates` of the records `indices` from their starts `preps[i][key]`, one
    batch per record shape (one compiled program each); returns {i: fit entries}."""
    groups: dict[tuple, list[int]] = {}
    for i in indices:
        groups.setdefault(preps[i]["group"], []).append(i)
    entries = {}
    for members in groups.values():
        outputs = _run(fn, nominal, preps, members, key, candidates, desc)
        for j, i in enumerate(members):
            entries[i] = fit_entries(
                preps[i], effects, candidates, [o[j] for o in outputs], preps[i]["u_out"]
            )
    return entries


LAG_PAIR = frozenset({"torquer_lag", "output_filter"})
"""The tie that another experiment can break (`step_design.next_experiments`)."""


def diagnose_step(
    datasets: list[StepData], nominal: NominalDevice, *, recommend: bool = True
) -> list[DiagnosisResult]:
    """Diagnose step records against a nominal device (docs/models.md §5, `step` kind).

    Records of one length and test sequence size are fitted together: one compilation, the
    batch vmapped and sharded across devices (`accel_jax.sweep`), every candidate model and
    start of a record vmapped. The stop candidate (simulated sample by sample) is fitted
    only for records that no linear model explains.

    **Arguments:**

    - `datasets`: validated `StepData` records (e.g. from `read_csv`).
    - `nominal`: the nominal device and its prior (`NominalDevice`).
    - `recommend`: with a `cannot_tell` between `torquer_lag` and `output_filter`, compute
        the experiment that would separate them (`result.next_experiment`, from the joint
        fit of `step_joint`: ~10–60 s per such record on a CPU).

    **Returns:** one `DiagnosisResult` per record, in order. Float64 (needs x64 enabled;
    a `ValueError` otherwise).
    """
    require_float64("the evidence compares log-likelihoods of ~1e4 to within ~1")
    effects = step_effects()
    linear = [0] + [i for i, e in enumerate(effects, start=1) if not e.nonlinear]
    nonlinear = [i for i, e in enumerate(effects, start=1) if e.nonlinear]
    prior_sigma = prior_sigma_of(nominal)
    preps = []
    for data in datasets:
        prep = prepare(data, nominal, effects)
        prep["prior_sigma"] = prior_sigma
        preps.append(prep)
    entries = _fit_grouped(
        fit_linear, nominal, preps, range(len(preps)), "guesses_linear", linear, effects,
        "diagnose step",
    )
    fits: list[list] = [entries[i] for i in range(len(preps))]  # every record's linear fits
    # Nested fits never lose: an effect at z = 0 is the nominal model, so a linear
    # candidate whose best fit ends below the nominal's log-likelihood started in the wrong
    # basin. Its record is fitted again with every candidate's second start at the nominal
    # optimum (same program; only where a candidate lost).
    for _ in range(NESTED_RESTARTS):
        losing = [i for i in range(len(preps)) if nested_losers(fits[i])]
        if not losing:
            break
        _restart_from_nominal(fits, preps, losing, effects, linear, nominal)
    # The stop candidate, for the records that no linear model explains.
    need = []
    for i, prep in enumerate(preps):
        if prep["domain_problems"] or not nonlinear:
            continue
        if not any(explains_deterministically(f, prep) for f in fits[i]):
            need.append(i)
            # One start from the nominal fit (a stop model with its stops out of reach is
            # the nominal model), one from the record's own starting point: the nominal fit
            # may have bent its nuisances (change times, offset) to absorb the clipping.
            guesses = np.array(prep["guesses_nonlinear"])
            guesses[:, 0, :_I_SLOT] = fits[i][0]["w"][:_I_SLOT]
            guesses[:, 0, _I_TIMING:] = fits[i][0]["w"][_I_TIMING:]
            # And a third: the nominal optimum itself, the effect at its no-effect value
            # (z = 0 is the nominal model), so that a nested fit never ends below the
            # nominal's likelihood (from the peak starts alone, a stop fit lost by
            # thousands on records that a compliant contact clipped).
            at_nominal = np.broadcast_to(
                _at_nominal(fits[i][0]["w_trained"]), guesses[:, :1].shape
            )
            prep["guesses_nonlinear"] = np.concatenate([guesses, at_nominal], axis=1)
    entries = _fit_grouped(
        fit_nonlinear, nominal, preps, need, "guesses_nonlinear", nonlinear, effects,
        "diagnose step (stops)",
    )
    for i, record_fits in entries.items():
        fits[i] = fits[i] + record_fits
    results = []
    for data, prep, record_fits in zip(datasets, preps, fits, strict=True):
        if len(record_fits) < 1 + len(effects):
            skipped = [e.name for e in effects if e.nonlinear]
            prep.setdefault("notes", []).append(
                f"{', '.join(skipped)} not fitted: a linear model already explains the record"
                if not prep["domain_problems"]
                else f"{', '.join(skipped)} not fitted: the record failed the domain check"
            )
        results.append(evaluate(prep["data"], nominal, prep, record_fits))
    if recommend:
        for data, prep, result in zip(datasets, preps, results, strict=True):
            if result.verdict == "cannot_tell" and set(result.tied) == LAG_PAIR:
                if prep.get("clock") is not None:  # the joint fit takes ≤ MAX_CHANGES
                    result.notes.append(
                        "no next experiment designed: the joint fit that designs it takes "
                        "step sequences, not a clocked sequence of hundreds of changes"
                    )
                    continue
                _recommend(result, data, nominal)
    return results


NESTED_RESTARTS = 2
"""Rounds of restarts from the nominal optimum for candidates that lost to it (a second
round when the restart also moved the nominal fit on, e.g. one that had stopped at its
step limit)."""


def _restart_from_nominal(fits, preps, losing, effects, linear, nominal) -> None:
    """Fit the records `losing` again, every candidate's second start at the nominal
    optimum with the effect at 0 (the same compiled program); keep each candidate's better
    fit (lower objective)."""
    for i in losing:
        guesses = np.array(preps[i]["guesses_linear"])
        guesses[:, 1, :] = _at_nominal(fits[i][0]["w_trained"])
        preps[i]["guesses_linear_again"] = guesses
    entries = _fit_grouped(
        fit_linear, nominal, preps, losing, "guesses_linear_again", linear, effects,
        "diagnose step (nested restarts)",
    )
    for i, again in entries.items():
        fits[i] = [
            new if new["objective"] < old["objective"] else old
            for old, new in zip(fits[i], again, strict=True)
        ]
        note = (
            "a candidate's fit ended below the nominal model's likelihood; refitted from "
            "the nominal optimum"
        )
        if note not in preps[i].setdefault("notes", []):
            preps[i]["notes"].append(note)


def _at_nominal(w_nominal) -> np.ndarray:
    """A start at the nominal fit's optimum with the effect's slot at 0: the nominal model
    exactly, for every effect (each is the identity at z = 0)."""
    w = np.array(w_nominal, dtype=np.float64)
    w[_I_SLOT:_I_TIMING] = 0.0
    return w


def _recommend(result: DiagnosisResult, data: StepData, nominal: NominalDevice) -> None:
    """Attach the next experiment to a lag tie (the record alone, fitted as a set of one)."""
    from .step_design import next_experiments
    from .step_joint import fit_set, prepare_set

    prepared = prepare_set([data], nominal)
    fits = fit_set(prepared, nominal)
    result.next_experiment = next_experiments(prepared, nominal, fits, list(result.tied))
    if result.next_experiment:
        best = result.next_experiment[0]
        result.reason += (
            f" To separate {result.tied[0]} from {result.tied[1]}: {best['description']} "
            f"(expected 2 ln B ≈ {best['expected_2lnB']:.3g})."
        )
