"""The typed results of `identify_step_record` and `identify_step_records`.

Each is a frozen dataclass whose attributes carry the names (and SI units, in the suffix)
of the keys of its JSON; `to_dict()` gives the JSON-ready dict that `accel-jax identify`
writes (key for key, in the same order). The string-keyed access of the plain dicts these
replaced (`result["fit"]`) still works for one release, with a `DeprecationWarning`
(`accel_jax._deprecated.LegacyItems`).
"""

from __future__ import annotations

import dataclasses
from typing import TypeAlias

import numpy as np

from .._deprecated import LegacyItems


def _plain(value):
    """`value` as the dicts held it: a typed part by its `to_dict()`, lists item by item."""
    if hasattr(value, "to_dict"):
        return value.to_dict()
    if isinstance(value, list):
        return [_plain(v) for v in value]
    return value


class _Fields:
    """`to_dict()`: the fields in their order, each as `_plain` gives it."""

    def to_dict(self) -> dict:
        """The JSON-ready dict: one key per field, in the fields' order."""
        return {name: _plain(value) for name, value in vars(self).items()}


@dataclasses.dataclass(frozen=True)
class StepSegment(_Fields):
    """The part of the record identified: the first change of the test voltage up to the
    next one (or the record's end).

    **Fields:** `samples` its number of samples; `t_start_s`, `t_end_s` its first and last
    sample's time in [s]; `step_time_s` when the step was applied in [s]; `test_step_V` the
    step's size in [V]; `sample_rate_Hz` the record's sample rate in [Hz].
    """

    samples: int
    t_start_s: float
    t_end_s: float
    step_time_s: float
    test_step_V: float
    sample_rate_Hz: float


@dataclasses.dataclass(frozen=True)
class OscillatoryEstimate(_Fields):
    """The oscillatory graph-analytic estimate (Mironov, Fominov & Maletin, steps
    (7)-(10)) and what it read off the record.

    **Fields:** `method` the method in words; `time_constant_s` T in [s];
    `damping_ratio` ξ; `period_s` the period t2 − t1 in [s]; `scale_factor` K̂_a in
    [V/(m/s²)]; `steady_state_V` U_ss in [V]; `crossing_t1_s`, `crossing_t2_s` the
    crossings of U_ss in [s]; `overshoot_A1_V`, `undershoot_A2_V` the extrema A1, A2 in
    [V] and `overshoot_A1_time_s`, `undershoot_A2_time_s` their times in [s];
    `dKa_percent` δK_a against the nominal K_a in [%].
    """

    method: str
    time_constant_s: float
    damping_ratio: float
    period_s: float
    scale_factor: float
    steady_state_V: float
    crossing_t1_s: float
    crossing_t2_s: float
    overshoot_A1_V: float
    overshoot_A1_time_s: float
    undershoot_A2_V: float
    undershoot_A2_time_s: float
    dKa_percent: float


@dataclasses.dataclass(frozen=True)
class AperiodicEstimate(_Fields):
    """The aperiodic graph-analytic estimate (Mironov, Fominov & Maletin, steps 1-10 with
    the lag correction (16)) and what it read off the record.

    **Fields:** `method` the method in words; `T1_s` … `T4_s` the time constants T1..T4
    in [s]; `time_constant_s` T in [s]; `damping_ratio` ξ; `lag_correction_s` the lag
    T_dm + T_f taken out of the inflection time in [s]; `scale_factor` K̂_a in
    [V/(m/s²)]; `steady_state_V` U_ss in [V]; `inflection_time_s` the time of the steepest
    slope in [s]; `max_slope_V_per_s` that slope in [V/s]; `dKa_percent` δK_a against the
    nominal K_a in [%].
    """

    method: str
    T1_s: float
    T2_s: float
    T3_s: float
    T4_s: float
    time_constant_s: float
    damping_ratio: float
    lag_correction_s: float
    scale_factor: float
    steady_state_V: float
    inflection_time_s: float
    max_slope_V_per_s: float
    dKa_percent: float


GraphEstimate: TypeAlias = OscillatoryEstimate | AperiodicEstimate
"""The graph-analytic estimate: oscillatory or aperiodic, whichever fitted the record."""


@dataclasses.dataclass(frozen=True)
class FitParameter(_Fields):
    """One parameter the order-3 fit estimates (T, ξ, T_dm, G, U0) or reports (K_a).

    **Fields:** `name`, `description`, `unit` (SI, the unit of the three values);
    `nominal` its nominal value (None where the device does not fix one); `estimate`;
    `std` σ from the fit's covariance; `shift_in_std` (estimate − nominal)/σ (None without
    a nominal value or a usable σ).
    """

    name: str
    description: str
    unit: str
    nominal: float | None
    estimate: float
    std: float
    shift_in_std: float | None


@dataclasses.dataclass(frozen=True)
class WhitenessTest(_Fields):
    """The Ljung-Box test of the fit residual's whiteness.

    **Fields:** `test` its name; `statistic` Q; `lags` L; `p_value`; `level` the level
    below which the residual is not white; `white` whether p ≥ level; `autocorrelation`
    r_1..r_L; `band_95` the ±1.96/√n band of r_k for white noise.
    """

    test: str
    statistic: float
    lags: int
    p_value: float
    level: float
    white: bool
    autocorrelation: list[float]
    band_95: float


@dataclasses.dataclass(frozen=True)
class FitQuality(_Fields):
    """The fit's quality as the System Identification Toolbox reports it.

    **Fields:** `fit_percent` `compare`'s fit percentage; `nrmse` `goodnessOfFit`'s NRMSE
    (both over the whole segment); `residual_rms_V` the residual's rms in [V];
    `noise_std_V` the noise σ of the settled tail in [V]; `whiteness` a `WhitenessTest`.
    """

    fit_percent: float
    nrmse: float
    residual_rms_V: float
    noise_std_V: float
    whiteness: WhitenessTest


@dataclasses.dataclass(frozen=True)
class LeastSquaresFit(_Fields):
    """The order-3 least-squares fit of the whole segment (T, ξ, T_dm free; T_f known).

    **Fields:** `method` the method in words; `time_constant_s` T and
    `time_constant_std_s` its σ in [s]; `damping_ratio` ξ and `damping_ratio_std` its σ;
    `torquer_time_constant_s` T_dm in [s]; `residual_rms_V` in [V]; `scale_factor` K̂_a and
    `scale_factor_std` its σ in [V/(m/s²)]; `dKa_percent` δK_a and `dKa_std_percent` its σ
    in [%]; `torquer_time_constant_std_s` σ of T_dm in [s]; `gain_V` G and `offset_V` U0
    in [V]; `known_feedback_fraction` K_test and `known_filter_time_constant_s` T_f in [s]
    (held fixed); `parameters` one `FitParameter` each, against its nominal value;
    `quality` a `FitQuality`.
    """

    method: str
    time_constant_s: float
    time_constant_std_s: float
    damping_ratio: float
    damping_ratio_std: float
    torquer_time_constant_s: float
    residual_rms_V: float
    scale_factor: float
    scale_factor_std: float
    dKa_percent: float
    dKa_std_percent: float
    torquer_time_constant_std_s: float
    gain_V: float
    offset_V: float
    known_feedback_fraction: float
    known_filter_time_constant_s: float
    parameters: list[FitParameter]
    quality: FitQuality


@dataclasses.dataclass(frozen=True)
class FitFailure:
    """The least-squares fit that did not succeed.

    **Fields:** `reason` why, in words (`{"failed": reason}` in the JSON).
    """

    reason: str

    def to_dict(self) -> dict:
        """`{"failed": reason}`."""
        return {"failed": self.reason}


@dataclasses.dataclass(frozen=True)
class NominalValues(_Fields):
    """The nominal device's values the estimates are compared with.

    **Fields:** `scale_factor` K_a in [V/(m/s²)]; `time_constant_s` T in [s];
    `damping_ratio` ξ; `torquer_time_constant_s` T_dm in [s];
    `pickoff_amplifier_gain_V_per_m` k_dp k_y in [V/m]; `shape_factor` the γ used.
    """

    scale_factor: float
    time_constant_s: float
    damping_ratio: float
    torquer_time_constant_s: float
    pickoff_amplifier_gain_V_per_m: float
    shape_factor: float


@dataclasses.dataclass(frozen=True, eq=False)
class StepTraces:
    """The segment sample by sample, for `identification_figure` (not in the JSON).

    **Fields:** `t_s` the times in [s]; `u_out_V` the output in [V]; `model_V` the fitted
    model's output in [V] (None when the fit failed).
    """

    t_s: np.ndarray
    u_out_V: np.ndarray
    model_V: np.ndarray | None = None

    def to_dict(self) -> dict:
        """`{"t_s", "u_out_V"}` and, when the fit succeeded, `"model_V"` (NumPy arrays)."""
        out = {"t_s": self.t_s, "u_out_V": self.u_out_V}
        if self.model_V is not None:
            out["model_V"] = self.model_V
        return out


@dataclasses.dataclass(frozen=True, eq=False)
class StepIdentification(LegacyItems):
    """What `identify_step_record` found in one record.

    **Fields:**

    - `segment`: the part of the record used (`StepSegment`).
    - `graph`: the graph-analytic estimate (`OscillatoryEstimate` or `AperiodicEstimate`).
    - `fit`: the order-3 least-squares fit (`LeastSquaresFit`), or `FitFailure`.
    - `nominal`: the nominal values compared with (`NominalValues`).
    - `assumptions`: each assumption the identification made, in words (a dict of str).
    - `traces`: the segment and the fitted model, sample by sample (`StepTraces`).

    `to_dict()` is the JSON of `accel-jax identify` (without its `source` and
    `provenance`); `result["fit"]` and the other keys of the dict this replaced still work
    for one release, with a `DeprecationWarning`.
    """

    segment: StepSegment
    graph: GraphEstimate
    fit: LeastSquaresFit | FitFailure
    nominal: NominalValues
    assumptions: dict[str, str]
    traces: StepTraces

    def to_dict(self, *, traces: bool = False) -> dict:
        """The JSON-ready dict: `segment`, `graph`, `fit`, `nominal`, `assumptions`, each
        as a plain dict; with `traces`, also `traces` (NumPy arrays, not JSON-ready).

        **Arguments:**

        - `traces`: include the traces (the dict `identify_step_record` returned before
            it was typed).

        **Returns:** a dict, key for key what `accel-jax identify` writes.
        """
        out = {
            "segment": self.segment.to_dict(),
            "graph": self.graph.to_dict(),
            "fit": self.fit.to_dict(),
            "nominal": self.nominal.to_dict(),
            "assumptions": dict(self.assumptions),
        }
        if traces:
            out["traces"] = self.traces.to_dict()
        return out

    def _legacy(self) -> dict:
        return self.to_dict(traces=True)


@dataclasses.dataclass(frozen=True)
class StopRecordGain(LegacyItems):
    """k_dp k_y by eq. (11) from a record whose test steps drive the pendulum onto both
    stops (`identify_step_records`; the values of `stop_record_gain`).

    **Fields:** `u_plus_V`, `u_minus_V` the output's medians on its upper and lower
    plateaus in [V]; `offset_V` ½(U⁺ + U⁻) in [V]; `pickoff_amplifier_gain_V_per_m`
    k_dp k_y in [V/m]; `nominal_V_per_m` its nominal value in [V/m]; `shift_relative` the
    relative shift from it; `plateau_samples` the samples on each plateau [upper, lower];
    `h_max_m` the stop displacement used in [m]; `noise_floor_V` the output's noise floor
    in [V]; `method` the method in words.

    `to_dict()` is `{"stops": {...}}`, the record's entry in the JSON of
    `accel-jax identify A.csv B.csv …` (without its `source`); `result["stops"]` still
    works for one release, with a `DeprecationWarning`.
    """

    u_plus_V: float
    u_minus_V: float
    offset_V: float
    pickoff_amplifier_gain_V_per_m: float
    nominal_V_per_m: float
    shift_relative: float
    plateau_samples: list[int]
    h_max_m: float
    noise_floor_V: float
    method: str

    def to_dict(self) -> dict:
        """`{"stops": {...}}`: the fields in their order under the key `stops`."""
        return {"stops": {name: _plain(value) for name, value in vars(self).items()}}

    def _legacy(self) -> dict:
        return self.to_dict()

    def _legacy_advice(self, key: str) -> str:
        return (
            "use its fields: result['stops'][name] is result.name (e.g. "
            "result.pickoff_amplifier_gain_V_per_m), or result.to_dict()['stops']"
        )
