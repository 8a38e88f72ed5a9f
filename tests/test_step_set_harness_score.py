"""The step-set harness's scoring (studies/step_set_harness.py `_score`) on a synthetic
score: every rate it reports is counted from truths and verdicts, so a miscount would change
the issue-20 figures without any diagnosis changing. No diagnosis runs here."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "studies"))

import step_set_harness as harness  # noqa: E402


def _truth(effect, lag):
    return {"effect": effect, "lag_s": lag}


def test_the_harness_scores_named_confused_and_false_alarm_sets_from_truth():
    truths = [
        _truth("none", None),
        _truth("torquer_lag", 3e-5),
        _truth("output_filter", 2e-5),
        _truth("none", None),
        _truth("torquer_lag", 1.01e-5),
        _truth("output_filter", 4e-5),
    ]
    verdicts = ["none", "torquer_lag", "torquer_lag", "unexplained", "none", "output_filter"]
    sets = {f"set_{i:04d}": {"verdict": v} for i, v in enumerate(verdicts)}
    singles = {
        "set_0001": {"verdict": "cannot_tell", "next_experiment": [{"description": "stops"}]},
        "set_0002": {"verdict": "torquer_lag", "next_experiment": []},
        "set_0003": {"verdict": "none", "next_experiment": []},
    }
    follows = {"set_0001": {"verdict": "torquer_lag"}}
    result = harness._score(truths, sets, singles, follows, {"set_0001": "torquer_lag"}, [1, 2, 3])

    s = result["sets"]
    assert (s["strictly_named"]["k"], s["strictly_named"]["n"]) == (2, 4)
    assert (s["lag_confusions"]["k"], s["lag_confusions"]["n"]) == (1, 4)
    assert (s["false_alarms"]["k"], s["false_alarms"]["n"]) == (1, 2)
    assert s["confusion"]["torquer_lag"] == {"torquer_lag": 1, "none": 1}
    single = result["single_small_steps"]
    assert single["lag_confusions"] == 1  # output_filter truth named torquer_lag
    assert (single["cannot_tell"], single["with_next_experiment"]) == (1, 1)
    assert single["ties_resolved_by_the_recommended_record"]["k"] == 1
    # the drawn lag travels with each set, so a lag device diagnosed `none` can be checked
    assert result["per_set"]["set_0004"] == {
        "truth": "torquer_lag",
        "truth_lag_s": 1.01e-5,
        "verdict": "none",
    }
