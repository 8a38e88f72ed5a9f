"""The typed results that replaced plain dicts (`StepIdentification`, `StopRecordGain`,
`StaticRecordAnalysis`, `HeldOutCheck`): their `to_dict()` is the old dict key for key and
in the same order (so the CLI's JSON is unchanged), and the old dict access still works with
a `DeprecationWarning` naming the attribute. (Nothing in the package uses it: pytest turns a
`DeprecationWarning` raised from `accel_jax` into an error, and the CLI tests run it all.)"""

import dataclasses
import json
import warnings

import equinox as eqx
import jax
import numpy as np
import pytest
from click.testing import CliRunner

import accel_jax as aj
from accel_jax._identify.step_record import identify_step_record, identify_step_records
from accel_jax._identify.step_result import (
    AperiodicEstimate,
    FitFailure,
    FitParameter,
    FitQuality,
    LeastSquaresFit,
    OscillatoryEstimate,
    StepIdentification,
    StepTraces,
    StopRecordGain,
    WhitenessTest,
)
from accel_jax._noise.analysis import StaticRecordAnalysis, analyse_static_record, analysis_to_json
from accel_jax._noise.held_out import HeldOutCheck
from accel_jax.cli import main
from accel_jax.report import identification_figure, identification_summary

# The keys of the dicts these results replaced, in their order (as the CLI's JSON has them).
SEGMENT = ["samples", "t_start_s", "t_end_s", "step_time_s", "test_step_V", "sample_rate_Hz"]
OSCILLATORY = [
    "method", "time_constant_s", "damping_ratio", "period_s", "scale_factor", "steady_state_V",
    "crossing_t1_s", "crossing_t2_s", "overshoot_A1_V", "overshoot_A1_time_s",
    "undershoot_A2_V", "undershoot_A2_time_s", "dKa_percent",
]  # fmt: skip
APERIODIC = [
    "method", "T1_s", "T2_s", "T3_s", "T4_s", "time_constant_s", "damping_ratio",
    "lag_correction_s", "scale_factor", "steady_state_V", "inflection_time_s",
    "max_slope_V_per_s", "dKa_percent",
]  # fmt: skip
FIT = [
    "method", "time_constant_s", "time_constant_std_s", "damping_ratio", "damping_ratio_std",
    "torquer_time_constant_s", "residual_rms_V", "scale_factor", "scale_factor_std",
    "dKa_percent", "dKa_std_percent", "torquer_time_constant_std_s", "gain_V", "offset_V",
    "known_feedback_fraction", "known_filter_time_constant_s", "parameters", "quality",
]  # fmt: skip
PARAMETER = ["name", "description", "unit", "nominal", "estimate", "std", "shift_in_std"]
QUALITY = ["fit_percent", "nrmse", "residual_rms_V", "noise_std_V", "whiteness"]
WHITENESS = [
    "test", "statistic", "lags", "p_value", "level", "white", "autocorrelation", "band_95",
]  # fmt: skip
NOMINAL = [
    "scale_factor", "time_constant_s", "damping_ratio", "torquer_time_constant_s",
    "pickoff_amplifier_gain_V_per_m", "shape_factor",
]  # fmt: skip
STOPS = [
    "u_plus_V", "u_minus_V", "offset_V", "pickoff_amplifier_gain_V_per_m", "nominal_V_per_m",
    "shift_relative", "plateau_samples", "h_max_m", "noise_floor_V", "method",
]  # fmt: skip
HELD_OUT = [
    "excess_deviance", "z", "bins", "removed", "exchanged", "ties", "bursts", "non_gaussian",
    "spectral_change", "drift", "drifting", "level_shift_test",
]  # fmt: skip
ADDED = ["white_floor", "low_pass_ties"]
"""Keys added to the held-out dict since (the signal chain's checks), after the old ones."""

N, PRE = 5000, 200


def _record(params, sample_rate, seed=0):
    ts = np.arange(N) / sample_rate
    u_test = (np.arange(N) >= PRE).astype(float)
    u = np.asarray(aj.simulate_linear(params, ts, u_test, key=jax.random.key(seed)))
    u = u + 1e-4 * np.random.default_rng(seed).standard_normal(N)
    return aj.StepData(ts, u_test, u)


@pytest.fixture(scope="module")
def identified():
    reference = aj.ServoParams.reference()
    over = eqx.tree_at(lambda p: p.damping, reference, aj.damping_for_ratio(reference, 2.0))
    return {
        "oscillatory": identify_step_record(_record(reference, 1e6), reference),
        "aperiodic": identify_step_record(_record(over, 1e5), over),
    }


def _as_old(result: StepIdentification) -> dict:
    """The dict `identify_step_record` returned before it was typed, built here from the
    attributes with the old keys written out (not by `to_dict`)."""
    graph = result.graph
    keys = OSCILLATORY if isinstance(graph, OscillatoryEstimate) else APERIODIC
    fit = result.fit
    assert isinstance(fit, LeastSquaresFit)
    quality = fit.quality
    old_fit = {k: getattr(fit, k) for k in FIT[:-2]}
    old_fit["parameters"] = [{k: getattr(row, k) for k in PARAMETER} for row in fit.parameters]
    old_fit["quality"] = {k: getattr(quality, k) for k in QUALITY[:-1]}
    old_fit["quality"]["whiteness"] = {k: getattr(quality.whiteness, k) for k in WHITENESS}
    return {
        "segment": {k: getattr(result.segment, k) for k in SEGMENT},
        "graph": {k: getattr(graph, k) for k in keys},
        "fit": old_fit,
        "nominal": {k: getattr(result.nominal, k) for k in NOMINAL},
        "assumptions": dict(result.assumptions),
    }


def _same_order(a, b):
    """Equal, and every dict's keys in the same order (what makes the JSON the same text)."""
    assert a == b
    if isinstance(a, dict):
        assert list(a) == list(b)
        for key in a:
            _same_order(a[key], b[key])
    elif isinstance(a, list):
        for x, y in zip(a, b, strict=True):
            _same_order(x, y)


@pytest.mark.parametrize("kind", ["oscillatory", "aperiodic"])
def test_step_identification_is_typed_and_its_dict_is_the_old_one(identified, kind):
    result = identified[kind]
    assert isinstance(
        result.graph, OscillatoryEstimate if kind == "oscillatory" else AperiodicEstimate
    )
    assert isinstance(result.fit, LeastSquaresFit)
    assert isinstance(result.fit.quality, FitQuality)
    assert isinstance(result.fit.quality.whiteness, WhitenessTest)
    assert all(isinstance(row, FitParameter) for row in result.fit.parameters)
    assert [row.name for row in result.fit.parameters] == ["T", "ξ", "T_dm", "G", "U0", "K_a"]
    assert isinstance(result.traces, StepTraces) and result.traces.model_V is not None
    assert result.segment.samples == N and result.graph.dKa_percent == pytest.approx(
        100 * (result.graph.scale_factor - result.nominal.scale_factor) / result.graph.scale_factor
    )
    with pytest.raises(dataclasses.FrozenInstanceError):
        result.fit = FitFailure("no")  # type: ignore[misc]

    plain = result.to_dict()
    _same_order(plain, _as_old(result))
    assert json.loads(json.dumps(plain)) == plain  # JSON-ready
    with_traces = result.to_dict(traces=True)
    assert list(with_traces) == ["segment", "graph", "fit", "nominal", "assumptions", "traces"]
    assert list(with_traces["traces"]) == ["t_s", "u_out_V", "model_V"]
    assert with_traces["traces"]["t_s"] is result.traces.t_s


def test_the_cli_json_is_the_results_dict(identified, tmp_path):
    """`accel-jax identify --json` writes `to_dict()` (after `source`, before
    `provenance`), in its order."""
    reference = aj.ServoParams.reference()
    data = _record(reference, 1e6)
    csv, out = tmp_path / "step.csv", tmp_path / "id.json"
    aj.write_csv(csv, data)
    result = CliRunner().invoke(main, ["identify", str(csv), "--json", str(out)])
    assert result.exit_code == 0, result.output
    doc = json.loads(out.read_text())
    assert list(doc) == [
        "source",
        "segment",
        "graph",
        "fit",
        "nominal",
        "assumptions",
        "provenance",
    ]
    expected = json.loads(json.dumps(identify_step_record(aj.read_csv(csv), reference).to_dict()))
    _same_order({k: doc[k] for k in expected}, expected)


def test_a_failed_fit_and_its_traces():
    failure = FitFailure("The least-squares fit did not converge within max_steps.")
    assert failure.to_dict() == {"failed": failure.reason}
    traces = StepTraces(np.zeros(3), np.ones(3))
    assert list(traces.to_dict()) == ["t_s", "u_out_V"]  # no model_V without a fit


def _stop_record(params):
    """A record whose ±5.5 V test levels hold the pendulum on its stops: the output sits on
    ±k_dp k_y h_max (+ 10 mV offset) with 1 mV of noise, made here with NumPy."""
    n = 3000
    u_test = np.repeat([0.0, 5.5, -5.5], n // 3)
    plateau = float(params.pickoff_gain * params.amplifier_gain * params.stop_displacement)
    u_out = 0.01 + np.sign(u_test) * plateau + 1e-3 * np.random.default_rng(2).normal(size=n)
    return aj.StepData(np.arange(n) * 2e-6, u_test, u_out)


def test_stop_record_gain_is_typed_and_its_dict_is_the_old_one(identified):
    reference = aj.ServoParams.reference()
    results = identify_step_records([_stop_record(reference)], reference)
    (stops,) = results
    assert isinstance(stops, StopRecordGain)
    assert stops.pickoff_amplifier_gain_V_per_m == pytest.approx(
        float(reference.pickoff_gain * reference.amplifier_gain), rel=0.01
    )
    plain = stops.to_dict()
    assert list(plain) == ["stops"] and list(plain["stops"]) == STOPS
    assert plain["stops"] == {k: getattr(stops, k) for k in STOPS}
    with pytest.warns(DeprecationWarning, match=r"result\['stops'\] is deprecated.*result\.name"):
        assert stops["stops"] == plain["stops"]


def test_the_old_dict_access_warns_and_gives_the_old_values(identified):
    result = identified["oscillatory"]
    old = result.to_dict(traces=True)
    pattern = r"result\['fit'\] is deprecated.*use result\.fit \(or result\.to_dict\(\)\['fit'\]\)"
    with pytest.warns(DeprecationWarning, match=pattern) as caught:
        assert result["fit"] == old["fit"]
    assert "next release" in str(caught[0].message)
    assert caught[0].filename == __file__  # attributed to the caller
    with pytest.warns(DeprecationWarning, match=r"result\['traces'\].*result\.traces"):
        assert result["traces"]["model_V"] is result.traces.model_V
    with pytest.warns(DeprecationWarning, match=r"result\.get\('graph'\)"):
        assert result.get("graph") == old["graph"]
    assert result.get("no_such_key", 3) == 3
    with pytest.warns(DeprecationWarning, match="'stops' in result"):
        assert "stops" not in result
    with pytest.warns(DeprecationWarning, match=r"result\.keys\(\)"):
        assert list(result.keys()) == list(old)
    with pytest.warns(DeprecationWarning, match=r"result\.items\(\)"):
        assert dict(result.items())["segment"] == old["segment"]
    with pytest.raises(KeyError):
        result["no_such_key"]


def test_the_report_takes_the_typed_result_without_warnings(identified):
    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)
        for result in identified.values():
            assert "δK_a" in identification_summary(result)
            assert len(identification_figure(result).axes) == 3


# ---- the static-record analysis and the selection's held-out check ----


@pytest.fixture(scope="module")
def stepped():
    """2 mg white noise with a 4 mg step in its level at a quarter (NumPy)."""
    rng = np.random.default_rng(21)
    n = 4000
    return 0.3 + 2e-3 * rng.normal(size=n) + 4e-3 * (np.arange(n) >= n // 4)


@pytest.mark.slow
def test_static_record_analysis_is_typed_and_its_dict_is_the_old_one(stepped):
    analysis = analyse_static_record(stepped, 0.01, n_bootstrap=50)
    assert isinstance(analysis, StaticRecordAnalysis)
    assert isinstance(analysis.selection.held_out, HeldOutCheck)
    assert isinstance(analysis.allan, aj.noise.AllanDeviation)
    plain = analysis.to_dict()
    assert list(plain) == ["allan_deviation", "ieee_terms", "effects"]
    held = plain["effects"]["held_out"]
    assert list(held) == [*HELD_OUT, "level_shifts", "saturation", *ADDED]
    assert held == {k: getattr(analysis.selection.held_out, k) for k in held}
    assert held["level_shifts"] and held["level_shifts"][0]["time_s"] == pytest.approx(
        10.0, abs=0.3
    )
    # analysis_to_json: the same, from the result or from a dict of its four parts
    old_form = {
        "allan": analysis.allan,
        "terms": analysis.terms,
        "selection": analysis.selection,
        "export_terms": analysis.export_terms,
    }
    _same_order(analysis_to_json(analysis), plain)
    _same_order(analysis_to_json(old_form), plain)
    json.dumps(plain)  # JSON-ready
    with pytest.warns(DeprecationWarning, match=r"result\['selection'\].*result\.selection"):
        assert analysis["selection"] is analysis.selection
    with pytest.warns(DeprecationWarning, match=r"result\['z'\] is deprecated.*result\.z"):
        assert analysis.selection.held_out["z"] == analysis.selection.held_out.z
    with pytest.warns(DeprecationWarning, match=r"result\.get\('level_shifts'\)"):
        assert analysis.selection.held_out.get("level_shifts") == held["level_shifts"]
    assert analysis.selection.held_out.get("step_or_walk") is None  # absent, no warning


def _held_out(**more):
    base = {k: [] for k in ("removed", "exchanged", "ties", "bursts")}
    return HeldOutCheck(
        excess_deviance=1.0,
        z=0.5,
        bins=100,
        non_gaussian={"tested": False, "significant": False},
        spectral_change={"tested": False, "significant": False},
        drift={"slope_per_s": 0.0, "t": 0.1},
        drifting=False,
        **{**base, **more},
    )


def test_held_out_check_keeps_the_old_keys_present_only_where_they_were():
    """`more_level_shifts` was set only when True; `step_or_walk` only where its test ran,
    then possibly None."""
    assert list(_held_out().to_dict()) == [*HELD_OUT, "level_shifts", "saturation", *ADDED]
    more = _held_out(more_level_shifts=True).to_dict()
    assert list(more) == [*HELD_OUT, "more_level_shifts", "level_shifts", "saturation", *ADDED]
    assert more["more_level_shifts"] is True
    ran = _held_out(step_or_walk=None, step_or_walk_tested=True).to_dict()
    assert list(ran) == [*HELD_OUT, "step_or_walk", "level_shifts", "saturation", *ADDED]
    assert ran["step_or_walk"] is None and ran["level_shift_test"] is None
    with pytest.warns(DeprecationWarning, match="'more_level_shifts' in result"):
        assert "more_level_shifts" not in _held_out()
    with pytest.raises(KeyError):
        _held_out()["more_level_shifts"]


def test_step_ranking_entry_is_typed_and_its_dict_is_the_old_row():
    # The step verdict decides on `RankingEntry`s (an `openworld.Candidate` each) and
    # reports their `to_dict`: the row `DiagnosisResult.ranking` held before, key for key
    # and in order (with `objective_round_off`, added since), a noise model's four keys only
    # on a noise model's row.
    from accel_jax.diagnose.openworld import Candidate, Whiteness
    from accel_jax.diagnose.step.state import RankingEntry

    common = dict(
        evidence=12.5, significant=True, explains=False, plausible=True,
        explained_fraction=0.4, fit_failed=False, objective_below_nominal=0.0,
        explains_up_to_model_form=False, gap_after_V=1e-3, gap_shrink=0.2,
        held_out_mean_square=2e-6, held_out_one_step_mean_square=1e-6, params={"T_dm_s": 4e-5},
        converged=True, fit_steps=7, out_of_prior=["J"],
    )
    old_keys = [
        "effect", "evidence", "fit_failed", "solver_failed", "objective_below_nominal",
        "objective_round_off", "log_likelihood_below_nominal", "at_no_effect",
        "optimum_log_likelihood_below_nominal", "significant",
        "stochastic", "explains", "explains_up_to_model_form", "plausible",
        "explained_fraction", "gap_after_V", "gap_shrink", "held_out_mean_square",
        "held_out_one_step_mean_square", "params", "converged", "fit_steps", "out_of_prior",
    ]
    noise_keys = [
        "deterministic_misfit", "one_step_whiteness", "variance_consistent",
        "predictability_null_quantile",
    ]
    lag = RankingEntry(effect="torquer_lag", stochastic=False, deterministic_misfit=False, **common)
    assert isinstance(lag, Candidate)
    assert list(lag.to_dict()) == old_keys
    assert lag.to_dict()["out_of_prior"] == ["J"] and lag.to_dict()["evidence"] == 12.5
    noise = RankingEntry(
        effect="colored_noise", stochastic=True, deterministic_misfit=True,
        one_step_whiteness=Whiteness(12.0, 20, 0.9, True, 1e-3), variance_consistent=False,
        **common,
    )
    row = noise.to_dict()
    assert list(row) == old_keys + noise_keys
    assert row["one_step_whiteness"] == {
        "statistic": 12.0, "lags": 20, "p_value": 0.9, "white": True, "level": 1e-3
    }
    assert row["deterministic_misfit"] is True and row["variance_consistent"] is False
    assert row["predictability_null_quantile"] is None
    json.dumps(row)


def test_the_experiment_menu_is_typed_and_its_old_dicts_warn():
    # `step.design.experiment_menu` returns `ExperimentDesign`s (they were dicts):
    # `to_dict()` has the old keys in order; the old access reads with a warning, and
    # `expected_evidence` still takes the old dict.
    from accel_jax.diagnose.step.design import ExperimentDesign, experiment_menu

    menu = experiment_menu(aj.NominalDevice.reference(), 500e3, 1e-4)
    assert all(isinstance(d, ExperimentDesign) for d in menu)
    keys = ["description", "record", "noise_V", "levels_V", "accel_levels_g"]
    assert [list(d.to_dict()) for d in menu] == [keys] * len(menu)
    steps, accel = menu[0], menu[1]
    assert steps.accel_levels_g is None and accel.accel_levels_g == [0.0, 1.0, -1.0, 1.0, 0.0]
    assert accel.record.a_in is not None and steps.noise_V == 1e-4
    assert ExperimentDesign.from_mapping(accel.to_dict()).to_dict() == accel.to_dict()
    with pytest.warns(DeprecationWarning, match="use result.levels_V"):
        assert accel["levels_V"] == accel.levels_V


def test_field_dict_is_every_field_in_order_json_ready():
    # `_io.field_dict`, the `to_dict()` of the typed results that hold their fields as they
    # are (`Decision`, `Whiteness`, `Predictability` and its calibrated subclass,
    # `NuisanceTest`, `ExperimentDesign`, the discovery's).
    import dataclasses

    from accel_jax._io import field_dict

    @dataclasses.dataclass(frozen=True)
    class Inner:
        a: int

        def to_dict(self):
            return {"a": self.a}

    @dataclasses.dataclass(frozen=True)
    class Outer:
        name: str
        tied: tuple
        parts: tuple
        inner: Inner | None
        table: dict
        extra: float | None = None
        last: float | None = None

    table = {"k": 1.0}
    out = field_dict(Outer("x", ("p", "q"), (Inner(1),), Inner(2), table), unless_none=("extra",))
    assert out == {
        "name": "x", "tied": ["p", "q"], "parts": [{"a": 1}], "inner": {"a": 2},
        "table": {"k": 1.0}, "last": None,
    }
    assert list(out) == ["name", "tied", "parts", "inner", "table", "last"]
    assert out["table"] is not table  # a copy: the caller may change it
    assert "extra" in field_dict(Outer("x", (), (), None, {}, extra=2.0), unless_none=("extra",))


def test_a_subclass_of_a_typed_result_reports_its_fields_after_its_parents():
    from accel_jax.diagnose.openworld import Predictability
    from accel_jax.diagnose.step.noise_null import CalibratedPredictability

    base = dict(input_locked=0.1, periodic=0.2, periodic_z=1.5, periodic_rms=1e-4,
                trend=0.0, frequency_Hz=None, deterministic=False)
    calibrated = CalibratedPredictability(
        **base, null_quantile={"trend": 0.3}, null_draws=100, null_model="colored_noise"
    )
    assert Predictability(**base).to_dict() == base
    assert calibrated.to_dict() == {
        **base, "null_quantile": {"trend": 0.3}, "null_draws": 100,
        "null_model": "colored_noise",
    }
