"""The step diagnosis's typed state of one record (host side, NumPy): what `record.prepare`
reads from a record (`StepRecord`), the scales its effects start from and report in
(`RecordHost`; with a candidate's fit, `CandidateHost`), the noise floor measured without a
model (`NoiseFloor`), a measured clocked sequence's distinct levels (`LevelGroups`), the
shape that batches records into one compiled program (`RecordShape`), each candidate's
fit and its assessment (`StepFit`), its entry in the ranking (`RankingEntry`: what the
verdict decides on), and a candidate's joint fit to a set of records (`JointFit`), its
score (`JointScore`, each record's `RecordScore`) and its entry in the set's ranking
(`SetRankingEntry`).

Each is a frozen dataclass: a later stage that changes a record (a note added, the joint
fit's `on_stops`, a design's floor) or a fit (its assessment) makes a new one with
`dataclasses.replace`. What the diagnosis reports is made dicts where it is reported
(`RankingEntry.to_dict`, `refit`; a set's ranking and records by `to_dict` where
`joint_verdict` puts them into its `SetDiagnosis`).
"""

from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING, Any, NamedTuple

import equinox as eqx
import numpy as np

from ..._data import StepData
from ..._io import field_dict
from ..openworld import Candidate, Whiteness
from .model import REFIT_FIELDS

if TYPE_CHECKING:
    from .effects import AbstractStepEffect
    from .model import StepContext
    from .inputs import Clock


class RecordView(eqx.Module):
    """The record as the fit sees it: block start times, U_test at each block's first
    sample, block means of U_out (`StepData`'s field names)."""

    t: np.ndarray
    u_test: np.ndarray
    u_out: np.ndarray


@dataclasses.dataclass(frozen=True)
class RecordHost:
    """The scales of one record that its effects' starts and physical values use (host
    side, floats).

    **Fields:** `lag_unit` [s] a lag's departure per unit z (3 % of the nominal loop's T);
    `gain` [V/m] the pick-off and amplifier gain k_dp k_y (deflection to output);
    `mid`, `half` [V] the middle and half range of the training output; `scale` [V] of the
    moment and initial-state parameters; `dt` [s] one block; `duration` [s] of the fitted
    record; `torquer_gain` [N·m/V] k_dm; `accel_per_g` [V/g] the moment of a 1 g input
    acceleration over k_dm; `timing_late` each timing parameter's value at the nominal's
    second start (changes half a sample earlier: `TIMING_PRIOR`'s mean);
    `nominal_torquer_time_constant`, `nominal_filter_time_constant` [s] the nominal
    device's lags T_dm, T_f (a lag effect departs from these); `top`, `bottom` [V] the
    whole record's largest and smallest output (block means, held-out part included);
    `block_samples` m, the samples in one block; `k_test` [V/V] the nominal device's
    closed-loop test gain, the settled output per volt of M/k_dm (an external moment's
    output, which passes through no test winding).
    """

    lag_unit: float
    gain: float
    mid: float
    half: float
    scale: float
    dt: float
    duration: float
    torquer_gain: float
    accel_per_g: float
    timing_late: np.ndarray
    nominal_torquer_time_constant: float
    nominal_filter_time_constant: float
    top: float
    bottom: float
    block_samples: int
    k_test: float

    def nominal_lag(self, field: str) -> float:
        """The nominal device's value [s] of the lag `ServoParams` field `field`
        (`torquer_time_constant` or `filter_time_constant`)."""
        return getattr(self, "nominal_" + field)

    def candidate(
        self, *, innovation_variance: float, test_gain: float, device: Any = None
    ) -> CandidateHost:
        """These scales with one candidate's fit (`CandidateHost`)."""
        own = {f.name: getattr(self, f.name) for f in dataclasses.fields(RecordHost)}
        return CandidateHost(
            **own, innovation_variance=innovation_variance, test_gain=test_gain, device=device
        )


@dataclasses.dataclass(frozen=True)
class CandidateHost(RecordHost):
    """A record's scales (`RecordHost`) with what one candidate's fit adds, for its
    effect's physical values (`AbstractStepEffect.physical`).

    **Fields:** those of `RecordHost`; `innovation_variance` [V²] the fit's one-step
    prediction variance on the training part; `test_gain` [V/V] the fitted closed-loop
    test gain, polarity included; `device` the fitted device (`ServoParams`: the nominal's
    with J, μ, c, k_dm refitted; None where not given).
    """

    innovation_variance: float
    test_gain: float
    device: Any = None


@dataclasses.dataclass(frozen=True)
class NoiseFloor:
    """A record's noise floor, measured without any model (`openworld.noise_floor`).

    **Fields:** `sigma` [V] the floor of a block mean the fit scales by (the largest of the
    block means' 4th-difference floor with the input levels' part added in quadrature, the
    ADC step's q/√12 and a relative 1e-12); `sigma_per_sample` [V] one sample's;
    `sigma_block_means` [V] the block means' own; `adc_step` [V] the ADC step q (0: none
    found); `quantisation_floor_block` [V] q/√12 in a block mean; `block_samples` samples
    per block; `input_levels` [V] a measured input's level errors times the test gain.
    """

    sigma: float
    sigma_per_sample: float
    sigma_block_means: float
    adc_step: float
    quantisation_floor_block: float
    block_samples: int
    input_levels: float

    METHOD = (
        "median absolute 4th difference of the block means (and the ADC step's q/√12), "
        "without any model"
    )

    def to_dict(self) -> dict[str, Any]:
        """The floor as the diagnosis reports it (`where["noise_floor"]`)."""
        return {
            "sigma_V": self.sigma,
            "sigma_per_sample_V": self.sigma_per_sample,
            "sigma_block_means_V": self.sigma_block_means,
            "adc_step_V": self.adc_step,
            "quantisation_floor_block_V": self.quantisation_floor_block,
            "block_samples": self.block_samples,
            "method": self.METHOD,
            "input_levels_V": self.input_levels,
        }


@dataclasses.dataclass(frozen=True)
class LevelGroups:
    """The distinct levels of a measured clocked sequence (`inputs.level_groups`): `group`
    (J + 1,) each plateau's level group, `means` [V] each group's level, `sigmas` [V] each
    group's standard error."""

    group: np.ndarray
    means: np.ndarray
    sigmas: np.ndarray


@dataclasses.dataclass(frozen=True)
class RecordShape:
    """What decides a record's compiled program: records of one shape are fitted as one
    batch (`entry`), and a set is padded to its records' largest (`joint_set.stack`).

    **Fields:** `n_padded` blocks after padding (a multiple of `record.BLOCK_BUCKET`);
    `j_padded` change slots (a multiple of 4); `max_block` the largest block the program
    allows (a power of two, at least `record.MIN_MAX_BLOCK`); `measured` whether the test
    input's levels are fitted as errors in variables; `clocked` whether the changes run on
    one bit clock; `n_levels` the level parameters (0 for an exact input); `mapped_timing`
    whether the change times go through a timing map (a measured or clocked input, or a
    known input delay).
    """

    n_padded: int
    j_padded: int
    max_block: int
    measured: bool
    clocked: bool
    n_levels: int
    mapped_timing: bool = False


@dataclasses.dataclass(frozen=True, eq=False)
class StepRecord:
    """One step record as the step diagnosis sees it (`record.prepare`).

    **Fields:**

    - `data`: the record as fitted (a measured input read as its plateaus; a measured
        clocked sequence's plateaus at their level groups' means).
    - `notes`: what was read from the inputs and what the diagnosis did, in words.
    - `ctx`: the fit's per-record context (`fit.StepContext`, JAX arrays).
    - `view`: the record as the fit sees it, in blocks (`RecordView`).
    - `u_out`: (`shape.n_padded`,) [V] the block means of U_out, zero on the padding.
    - `n`, `block`: the blocks fitted and the samples in each; `dt` [s] a block's period,
        `dt_sample` [s] a sample's.
    - `held`: (n,) whether each block is held out; `held_rule` how they were chosen.
    - `floor`: the noise floor (`NoiseFloor`); `sigma` [V] its value, the fit's scale.
    - `domain_problems`: why the record lies outside the model family (empty: none);
        `domain`: what the domain check measured (reported as it is).
    - `polarity`: ±1, the test winding's sign from the settled levels; `k_test` [V/V]
        the nominal closed-loop test gain; `levels_slope` [V/V], `levels_intercept` [V]
        the settled levels' regression on the test voltage.
    - `change_index`, `change_block`: the sample and the block of each input change;
        `change_step` [V] ΔU_test and `change_accel` [g] Δa_in there.
    - `accel_sign`: ±1, the input axis's direction; `accel_slope` [V/g] the settled
        levels' slope in the acceleration; `has_accel` whether the record has `a_in`.
    - `period` [s]: the nominal loop's time constant T.
    - `shape`: its compiled program's shape (`RecordShape`).
    - `clock`: the bit clock of a many-change sequence (`inputs.Clock`), else None;
        `level_groups`: a measured clocked sequence's levels (`LevelGroups`), else None.
    - `guesses_linear`, `guesses_nonlinear`: (candidates, starts, parameters) the starts
        of the linear and of the stop candidates' fits.
    - `host`: the scales its effects use (`RecordHost`).
    - `prior_sigma`: (4,) the relative prior σ of J, μ, c, k_dm (`fit.REFIT_FIELDS`).
    - `input_delay_known`: the inputs' known delay behind the output [samples]
        (`StepData.input_delay`), which the change times' priors are centred on; None:
        unknown.
    - `input_measured`: whether `u_test` was read as a measurement (`inputs.read_input`;
        with an acceleration column too, where its levels carry no fitted errors).
    - `on_stops`: whether the joint fit simulates it with the stops (`joint_set.prepare_set`;
        False elsewhere).
    """

    data: StepData
    notes: tuple[str, ...]
    ctx: StepContext
    view: RecordView
    u_out: np.ndarray
    n: int
    block: int
    dt: float
    dt_sample: float
    held: np.ndarray
    held_rule: str
    floor: NoiseFloor
    sigma: float
    domain_problems: tuple[str, ...]
    domain: dict[str, Any]
    polarity: float
    k_test: float
    levels_slope: float
    levels_intercept: float
    change_index: np.ndarray
    change_block: np.ndarray
    change_step: np.ndarray
    change_accel: np.ndarray
    accel_sign: float
    accel_slope: float
    has_accel: bool
    period: float
    shape: RecordShape
    clock: Clock | None
    level_groups: LevelGroups | None
    guesses_linear: np.ndarray
    guesses_nonlinear: np.ndarray
    host: RecordHost
    prior_sigma: np.ndarray
    on_stops: bool = False
    input_delay_known: float | None = None
    input_measured: bool = False

    def with_note(self, note: str) -> StepRecord:
        """This record with `note` added to its notes."""
        return dataclasses.replace(self, notes=self.notes + (note,))


class Baseline(NamedTuple):
    """The nominal model's fit that a later fit is judged against where it is not the
    record's nominal fit (`StepFit.baseline`): its solver objective (`StepFit.objective`)
    and reported ln L (`StepFit.log_likelihood`)."""

    objective: float
    log_likelihood: float

    @classmethod
    def of(cls, fit: StepFit) -> Baseline:
        """`fit`'s objective and reported ln L."""
        return cls(float(fit.objective), float(fit.log_likelihood))


@dataclasses.dataclass(frozen=True, eq=False)
class StepFit:
    """One candidate model's fit to one record (`assess.fit_entries`, host side) and, once
    judged, its assessment (`assess.assess_fit`, `verdict.evaluate`).

    **The fit:**

    - `effect`: the candidate's name (`nominal` or the effect's); `model` the effect
        (`AbstractStepEffect`; None for the nominal model); `stochastic` whether it is a
        noise model; `k` its number of parameters.
    - `w`: the fitted parameter vector (`layout.W`), the held-out nuisances moved;
        `w_trained` the training optimum before they moved; `z` its refit part (4,) and
        `z_gain` the test winding's gain z; `gain` [V/V] the test winding's gain with its
        polarity.
    - `log_likelihood`: the profiled ln L of the training part at the training optimum
        `w_trained`, where `objective` is (with the refit's and the gain's priors, and for
        a measured input its level errors' and drift's terms: errors in variables);
        `innovation_variance` [V²] the one-step prediction variance there.
    - `prediction`, `prior_prediction` (n,) [V]: the fitted model's block means (at `w`)
        and the same model with the device at its prior values; `error` (n,) [V] the
        measured block means less `prediction`; `innovations` (n,) [V] the one-step
        errors at `w`.
    - `converged`: the solver's or the Newton decrement's word (`fit.CONVERGED_DECREMENT`);
        `steps` the solver's steps; `decrement` the Newton decrement; `objective` the
        solver's penalised cost at `w_trained` (`assess.nested_failed`);
        `baseline` the nominal model's fit at the same noise scale where the record's
        nominal fit was made at another (`rescale.REWEIGHT_ABOVE`), else None: what the fit
        is judged against (`assess.baseline`) and its evidence measured from.
    - `params`: the effect's physical values (`AbstractStepEffect.physical`; empty for the
        nominal model).
    - `optimum_shortfall`: where the fit is the nested model at its no-effect value
        (`rescale.settle_at_no_effect`: the solver's optimum read a lower ln L than the
        nominal, which the nested model contains), how far below the nominal's reported ln
        L that optimum had ended; None elsewhere.

    **The assessment** (NaN / False / None before `assess.assess_fit`): `ms_train`, `ms_held`
    [V²] the free-run errors' mean squares on the training and held-out parts,
    `ms_held_one_step` [V²] the one-step errors' on the held-out part;
    `model_noise_variance` [V²] the noise variance the model predicts (the floor's, or a
    noise model's σ_w² + σ_s²); `gap_train`, `gap_held` [V] the excess over it
    (`openworld.excess`); `explains` whether the model explains the record;
    `explains_model_form` whether a deterministic effect explains it up to its model form
    (`openworld.MODEL_FORM`); `out_of_prior` the refitted values beyond
    `openworld.PRIOR_LIMIT`; `plausible` whether it is credible. A noise model's
    `one_step_whiteness` (the held-out innovations' Ljung–Box test, an
    `openworld.Whiteness`), `free_run_over_noise_variance` (training, held-out) and
    `variance_consistent`; the nominal model's `whiteness` (its held-out free-run errors',
    an `openworld.Whiteness`); None elsewhere.
    """

    effect: str
    model: AbstractStepEffect | None
    stochastic: bool
    k: int
    w: np.ndarray
    w_trained: np.ndarray
    z: np.ndarray
    z_gain: float
    gain: float
    log_likelihood: float
    innovation_variance: float
    prediction: np.ndarray
    prior_prediction: np.ndarray
    error: np.ndarray
    innovations: np.ndarray
    converged: bool
    steps: int
    decrement: float
    objective: float
    params: dict[str, Any]
    baseline: Baseline | None = None
    optimum_shortfall: float | None = None
    ms_train: float = math.nan
    ms_held: float = math.nan
    ms_held_one_step: float = math.nan
    model_noise_variance: float = math.nan
    gap_train: float = math.nan
    gap_held: float = math.nan
    explains: bool = False
    explains_model_form: bool = False
    out_of_prior: tuple[str, ...] = ()
    plausible: bool = False
    one_step_whiteness: Whiteness | None = None
    free_run_over_noise_variance: list[float] | None = None
    variance_consistent: bool | None = None
    whiteness: Whiteness | None = None

    def device_shifts(self, prior_sigma=None) -> list[tuple[str, float]]:
        """(name, shift in σ of its prior) of each refitted device parameter
        (`model.REFIT_FIELDS`; with `prior_sigma`, those whose prior σ is not 0: the others
        are held) and of the test winding's gain."""
        shifts = [
            (name, float(z))
            for j, (name, z) in enumerate(zip(REFIT_FIELDS, self.z, strict=True))
            if prior_sigma is None or prior_sigma[j] > 0
        ]
        return shifts + [("test_winding_gain", float(self.z_gain))]


@dataclasses.dataclass(frozen=True, eq=False)
class JointFit:
    """One candidate's fit to a set of records of one device (`joint.fit_set`).

    **Fields:** `x` the fitted vector (the shared parameters, `layout.Shared`, then each
    record's own, `layout.Own`); `cost` the penalised cost Σr² at x (inf when not finite);
    `prediction` (records, blocks) [V] each record's fitted block means (padded);
    `penalties` the residuals of the priors and barriers at x; `converged` the solver's
    word; `steps` the solver's steps of each start tried.
    """

    x: np.ndarray
    cost: float
    prediction: np.ndarray
    penalties: np.ndarray
    converged: bool
    steps: list[int]


@dataclasses.dataclass(frozen=True)
class RecordScore:
    """One record's misfit under a candidate's joint fit (`joint._score`).

    **Fields** (named as reported): `rms_V` [V] the RMS of the record's block means less the
    fit's; `noise_floor_V` [V] its floor (`StepRecord.sigma`); `excess_over_floor` the RMS's
    excess over the floor (`openworld.excess`), in floors; `at_floor` whether that excess is
    within `openworld.FLOOR_FACTOR`.
    """

    rms_V: float
    noise_floor_V: float
    excess_over_floor: float
    at_floor: bool

    def to_dict(self) -> dict[str, Any]:
        """The score as the diagnosis reports it (`SetDiagnosis.records`, with the record's
        name, `on_stops` and `has_accel` before it)."""
        return field_dict(self)


@dataclasses.dataclass(frozen=True, eq=False)
class JointScore:
    """A joint fit's score (`joint._score`): `log_likelihood` the profiled ln L of every
    record with the shared priors; `records` each record's misfit (`RecordScore`, in the
    set's order); `n` the blocks of the set."""

    log_likelihood: float
    records: tuple[RecordScore, ...]
    n: int


@dataclasses.dataclass(frozen=True)
class RankingEntry(Candidate):
    """A candidate's entry in the ranking (`verdict.ranking_entry`): the fields
    `openworld.decide` reads (`openworld.Candidate`) and what the diagnosis reports with
    them (`to_dict`: `DiagnosisResult.ranking`'s dict, key for key).

    - `fit_failed`: its nested fit ended below the nominal's likelihood: the penalised one
        the solver maximised (a solver failure, `assess.nested_failed`;
        `objective_below_nominal` by how much, ≥ 0, ln L units, and `objective_round_off`
        the round-off share of that comparison, `assess.nested_round_off`: a shortfall
        within it, or within `assess.NESTED_RESTART_ABOVE`, is not one) or the reported ln L that
        the evidence compares (`assess.reported_below`; `log_likelihood_below_nominal`);
        `solver_failed` whether the former (a fit flagged by its reported ln L alone did
        not fail in the solver: the two likelihoods weigh the residual against the priors
        differently, `assess.NESTED_LNL_SLACK`).
    - `at_no_effect`: the entry is the nested model at its no-effect value, the nominal
        model exactly (`rescale.settle_at_no_effect`: the solver's optimum read a ln L
        `optimum_log_likelihood_below_nominal` below the nominal's, after the refits at
        σ̂): its evidence is −k ln n, its fit the nominal's.
    - `explains_up_to_model_form`: a deterministic effect that explains the record up to
        its model form (`openworld.MODEL_FORM`).
    - `gap_after_V` [V]: the held-out gap with the effect; `gap_shrink` the fraction of the
        nominal's it removes (RMS).
    - `held_out_mean_square`, `held_out_one_step_mean_square` [V²]: its free-run and
        one-step errors' on the held-out part.
    - `params`: the effect's physical values; `converged`, `fit_steps` the solver's word
        and steps; `out_of_prior` the refitted values beyond `openworld.PRIOR_LIMIT`.
    - A noise model's (None for a deterministic effect, and left out of `to_dict`):
        `one_step_whiteness` its held-out one-step errors' Ljung–Box test (an
        `openworld.Whiteness`; its `to_dict()` in the row),
        `variance_consistent`, and `predictability_null_quantile` what each predictor
        removes from the fitted noise alone (`noise_null`; None where not computed).
    """

    fit_failed: bool
    objective_below_nominal: float
    explains_up_to_model_form: bool
    gap_after_V: float
    gap_shrink: float
    held_out_mean_square: float
    held_out_one_step_mean_square: float
    params: dict[str, Any]
    converged: bool
    fit_steps: int
    out_of_prior: list[str]
    log_likelihood_below_nominal: float = 0.0
    solver_failed: bool = False
    objective_round_off: float = 0.0
    at_no_effect: bool = False
    optimum_log_likelihood_below_nominal: float | None = None
    one_step_whiteness: Whiteness | None = None
    variance_consistent: bool | None = None
    predictability_null_quantile: dict[str, Any] | None = None

    def to_dict(self) -> dict[str, Any]:
        out = {
            "effect": self.effect,
            "evidence": self.evidence,
            "fit_failed": self.fit_failed,
            "solver_failed": self.solver_failed,
            "objective_below_nominal": self.objective_below_nominal,
            "objective_round_off": self.objective_round_off,
            "log_likelihood_below_nominal": self.log_likelihood_below_nominal,
            "at_no_effect": self.at_no_effect,
            "optimum_log_likelihood_below_nominal": self.optimum_log_likelihood_below_nominal,
            "significant": self.significant,
            "stochastic": self.stochastic,
            "explains": self.explains,
            "explains_up_to_model_form": self.explains_up_to_model_form,
            "plausible": self.plausible,
            "explained_fraction": self.explained_fraction,
            "gap_after_V": self.gap_after_V,
            "gap_shrink": self.gap_shrink,
            "held_out_mean_square": self.held_out_mean_square,
            "held_out_one_step_mean_square": self.held_out_one_step_mean_square,
            "params": self.params,
            "converged": self.converged,
            "fit_steps": self.fit_steps,
            "out_of_prior": list(self.out_of_prior),
        }
        if self.stochastic:
            white = self.one_step_whiteness
            out.update(
                {
                    "deterministic_misfit": self.deterministic_misfit,
                    "one_step_whiteness": None if white is None else white.to_dict(),
                    "variance_consistent": self.variance_consistent,
                    "predictability_null_quantile": self.predictability_null_quantile,
                }
            )
        return out


@dataclasses.dataclass(frozen=True, eq=False)
class SetRankingEntry:
    """A candidate's entry in the ranking of a set of records (`joint_verdict._rank`).

    **Fields** (named as reported): `effect` the candidate (`joint.CANDIDATES`); `evidence`
    its 2 ln B against the nominal model, every record together (Schwarz: ln n per lag
    parameter; 0 for the nominal); `all_at_floor` whether it leaves every record at its
    floor (`RecordScore.at_floor`); `worst_excess_over_floor` the largest of the records'
    excesses over their floors, in floors; `converged` the solver's word
    (`JointFit.converged`); `shared` the shared device values it fitted
    (`joint.shared_values`: parameter name → value, as reported).
    """

    effect: str
    evidence: float
    all_at_floor: bool
    worst_excess_over_floor: float
    converged: bool
    shared: dict[str, Any]

    def to_dict(self) -> dict[str, Any]:
        """The entry as the diagnosis reports it (`SetDiagnosis.ranking`)."""
        return field_dict(self)
