"""The signal-chain harness (studies/chain_noise_harness.py) and its truth
(studies/chain_truth.py): the truth's spectrum against Welch's estimate of its own records,
the model-free white level, the scoring on hand-made rows, and one blind record end to
end (the diagnosing child sees only the file)."""

import math
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import signal

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "studies"))
import chain_noise_harness as harness  # noqa: E402
import chain_truth  # noqa: E402


@pytest.mark.parametrize("kind", chain_truth.KINDS)
def test_the_truths_density_is_its_records(kind):
    # The truth's stated two-sided density against Welch's estimate of its own record
    # (quantisation, which `density` leaves out, is at most a quarter of the noise's σ:
    # an LSB²/12 floor under 0.6 % of the variance), in the band where both are well
    # above the record's smallest density.
    drawn = chain_truth.draw(7, kind)
    x, dt, truth = drawn["x"], drawn["dt"], drawn["truth"]
    f, p = signal.welch(x - x.mean(), 1 / dt, nperseg=1024)
    estimate = p / 2  # one-sided → two-sided
    stated = chain_truth.density(truth, f)
    band = (f > 0) & (f < 0.45 / dt) & (stated > 0.05 * stated.max())
    ratio = estimate[band] / stated[band]
    assert abs(np.median(ratio) - 1) < 0.1, (kind, np.median(ratio))


def test_the_flat_band_sigma_of_white_noise_is_its_sigma():
    x = 3e-3 * np.random.default_rng(0).normal(size=40000)
    assert harness.flat_band_sigma(x, 0.01) == pytest.approx(3e-3, rel=0.05)


def _truth(kind, **changes):
    truth = {
        "kind": kind, "lsb": 0.0, "order": 2, "f3dB_Hz": 20.0, "sensor_white_sigma": 1e-3,
        "after_white_sigma": 2e-4, "flat_band_sigma": 1.02e-3,
    }
    return {**truth, **changes}


def _row(effects, unexplained=False, **parameters):
    names = list(effects) + (["unexplained"] if unexplained else [])
    return {
        "verdict": "+".join(names) or "none", "effects": list(effects),
        "unexplained": unexplained, "parameters": {"white_sigma": 1e-3, **parameters},
    }


def test_scoring_a_butterworth_chain():
    band = {
        "corner_Hz": 21.0, "order": 2, "shape": "butterworth", "white_after_filter_sigma": 2.5e-4
    }
    rows = {
        "right": _row(["bandlimit"], bandlimit=band),
        # a quantisation companion counts only where the record was quantised
        "quantised": _row(["bandlimit", "quantization"], bandlimit=band),
        "companion": _row(["exp_cosine", "bandlimit"], bandlimit=band),
        "collapsed": _row(["bandlimit"], bandlimit=band, white_sigma=2e-11),
        "far": _row(["bandlimit"], bandlimit={**band, "corner_Hz": 30.0, "order": 1}),
    }
    truths = {name: _truth("butterworth") for name in rows}
    truths["quantised"]["lsb"] = 1e-4
    score = harness.score(truths, rows)["butterworth"]
    assert score["records"] == 5 and score["errors"] == 0
    assert score["bandlimit_alone"] == {"n": 5, "share": 0.8}
    assert score["of_those_order_right"] == {"n": 4, "share": 0.75}
    assert score["of_those_corner_within_10_percent"]["share"] == 0.75
    assert score["of_those_white_within_2"]["share"] == 0.75  # the collapsed one is not
    assert score["white_collapsed"]["share"] == pytest.approx(0.2)
    again = harness.score({"q": _truth("butterworth")}, {"q": rows["quantised"]})
    assert again["butterworth"]["bandlimit_alone"]["share"] == 0.0
    # the shape counts with the order: a Bessel low-pass of order 2 is not the Butterworth
    other = _row(["bandlimit"], bandlimit={**band, "shape": "bessel"})
    bessel = harness.score({"b": _truth("butterworth")}, {"b": other})
    assert bessel["butterworth"]["of_those_order_right"]["share"] == 0.0


def test_scoring_a_moving_average_by_its_samples():
    band = {"corner_Hz": 20.0, "order": None, "shape": "moving_average", "taps": 5}
    truths = {n: _truth("moving_average", order=5) for n in ("right", "wrong")}
    rows = {
        "right": _row(["bandlimit"], bandlimit=band),
        "wrong": _row(["bandlimit"], bandlimit={**band, "taps": 4}),
    }
    score = harness.score(truths, rows)["moving_average"]
    assert score["of_those_order_right"] == {"n": 2, "share": 0.5}


def test_scoring_white_records_and_errors():
    truths = {"a": _truth("white"), "b": _truth("white"), "c": _truth("white")}
    rows = {"a": _row([]), "b": _row([], unexplained=True), "c": {"error": "ValueError: x"}}
    score = harness.score(truths, rows)["white"]
    # An errored record stays in the denominator, as a failure (here a false alarm).
    assert score["errors"] == 1 and score["false_alarms"] == {"n": 3, "share": 2 / 3}
    assert harness.score({"d": _truth("white")}, {})["white"]["errors"] == 1  # no row
    band = {"corner_Hz": 21.0, "order": 2, "shape": "butterworth"}
    chains = {"a": _truth("butterworth"), "b": _truth("butterworth"), "c": _truth("butterworth")}
    rows = {"a": _row(["bandlimit"], bandlimit=band),
            "b": _row(["bandlimit"], bandlimit={**band, "corner_Hz": 30.0}),
            "c": {"error": "ValueError: x"}}
    chain = harness.score(chains, rows)["butterworth"]
    assert chain["bandlimit_alone"] == {"n": 3, "share": 2 / 3}
    assert chain["bandlimit_alone_corner_within_10_percent"] == {"n": 3, "share": 1 / 3}
    assert chain["white_within_2_of_flat_band"] == {"n": 3, "share": 2 / 3}


def test_one_blind_record_end_to_end(tmp_path):
    # The harness as a user runs it, one white record: the child process writes a row
    # for the file, and the scoring reads it.
    assert harness.main(["--per-kind", "1", "--kinds", "white", "--out", str(tmp_path)]) == 0
    import json

    result = json.loads((tmp_path / "result.json").read_text())
    (name, record), = result["records"].items()
    assert name == "white_0000" and record["found"]["verdict"]
    assert result["score"]["white"]["records"] == 1
    truth = record["truth"]
    assert math.isclose(truth["flat_band_sigma"], truth["sensor_white_sigma"], rel_tol=0.1)


def test_bad_arguments_are_refused(capsys):
    with pytest.raises(SystemExit):
        harness.main(["--kinds", "pink"])
    assert "unknown kind" in capsys.readouterr().err
