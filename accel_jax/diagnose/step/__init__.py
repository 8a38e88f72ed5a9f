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
at z = 0): `torquer_lag`, `output_filter`, `stop_saturation`, `disturbance_drift`,
`colored_noise`, `stop_contact` (compliant stops, fitted where the inelastic clamp of
`stop_saturation` does not explain the record) and `moment_noise` (a Gauss–Markov moment
inside the loop, fitted where no deterministic linear effect explains the record), each
described where it is defined (`effects`).

**Held out**: every third segment of constant test voltage, from the third on (the last
third of the record when it has fewer than four segments; `record.held_out_samples`).
Interleaving keeps both polarities and every level in training and in the test, so an
effect seen only at one end of the sequence (a one-sided stop contact) cannot hide in the
training part. The models are fitted on the training samples; then only the times of the
held-out changes and the effects' nuisances are fitted on the held-out samples (what no
training data can fix), and the held-out *free-run* simulation error is the gap (one-step
prediction errors are reported beside it).

**Verdict**: `openworld.decide` — `none`, an effect, `cannot_tell` or `unexplained`, after
a domain check (`domain`) that refuses records the model family cannot describe (such a
record is `unexplained`; its effects are not fitted, `entry.DOMAIN_NOTE`).

**Discovery** (`diagnose_step(..., discover=True)`): where no library effect explains a
record, the missing term is looked for in a library of terms at named places in the loop
(`terms`, `discover`) and reported as a hypothesis (`DiagnosisResult.discovery`); the
verdict stays `unexplained`.

**Modules.** `entry` (`diagnose_step`; `starts`, where its later fits start), `record` (a
record read into a `StepRecord`, the typed state of `state`; `segments`, `domain`),
`inputs` (a measured input read as plateaus), `effects`, `fit` (the JAX fit of every
candidate, each model a `CandidateModel`;
`layout` names each parameter of its vector and of the joint fit's), `assess` (each
candidate's fit, a `state.StepFit`, and its assessment), `verdict` (the open-world
decision; the ranking's entries, as reported, from `ranking_entry`), `refit` and `nuisance`
(what the refit says); several records of one device: `joint` (the joint fit, each
candidate's a `state.JointFit`), `joint_verdict` (its ranking and verdict,
`diagnose_step_set`), `design` (the next experiment for a lag tie); `terms` and `discover`
(the discovery of a missing term).

Everything is float64 (enable x64: the fitted change times are ~1e-7 s, and the evidence
compares log-likelihoods of ~1e4 to within ~1).
"""

from __future__ import annotations

from .effects import AbstractStepEffect as AbstractStepEffect
from .effects import ColoredNoise as ColoredNoise
from .effects import DisturbanceDrift as DisturbanceDrift
from .effects import OutputFilter as OutputFilter
from .effects import StopContact as StopContact
from .effects import StopSaturation as StopSaturation
from .effects import TorquerLag as TorquerLag
from .effects import step_effects as step_effects
from .entry import LAG_PAIR as LAG_PAIR
from .entry import NESTED_RESTARTS as NESTED_RESTARTS
from .entry import diagnose_step as diagnose_step
from .joint_verdict import SetDiagnosis as SetDiagnosis
from .joint_verdict import diagnose_step_set as diagnose_step_set
