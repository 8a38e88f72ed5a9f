"""The step diagnosis on records with compliant stops, made by an independent truth
simulator (`studies/contact_truth.py`: SciPy, spring-damper contacts as events, written
without the library's code): `stop_contact` named, its stiffness, damping and reached
clearance recovered, a stop on one side reported as reached on that side only; and the
effect's hooks are the nominal model at z = 0 (`test_simulate_sequence`)."""

import sys
from pathlib import Path

import numpy as np
import pytest

import accel_jax as aj
from accel_jax.diagnose import diagnose_step

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "studies"))
import contact_truth  # noqa: E402

NOMINAL = aj.NominalDevice.reference(torquer_time_constant=0.0, filter_time_constant=0.0)
"""The blind harnesses' nominal device (the truths have ideal lags)."""

CASES = (("stop_compliant", 16), ("stop_one_sided", 15))
"""(class, seed) of the two records, both drawn at 0.5 MHz (the cheapest rate): a
symmetric pair of compliant stops, the record starting pressed against one (κ = 805,
ζ_c = 0.23, in contact 20 % of the time), and one stop touched in overshoots (κ = 960,
ζ_c = 0.13, 0.7 % of the time)."""


def _truth(effect, seed):
    rng = np.random.default_rng(seed)
    truth = contact_truth.draw_truth(rng, effect)
    t, u, y, _ = contact_truth.make(truth, np.random.default_rng(rng.integers(1 << 30)))
    return truth, aj.StepData(t, u, y)


# Both tests on the worker of `step_cases`, whose records have this layout and include
# stop records: the compliant stops' programs are compiled there once.
pytestmark = pytest.mark.worker_of("step_cases")


@pytest.fixture(scope="module")
def diagnosed():
    truths, data = zip(*(_truth(*case) for case in CASES))
    return list(zip(truths, diagnose_step(list(data), NOMINAL, recommend=False)))


def _entry(result, name):
    return next(e for e in result.ranking if e["effect"] == name)


def _output_stop(truth, side):
    """The stop's output voltage [V] on the truth's `side` (+1: its upper stop), seen
    through the recorder's sign and offset."""
    stop = truth["stop_hi_V"] if side > 0 else truth["stop_lo_V"]
    return truth["output_sign"] * side * stop + truth["output_offset_V"]


def test_compliant_stops_are_named_with_their_stiffness_and_damping(diagnosed):
    for truth, result in diagnosed:
        assert result.verdict == "stop_contact", (truth["effect"], result.reason)
        entry = _entry(result, "stop_contact")
        assert not entry["fit_failed"] and entry["explains"]
        params = entry["params"]
        # The contact's law, recovered from the record alone (the truth draws κ over
        # 10–3000 and ζ_c over 0.05–2, log-uniform). The damping sets a bounce's
        # restitution, so every contact measures it; the stiffness only sets how long a
        # contact lasts and how deep it goes, so a record that touches a stop for a few
        # samples leaves κ near its prior's middle (a record touched for 0.2 % of its
        # samples, at 2 MHz: κ 293 for 1442), and the clearance then carries the
        # penetration a softer contact needs (1.3 % there).
        assert abs(np.log(params["contact_damping_ratio"] / truth["zeta_c"])) < np.log(1.5)
        if truth["contact_fraction"] > 0.05:
            assert abs(np.log(params["contact_stiffness_over_loop"] / truth["kappa"])) < np.log(1.5)
        # Each stop the record reached, where the truth put it (in output volts).
        for side in truth["sides_reached"]:
            sign = 1 if side == "high" else -1
            expected = _output_stop(truth, sign)
            fitted = params["stop_high_V"] if expected > 0 else params["stop_low_V"]
            assert fitted == pytest.approx(expected, rel=0.01 if truth["contact_fraction"] > 0.05 else 0.02)
        # The summary shows the named effect's fitted values, the contact's law included.
        line = next(x for x in result.summary().splitlines() if x.startswith("fitted "))
        assert line.startswith("fitted stop_contact: ")
        assert f"contact_damping_ratio = {params['contact_damping_ratio']:.4g}" in line
        assert "contact_stiffness_over_loop = " in line and "stop_high_V = " in line


def test_a_stop_on_one_side_says_nothing_about_the_other(diagnosed):
    truth, result = diagnosed[1]
    assert truth["effect"] == "stop_one_sided" and len(truth["sides_reached"]) == 1
    params = _entry(result, "stop_contact")["params"]
    side = 1 if truth["sides_reached"][0] == "high" else -1
    reached_high = _output_stop(truth, side) > 0
    assert params["stop_high_reached"] == float(reached_high)
    assert params["stop_low_reached"] == float(not reached_high)
    unreached = params["stop_low_V"] if reached_high else params["stop_high_V"]
    assert np.isinf(unreached)
