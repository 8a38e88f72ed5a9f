"""The discovery harness's scoring (studies/discovery_harness.py): a record is right only
when the best subset is exactly the generating term(s) or the one tie listed; the
calibration figure compares the coefficient with the truth's physics, in the loop's own
frame; a saved result is rescored without running anything. No JAX."""

import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "studies"))
import discovery_harness as harness  # noqa: E402

SCALES = {"half_V": 2.0, "period_s": 3e-4}


def _row(effect, terms, coefficient=0.0, sigma=1.0, rating="credible", tie=None, **truth):
    best = {
        "terms": list(terms),
        "columns": [{"term": t, "coefficient": coefficient, "sigma": sigma} for t in terms],
    }
    discovery = {"rating": rating, "best": best, "tie": tie, "scales": SCALES}
    return {"truth": {"class": effect, **truth}, "verdict": "unexplained", "discovery": discovery}


def test_judge_needs_the_exact_subset_or_its_tie():
    periodic = _row("periodic_disturbance", ["forcing_sinusoid"])
    right = harness.judge("periodic_disturbance", periodic)
    assert right["right"] and right["credible_and_right"]
    # One of a pair is not the pair.
    half = harness.judge("pickoff_nonlinearity", _row("pickoff_nonlinearity", ["pickoff_cube"]))
    assert not half["right"]
    tie = {"terms": ["pickoff_square", "pickoff_cube"]}
    other = _row("pickoff_nonlinearity", ["pickoff_abs"], tie=tie)
    tied = harness.judge("pickoff_nonlinearity", other)
    assert tied["right"]
    # Nothing to find: never right, and a credible discovery counts against.
    clean = harness.judge("none", _row("none", ["forcing_ramp"]))
    assert not clean["right"] and clean["credible"]


def test_truth_coefficients_from_the_physics():
    lag = {"class": "loo_output_filter", "lag_s": 3e-5}
    assert harness.truth_coefficient(lag, SCALES) == pytest.approx(0.1)
    # The loop's frame: a reversed output reverses the asymmetry's and the drift's sign.
    asym = {"class": "torquer_asymmetry", "asymmetry": 0.02, "output_sign": -1.0}
    assert harness.truth_coefficient(asym, SCALES) == pytest.approx(-0.02)
    # The drift's ramp is a moment term: the output moves by k_test·c·h (k_test of the
    # truth's device, here 0.25 = k_dm·gain/(c + k_dm·gain) with gain = k_dp·k_y·l).
    l = harness.step_truth.Device().l
    device = {"k_dp": 1.0, "k_y": 1.0 / l, "k_dm": 1.0, "c": 3.0}  # gain 1, k_test 1/4
    drift = {"class": "loo_disturbance_drift", "drift_V": 0.01, "output_sign": 1.0,
             "device": device}
    assert harness.truth_coefficient(drift, SCALES) == pytest.approx(0.005 / 0.25)
    assert harness.truth_coefficient({"class": "periodic_disturbance"}, SCALES) is None


def test_calibration_counts_only_the_generating_term():
    records = {
        "a": _row("loo_output_filter", ["output_pole"], 0.1 + 1.5e-3, 1e-3, lag_s=3e-5),
        "b": _row("loo_output_filter", ["output_pole"], 0.1 + 3e-3, 1e-3, lag_s=3e-5),
        # The equivalent term, not the generating one: not in the calibration.
        "c": _row("loo_output_filter", ["torquer_pole"], 0.1, 1e-3, lag_s=3e-5),
        "d": _row("none", ["forcing_ramp"], 0.1, 1e-3),
    }
    out = harness.calibration(records)
    assert out["records"] == 2 and out["within_2_sigma"] == 1
    assert out["in_band_85_99"] is False  # 50 %: too few within 2σ
    assert out["z"]["a"] == pytest.approx(1.5) and out["z"]["b"] == pytest.approx(3.0)


def test_rescore_a_saved_result(tmp_path, capsys):
    records = {"a": _row("loo_output_filter", ["output_pole"], 0.1, 1e-3, lag_s=3e-5)}
    path = tmp_path / "result.json"
    path.write_text(json.dumps({"records": records}))
    assert harness.main(["--rescore", str(path)]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["calibration"]["within_2_sigma"] == 1
    assert printed["score"]["findable_credible_and_right"] == 1


def test_rescore_refuses_a_file_that_is_not_a_result(tmp_path, capsys):
    bad = tmp_path / "result.json"
    bad.write_text("{not json")
    with pytest.raises(SystemExit) as stop:
        harness.main(["--rescore", str(bad)])
    assert stop.value.code == 2
    assert "cannot read a harness result" in capsys.readouterr().err


def test_rescore_merges_runs(tmp_path, capsys):
    first = {"a": _row("loo_output_filter", ["output_pole"], 0.1, 1e-3, lag_s=3e-5)}
    later = {"b": _row("loo_output_filter", ["torquer_pole"], 0.1, 1e-3, lag_s=3e-5)}
    paths = []
    for i, records in enumerate((first, later)):
        paths.append(tmp_path / f"r{i}.json")
        paths[-1].write_text(json.dumps({"records": records}))
    assert harness.main(["--rescore", *map(str, paths)]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["score"]["findable_records"] == 2
    assert printed["score"]["findable_credible_and_right"] == 1


def test_rescore_refuses_a_record_given_twice_with_other_results(tmp_path, capsys):
    paths = []
    for i, value in enumerate((0.1, 0.2)):
        records = {"a": _row("loo_output_filter", ["output_pole"], value, 1e-3, lag_s=3e-5)}
        paths.append(tmp_path / f"r{i}.json")
        paths[-1].write_text(json.dumps({"records": records}))
    with pytest.raises(SystemExit) as stop:
        harness.main(["--rescore", *map(str, paths)])
    assert stop.value.code == 2
    assert "record a is in an earlier file" in capsys.readouterr().err
