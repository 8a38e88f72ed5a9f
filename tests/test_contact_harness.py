"""studies/contact_harness.py's draw and scoring, on rows made by hand (the blind diagnosis
of its records is run on its own, by hand: ~1 min of a core per record)."""

import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "studies"))
import contact_harness as harness  # noqa: E402


def _truth(effect, kappa=50.0, zeta_c=0.5, sides=("high",), against=False):
    return {"effect": effect, "kappa": kappa, "zeta_c": zeta_c, "sides_reached": list(sides),
            "start_against_stop": against}


def _row(verdict, tied=(), **contact):
    row = {"verdict": verdict, "tied": list(tied)}
    if contact:
        row["stop_contact"] = {"params": contact}
    return row


def test_named_strictly_and_as_the_stop_family_over_every_record():
    truths = {
        "a": _truth("stop_compliant", kappa=20.0),
        "b": _truth("stop_compliant", kappa=500.0),
        "c": _truth("stop_compliant", kappa=2000.0, zeta_c=1.5, against=True),
        "d": _truth("stop_compliant", kappa=30.0),
        "e": _truth("stop_compliant", sides=()),  # the contact never pushed
        "f": _truth("stop_compliant", kappa=40.0),
    }
    rows = {
        "a": _row("stop_contact", contact_stiffness_over_loop=40.0, contact_damping_ratio=0.25),
        "b": _row("cannot_tell", tied=("stop_saturation", "stop_contact")),
        "c": _row("stop_saturation"),  # the stiff, damped limit: the family, not the name
        "d": _row("none"),  # the contact acted: false assurance
        "e": _row("none"),  # nothing acted: counted apart, no false assurance
        "f": {"refused": "no plateaus"},  # a refusal is a miss, not a dropped record
    }
    s = harness.score(truths, rows)["stop_compliant"]
    assert s["records"] == 6 and s["stop_absent"] == 1
    assert s["named"] == {"n": 5, "count": 2, "share": 0.4}
    assert s["family"] == {"n": 5, "count": 3, "share": 0.6}
    assert s["false_assurance"] == 1
    assert s["by_kappa"]["1000-3000"]["family"]["count"] == 1
    assert s["by_kappa"]["1000-3000"]["named"]["count"] == 0
    assert s["starting_against_stop"]["named"] == {"n": 1, "count": 0, "share": 0.0}
    assert s["fitted_over_true"] == {"records": 1, "kappa_median": 2.0, "zeta_c_median": 0.5}
    assert s["verdicts"]["refused"] == 1


def test_false_alarms_missing_rows_and_the_totals():
    truths = {"n0": _truth("none"), "n1": _truth("none"), "o": _truth("stop_one_sided")}
    rows = {"n0": _row("none"), "n1": _row("disturbance_drift")}  # "o" returned nothing
    s = harness.score(truths, rows)
    assert s["none"]["false_alarms"] == {"n": 2, "count": 1, "share": 0.5}
    assert s["stop_one_sided"]["named"]["count"] == 0 and s["stop_one_sided"]["records"] == 1
    assert s["false_assurance"] == 0
    assert s["lowest_named"] == ("stop_one_sided", 0.0)


def test_a_record_is_drawn_the_same_in_every_shard(tmp_path):
    names = harness.record_names(3, ("none", "stop_one_sided"))
    assert names[3] == "stop_one_sided_0000" and len(names) == 6
    one, _, attempt = harness.draw("stop_one_sided", 5, 1)
    again, _, _ = harness.draw("stop_one_sided", 5, 1)
    assert one == again and attempt >= 0
    assert one["effect"] == "stop_one_sided" and 10 <= one["kappa"] <= 3000
    truths = harness.write_records(["stop_one_sided_0001"], 5, tmp_path)
    assert (tmp_path / "stop_one_sided_0001.csv").exists()
    assert truths["stop_one_sided_0001"]["kappa"] == one["kappa"]


def test_merge_joins_shards_and_says_which_are_missing(tmp_path, capsys):
    def shard(k, n=3):
        name = f"none_{k:04d}"
        return {"assumptions": {"per_class": 3, "classes": ["none"], "seed": 1,
                                "shard": [k, n], "shard_count": n, "commit": "abc"},
                "truths": {name: _truth("none")}, "rows": {name: _row("none")}, "seconds": 2.0}

    pair = harness.merge([shard(0), shard(1)])
    assert pair["assumptions"]["missing_shards"] == [2] and not pair["assumptions"]["complete"]
    whole = harness.merge([pair, shard(2)])
    assert whole["assumptions"]["complete"] and whole["score"]["none"]["records"] == 3
    with pytest.raises(ValueError, match="overlap"):
        harness.merge([pair, shard(1)])
    other = shard(2)
    other["assumptions"]["seed"] = 2
    with pytest.raises(ValueError, match="seed"):
        harness.merge([pair, other])
    bad = tmp_path / "r.json"
    bad.write_text("{}")
    assert harness.main(["--merge", str(bad), "--out", str(tmp_path / "o")]) == 1
    assert "cannot merge" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()
    good = tmp_path / "p.json"
    good.write_text(json.dumps(pair))
    assert harness.main(["--merge", str(good), "--out", str(tmp_path / "m")]) == 0
