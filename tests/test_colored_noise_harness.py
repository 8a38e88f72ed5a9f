"""studies/colored_noise_harness.py's scoring, on rows made by hand (the blind run itself
takes ~15 s of a core per record and is run on its own)."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "studies"))
import colored_noise_harness as harness  # noqa: E402


def _row(verdict, lb=20.0, p=0.5, significant=True, consistent=True, tied=()):
    row = {"verdict": verdict, "tied": list(tied)}
    for key in ("noise", "moment"):
        row.update({
            key + "_evidence": 10.0,
            key + "_ljung_box": lb,
            key + "_ljung_box_p": p,
            key + "_significant": significant,
            key + "_variance_consistent": consistent,
            key + "_fit_failed": False,
        })
    return row


def test_score_counts_per_class_and_strength_band():
    truths = {
        "a": {"effect": "output_gm", "ratio": 1.5},
        "b": {"effect": "output_gm", "ratio": 12.0},
        "c": {"effect": "moment_gm", "ratio": 5.0},
        "e": {"effect": "moment_gm", "ratio": 2.0},
        "f": {"effect": "moment_gm", "ratio": 15.0},
        "d": {"effect": "none", "ratio": None},
    }
    rows = {
        "a": _row("colored_noise"),
        "b": _row("unexplained", lb=60.0, p=1e-5),
        "c": _row("unexplained", lb=150.0, p=1e-20, consistent=False),
        # A tie between the two places names the truth; the wrong place only credits noise.
        "e": _row("cannot_tell", tied=("colored_noise", "moment_noise")),
        "f": _row("colored_noise"),
        "d": _row("colored_noise"),
    }
    score = harness.score(truths, rows)
    out = score["output_gm"]
    assert out["verdicts"] == {"colored_noise": 1, "unexplained": 1}
    assert out["right_share"] == 0.5
    assert out["by_ratio"]["1-3"] == {"n": 1, "right": 1, "noise_credited": 1}
    assert out["by_ratio"]["8-20"] == {"n": 1, "right": 0, "noise_credited": 0}
    assert out["noise_white_held_out"] == 1
    moment = score["moment_gm"]
    assert moment["right"] == "moment_noise"
    assert moment["right_share"] == 1 / 3
    assert moment["noise_credited_share"] == 2 / 3
    assert moment["by_ratio"]["8-20"] == {"n": 1, "right": 0, "noise_credited": 1}
    assert moment["noise_variance_consistent"] == 2
    assert score["none"]["right"] == "none" and score["none"]["right_share"] == 0.0


def test_false_assurance_false_alarms_and_an_empty_tie():
    truths = {
        "a": {"effect": "output_gm", "ratio": 4.0},
        "b": {"effect": "output_gm", "ratio": 2.0},
        "c": {"effect": "none", "ratio": None},
        "d": {"effect": "none", "ratio": None},
    }
    rows = {
        "a": _row("none"),  # a coloured noise read as nothing missing
        "b": _row("cannot_tell", tied=()),  # a tie naming nothing credits no noise
        "c": _row("none"),
        "d": _row("disturbance_drift"),
    }
    score = harness.score(truths, rows)
    assert score["output_gm"]["false_assurance"] == 1
    assert score["output_gm"]["noise_credited_share"] == 0.0
    assert score["none"]["false_alarms"] == {"n": 2, "count": 1}
