"""The measured-input harness spread over machines: shards of one draw, each record the same
whichever shard writes it, and the shards' results merged and scored together
(studies/measured_input_harness.py; the diagnoses themselves are not run here)."""

import json
import math
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "studies"))
import measured_input_harness as harness  # noqa: E402


def test_shards_partition_the_draw():
    shards = [harness.shard_indices(23, (k, 4)) for k in range(4)]
    joined = sorted(i for s in shards for i in s)
    assert joined == list(range(23))
    assert harness.shard_indices(5, (0, 1)) == [0, 1, 2, 3, 4]
    with pytest.raises(ValueError, match="0 ≤ k < n"):
        harness.shard_indices(5, (4, 4))


def test_a_record_is_the_same_whichever_shard_writes_it(tmp_path):
    truths = harness.draw(2, 5, ("none",))
    alone = harness.write_twins(truths, [1], tmp_path / "a", 5)
    both = harness.write_twins(truths, [0, 1], tmp_path / "b", 5)
    assert alone[0] == both[1]
    for twin in ("clean", "measured"):
        a = (tmp_path / "a" / twin / "0001.csv").read_bytes()
        assert a == (tmp_path / "b" / twin / "0001.csv").read_bytes()
    assert not (tmp_path / "a" / "clean" / "0000.csv").exists()


def _acts(truth):
    return None  # the stub truths here have no world to simulate: every effect acts


def _row(verdict, strained=False, hidden=0.0):
    return {"verdict": verdict, "tied": [], "fit_failed": [], "nuisance_strained": strained,
            "hidden_lag_samples": hidden}


def _shard_result(shard, rows, seed=7):
    truths = [{"effect": "none"}, {"effect": "torquer_lag", "lag_s": 1e-5, "rate": 1e6},
              {"effect": "none"}]
    return {
        "assumptions": {"truth": "t", "per_class": 2, "classes": ["none", "torquer_lag"],
                        "seed": seed, "prbs": 0, "shard": list(shard), "shard_count": 2,
                        "commit": "abc"},
        "score": harness.score(truths, rows, _acts),
        "prbs": None,
        "prbs_picked": [],
        "truths": truths,
        "channels": {k.split("/")[1]: {} for k in rows if k.startswith("clean/")},
        "rows": rows,
        "seconds": 1.5,
    }


def test_merged_shards_are_scored_together():
    a = _shard_result((0, 2), {
        "clean/0000": _row("none"), "measured/0000": _row("none", strained=True),
        "clean/0002": _row("none"), "measured/0002": _row("unexplained"),
    })
    b = _shard_result((1, 2), {"clean/0001": _row("none"), "measured/0001": _row("none")})
    assert a["score"]["records"] == 2 and b["score"]["records"] == 1
    merged = harness.merge([a, b], _acts)
    s = merged["score"]
    assert s["records"] == 3 and s["agreement"] == pytest.approx(2 / 3)
    assert s["false_assurance"] == 2  # the torquer-lag record read none in both twins
    assert s["nuisance_trips_on_measured_none"] == 1 and s["nuisance_trips_on_clean_none"] == 0
    assert merged["assumptions"]["merged_shards"] == [[0, 2], [1, 2]]
    assert merged["seconds"] == 3.0


def test_merge_refuses_shards_of_different_draws_or_overlapping_ones():
    rows = {"clean/0000": _row("none"), "measured/0000": _row("none")}
    with pytest.raises(ValueError, match="seed"):
        harness.merge([_shard_result((0, 2), rows), _shard_result((1, 2), {}, seed=8)], _acts)
    with pytest.raises(ValueError, match="overlap"):
        harness.merge([_shard_result((0, 2), rows), _shard_result((1, 2), rows)], _acts)


def test_the_command_line_refuses_a_bad_shard_and_a_bad_merge(tmp_path, capsys):
    with pytest.raises(SystemExit):
        harness.main(["--shard", "3/2"])
    assert "0 ≤ k < n" in capsys.readouterr().err
    bad = tmp_path / "r.json"
    bad.write_text("{}")
    assert harness.main(["--merge", str(bad), "--out", str(tmp_path / "o")]) == 1
    assert "cannot merge" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_records_picked_by_index_are_checked_and_never_merged_as_a_shard(tmp_path, capsys):
    assert harness.record_indices(30, [7, 3, 7]) == [3, 7]
    with pytest.raises(ValueError, match="records 0 to 29"):
        harness.record_indices(30, [30])
    out = tmp_path / "o"
    # 2 per class: records 0 … 2·11 − 1; one outside is refused before anything runs.
    assert harness.main(["--per-class", "2", "--records", "3", "22", "--out", str(out)]) == 1
    assert "--records 22: the draw has records 0 to 21" in capsys.readouterr().err
    assert not out.exists()
    with pytest.raises(SystemExit):
        harness.main(["--records", "3", "--shard", "1/2"])
    assert "one or the other" in capsys.readouterr().err
    picked = _shard_result((0, 1), {})
    picked["assumptions"]["records"] = [3, 7]
    with pytest.raises(ValueError, match="not a shard"):
        harness.merge([picked], _acts)


def test_twins_that_name_the_stop_family_agree():
    truths = [{"effect": "stop_saturation"}] * 2
    rows = {
        "clean/0000": _row("stop_saturation"), "measured/0000": _row("stop_contact"),
        "clean/0001": _row("stop_saturation"), "measured/0001": _row("unexplained"),
    }
    entry = harness.score(truths, rows, _acts)["per_class"]["stop_saturation"]
    assert (entry["records"], entry["agree"], entry["agree_exact"]) == (2, 1, 0)


def test_a_none_on_a_stop_the_record_never_reaches_is_not_false_assurance():
    """Record 367 of the 100-per-class draw (seed 2027): a stop at 1.08 of the largest small
    level's settled output, beyond every transient; the truth simulator's noise-free record
    with the stop equals the one without it, so its `none` is counted apart. The same world
    with its stop at 0.8 (reached) is false assurance."""
    truths = harness.draw(100, 2027)
    never = truths[367]
    assert never["effect"] == "stop_saturation" and never["stop_over_u_max"] > 1.05
    reached = {**never, "stop_over_u_max": 0.8}
    assert harness.effect_signal(never)["chi2"] == 0.0
    assert harness.effect_signal(reached)["chi2"] > 100 * harness.EFFECT_ABSENT_CHI2
    rows = {"clean/0000": _row("none"), "measured/0000": _row("none"),
            "clean/0001": _row("none"), "measured/0001": _row("stop_saturation")}
    s = harness.score([never, reached], rows)
    assert s["false_assurance"] == 1  # the reached stop's clean twin
    assert list(s["none_effect_absent"]) == ["0000"]
    assert s["none_effect_absent"]["0000"]["none_twins"] == 2


def test_a_none_within_the_lag_the_diagnosis_cannot_rule_out_is_counted_apart(tmp_path):
    """Record 263 of the 100-per-class draw: an output filter of 2.57 samples read `none` on
    its measured twin, whose input channel was 1.83 samples late (delay and anti-alias lag);
    the diagnosis said a loop lag up to 9.13 samples hides in the fitted delay. The same
    `none` on a lag beyond what it states is false assurance; rows from before the diagnosis
    stated it get the bound from their fitted delay."""
    filter_263 = {"effect": "output_filter", "lag_s": 5.135e-6, "rate": 5e5}
    longer = {**filter_263, "lag_s": 2e-5}  # 10 samples
    rows = {"clean/0000": _row("unexplained"), "measured/0000": _row("none", hidden=9.13),
            "clean/0001": _row("unexplained"), "measured/0001": _row("none", hidden=9.13)}
    s = harness.score([filter_263, longer], rows, _acts)
    assert s["false_assurance"] == 1 and s["within_beyond_channel"] is None
    assert list(s["none_lag_within_stated"]) == ["measured/0000"]
    assert s["none_lag_within_stated"]["measured/0000"]["lag_samples"] == pytest.approx(2.5675)
    # Against the true channel: 263's (1.30 samples late, 0.53 of anti-alias lag) leaves its
    # filter ambiguous; a channel without delay would not have hidden it.
    channel = {"delay_samples": 1.30, "antialias_tau_samples": 0.53}
    s = harness.score([filter_263], {k: rows[k] for k in ("clean/0000", "measured/0000")},
                      _acts, channels={"0": channel})
    within = s["none_lag_within_stated"]["measured/0000"]
    assert within["channel_ambiguity_samples"] == pytest.approx(1.83 + 1 + 2.25)
    assert s["within_beyond_channel"] == 0
    s = harness.score([{**filter_263, "lag_s": 1.4e-5}], {  # 7 samples
        "clean/0000": _row("unexplained"), "measured/0000": _row("none", hidden=9.13)
    }, _acts, channels={"0": {"delay_samples": 0.0, "antialias_tau_samples": 0.0}})
    assert s["false_assurance"] == 0 and s["within_beyond_channel"] == 1
    old = {"verdict": "none", "input_delay_samples": -0.13}
    assert harness.hidden_lag(old, measured=True) == pytest.approx(9.13)
    assert harness.hidden_lag(old, measured=False) == pytest.approx(1.13)
    assert harness.hidden_lag({**old, "input_delay_samples": 1.5}, measured=False) == 0.0
    # --rescore: the rows scored again by this commit's scoring, written whole.
    stale = {**_shard_result((0, 1), {}), "truths": [filter_263], "rows": {
        "clean/0000": _row("unexplained"), "measured/0000": {**old, "tied": [], "fit_failed": []}
    }}
    stale["score"]["false_assurance"] = 1
    path = tmp_path / "old.json"
    path.write_text(json.dumps(stale))
    assert harness.main(["--rescore", str(path), "--out", str(tmp_path / "new")]) == 0
    new = json.loads((tmp_path / "new" / "result.json").read_text())
    assert new["score"]["false_assurance"] == 0 and new["rows"] == stale["rows"]
    assert new["assumptions"]["commit"] == "abc" and "rescored_at" in new["assumptions"]


def test_a_compact_result_keeps_the_scores_and_each_channels_draws(tmp_path):
    truths = harness.draw(1, 5, ("none",))
    (channel,) = harness.write_twins(truths, [0], tmp_path, 5)
    rows = {"clean/0000": {**_row("none"), "notes": ["a"]}, "measured/0000": _row("none")}
    result = {**_shard_result((0, 1), rows), "channels": {"0": channel}}
    small = harness.compact(result)
    assert small["score"] == result["score"] and small["compact"]
    assert "notes" not in small["rows"]["clean/0000"] and "notes" in result["rows"]["clean/0000"]
    c = small["channels"]["0"]
    assert c["delay_samples"] == channel["delay_samples"] and "change_index" not in c
    assert c["spikes"] == len(channel["spikes"] or [])
    # Compact shards merged (the merge is no longer marked compact) compact again: the spike
    # count is kept (it raised "object of type 'int' has no len()").
    again = harness.compact({**small, "compact": False})
    assert again["channels"]["0"]["spikes"] == c["spikes"]


def test_prbs_twins_are_scored_on_their_own_world():
    """A PRBS twin's `none` is judged by what the effect changes in the PRBS world (its
    drive between ±U_max, `PRBS_LENGTH` times as long), not in the step record's."""
    truths = harness.draw(100, 2027)
    world, _ = harness.prbs_world(truths, 367, 2027)
    step_n = harness.step_truth.DURATION
    assert world["duration_s"] == pytest.approx(harness.PRBS_LENGTH * step_n)
    assert world["levels_V"] != truths[367]["levels_V"]
    # A noise effect's χ² is its expected energy over the record: 2.5 times the step's.
    noisy = next(i for i, t in enumerate(truths) if t["effect"] == "colored_noise")
    step_chi2 = harness.effect_signal(truths[noisy])["chi2"]
    prbs_chi2 = harness.effect_signal(harness.prbs_world(truths, noisy, 2027)[0])["chi2"]
    assert prbs_chi2 == pytest.approx(harness.PRBS_LENGTH * step_chi2, rel=1e-3)

    lag = next(i for i, t in enumerate(truths) if t["effect"] == "torquer_lag")
    asked = []

    def signal(w):  # the stop acts in no record, the lag in every one
        asked.append(w)
        return {"chi2": 0.0 if w["effect"] == "stop_saturation" else 50.0, "peak_sigma": 0.0}

    rows = {}
    for i in (367, lag):
        rows |= {f"clean/{i:04d}": _row("none"), f"prbs_clean/{i:04d}": _row("none"),
                 f"prbs_measured/{i:04d}": _row("stop_saturation" if i == 367 else "none")}
    out = harness.score_prbs(truths, rows, [367, lag], 2027, signal)
    assert out["false_assurance"] == 2  # the lag's two none twins
    assert list(out["none_effect_absent"]) == ["prbs_clean/0367"]
    assert all(w["duration_s"] == world["duration_s"] for w in asked) and len(asked) == 3
    assert (out["agree_clean"], out["agree_measured"]) == (2, 1)


def test_nested_fits_below_the_nominal_are_counted_on_the_objective_apart_from_the_flags():
    # A fit flagged by its reported ln L alone (objective not below: 0 or round-off) counts
    # in `nested_fit_failures` only; one whose objective ended below counts in both.
    truths = [{"effect": "none"}, {"effect": "none"}]
    flagged = {**_row("none"), "fit_failed": ["disturbance_drift"],
               "below_nominal": {"torquer_lag": 0.0, "disturbance_drift": 7.8e-10}}
    lost = {**_row("none"), "fit_failed": ["stop_saturation"],
            "below_nominal": {"stop_saturation": 12.5},
            "reported_below_nominal": {"stop_saturation": 900.0, "torquer_lag": 0.4}}
    # A fit reported at its no-effect value (`rescale.settle_at_no_effect`) is counted apart,
    # and the reported ln L below the nominal's read over the fits not flagged.
    settled = {**_row("none"), "at_no_effect": {"stop_saturation": 2661.0},
               "reported_below_nominal": {"stop_saturation": 0.0, "torquer_lag": 1.5}}
    rows = {"clean/0000": settled, "measured/0000": flagged,
            "clean/0001": _row("none"), "measured/0001": lost}
    s = harness.score(truths, rows, _acts)
    assert s["nested_fit_failures"] == 2 and s["rankings"] == 4
    assert s["nested_below_on_objective"] == 1
    assert s["largest_objective_below_nominal"] == 12.5
    assert s["settled_at_no_effect"] == 1 and s["largest_reported_below_nominal"] == 1.5


def test_a_none_on_a_start_on_stop_record_is_false_assurance_where_the_stop_acts_again():
    """An on-stop record leaves its stop at the first sample. Its `none` is counted apart
    only where the truth simulator's pendulum never reaches a stop again (`stop_contacts`,
    read from the simulator's own contact events, record by record); where it does, the
    stop acts within the record and the `none` is false assurance."""
    truths = harness.draw(100, 2027)
    on_stop = harness.step_truth.ON_STOP_EFFECT
    free = next(t for t in truths if t["effect"] == on_stop)
    assert harness.stop_contacts(free) == []  # leaves its stop at t0 and stays clear
    # The same world with its stops well inside the small steps' reach: hit again.
    struck = {**free, "stop_over_u_max": 0.7}
    hits = harness.stop_contacts(struck)
    assert hits and all(0 < h < harness.step_truth.DURATION for h in hits)
    rows = {"clean/0000": _row("none"), "measured/0000": _row("none"),
            "clean/0001": _row("none"), "measured/0001": _row("stop_saturation")}
    asked = []

    def contacts(truth):
        asked.append(truth["stop_over_u_max"])
        return hits if truth is struck else []

    s = harness.score([free, struck], rows, _acts, contacts=contacts)
    assert s["false_assurance"] == 1  # the struck record's clean twin
    assert s["start_on_stop_none"] == 2  # the free record's two twins, counted apart
    assert list(s["start_on_stop_stop_acts"]) == ["0001"]
    assert s["start_on_stop_stop_acts"]["0001"]["none_twins"] == 1
    assert len(asked) == 2  # asked once per record read none


def test_a_refused_measured_twin_disagrees_and_its_clean_twin_still_counts():
    truths = [{"effect": "torquer_lag", "lag_s": 1e-5, "rate": 1e6}, {"effect": "none"}]
    rows = {"clean/0000": _row("none", hidden=0.0), "measured/0000": {"refused": "no plateaus"},
            "clean/0001": _row("none", strained=True), "measured/0001": {"refused": "x"}}
    s = harness.score(truths, rows, _acts)
    assert s["refused_measured"] == 2 and s["agreement"] == 0.0
    assert s["false_assurance"] == 1  # the lag record's clean none (its lag 10 samples)
    assert s["nuisance_trips_on_clean_none"] == 1
    assert s["per_class"]["torquer_lag"]["none_clean"] == 1


def test_agreement_is_given_per_class_with_the_lowest():
    truths = [{"effect": "none"}] * 2 + [{"effect": "stop_saturation"}] * 2
    rows = {"clean/0000": _row("none"), "measured/0000": _row("none"),
            "clean/0001": _row("none"), "measured/0001": _row("none"),
            "clean/0002": _row("stop_saturation"), "measured/0002": _row("unexplained"),
            "clean/0003": _row("stop_saturation"), "measured/0003": _row("stop_contact")}
    s = harness.score(truths, rows, _acts)
    assert s["agreement"] == pytest.approx(3 / 4)
    assert s["agreement_by_class"] == {"none": 1.0, "stop_saturation": 0.5}
    assert s["agreement_lowest_class"] == ["stop_saturation", 0.5]


def test_merges_merge_again_and_say_which_shards_are_missing(tmp_path):
    def shard(k, n=3):
        i, verdict = f"{k:04d}", "torquer_lag" if k == 1 else "none"  # as its truth
        rows = {f"clean/{i}": _row(verdict), f"measured/{i}": _row(verdict)}
        result = _shard_result((k, n), rows)
        result["assumptions"]["shard_count"] = n
        return result

    pair = harness.merge([shard(0), shard(1)], _acts)
    assert pair["assumptions"]["complete"] is False
    assert pair["assumptions"]["missing_shards"] == [2]
    whole = harness.merge([pair, shard(2)], _acts)
    assert whole["assumptions"]["complete"] is True and whole["assumptions"]["missing_shards"] == []
    assert whole["assumptions"]["merged_shards"] == [[0, 3], [1, 3], [2, 3]]
    assert whole["score"]["records"] == 3
    with pytest.raises(ValueError, match="overlap"):
        harness.merge([pair, shard(1)], _acts)  # shard 1 alone and inside the merge
    other = shard(2)
    other["truths"] = [*other["truths"][:2], {"effect": "torquer_lag"}]
    with pytest.raises(ValueError, match="truths differ"):
        harness.merge([pair, other], _acts)
    # The same draw on another CPU (a float in its last bit) merges; a real change does not.
    for truth, merges in ((math.nextafter(2.5e-5, 1.0), True), (2.5e-5 * (1 + 1e-9), False)):
        a, b = shard(0), shard(1)
        a["truths"][0]["device"], b["truths"][0]["device"] = {"mu": 2.5e-5}, {"mu": truth}
        if merges:
            assert harness.merge([a, b], _acts)["truths"][0]["device"] == {"mu": 2.5e-5}
        else:
            with pytest.raises(ValueError, match="truths differ"):
                harness.merge([a, b], _acts)
    # From the command line: a merged file is accepted, and the partial state printed.
    files = []
    for name, result in (("p.json", pair), ("s.json", shard(2))):
        files.append(tmp_path / name)
        files[-1].write_text(json.dumps(result))
    assert harness.main(["--merge", *map(str, files), "--out", str(tmp_path / "o")]) == 0
    assert json.loads((tmp_path / "o" / "result.json").read_text())["assumptions"]["complete"]


def test_prbs_twins_name_the_stop_family_as_the_step_record_does():
    truths = [{"effect": "stop_saturation"}]
    rows = {"clean/0000": _row("stop_saturation"), "prbs_clean/0000": _row("stop_contact"),
            "prbs_measured/0000": _row("unexplained")}
    out = harness.score_prbs(truths, rows, [0], 7, _acts)
    assert (out["agree_clean"], out["agree_measured"]) == (1, 0)


def test_a_twin_that_names_one_effect_of_the_others_lag_tie_is_compatible_not_agreeing():
    """`compatible` beside the agreement: one twin's tie and the other naming one of its
    effects (either way round) is a finer answer; a different name, `none` against
    `unexplained`, or a tie of other effects is a contradiction."""

    def tie(*names):
        return {**_row("cannot_tell"), "tied": list(names)}

    truths = [{"effect": "output_filter", "lag_s": 4e-5, "rate": 5e5}] * 6
    rows = {
        "clean/0000": tie("output_filter", "torquer_lag"), "measured/0000": _row("output_filter"),
        "clean/0001": _row("torquer_lag"), "measured/0001": tie("torquer_lag", "output_filter"),
        "clean/0002": _row("torquer_lag"), "measured/0002": _row("output_filter"),
        "clean/0003": _row("unexplained"), "measured/0003": _row("unexplained"),
        "clean/0004": tie("output_filter", "torquer_lag"), "measured/0004": _row("unexplained"),
        "clean/0005": tie("stop_saturation", "torquer_lag"),
        "measured/0005": tie("output_filter", "torquer_lag"),
    }
    s = harness.score(truths, rows, _acts)
    entry = s["per_class"]["output_filter"]
    assert (entry["agree"], entry["compatible"]) == (1, 3)
    assert s["compatible"] == pytest.approx(3 / 6) and s["agreement"] == pytest.approx(1 / 6)
    assert s["compatible_by_class"] == {"output_filter": pytest.approx(0.5)}
    assert not harness.resolves(_row("none"), _row("unexplained"))


def test_discover_diagnoses_as_the_command_does_and_is_part_of_the_draw(
    tmp_path, monkeypatch, capsys
):
    """`--discover` reaches the blind child (its first argument: the records diagnosed with
    `discover=True`, as `accel-jax diagnose` by default), is stated in the assumptions, and
    shards diagnosed with and without it are not merged."""
    # The child itself, on a folder with no records: it takes the option and writes no row.
    (tmp_path / "empty").mkdir()
    assert harness.diagnose_blind([tmp_path / "empty"], discover=True) == {}
    calls = []

    def child(code, *args):
        calls.append(args)
        assert "discover=discover" in code
        return {f"{twin}/0000": _row("none") for twin in ("clean", "measured")}

    monkeypatch.setattr(harness, "run_blind", child)
    out = tmp_path / "o"
    options = ["--per-class", "1", "--records", "0", "--discover", "--out", str(out)]
    assert harness.main(options) == 0
    assert calls[0][0] == "--discover" and all(a != "--discover" for a in calls[0][1:])
    result = json.loads((out / "result.json").read_text())
    assert result["assumptions"]["discover"] is True
    with pytest.raises(SystemExit):
        harness.main(["--discover", "--rescore", str(out / "result.json")])
    assert "only score rows already made" in capsys.readouterr().err
    plain = _shard_result((0, 2), {})
    other = _shard_result((1, 2), {})
    other["assumptions"]["discover"] = True
    with pytest.raises(ValueError, match="differ in discover"):
        harness.merge([plain, other], _acts)
