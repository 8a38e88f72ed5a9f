"""A known delay of the input channels (`StepData.input_delay`, `accel-jax diagnose
--input-delay`): the change times' priors centred on it, the output's lateness judged beyond
it, and bad or misplaced delays refused. The record comes from the independent truth
simulator (studies/step_truth.py, written without the diagnosis code)."""

import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from accel_jax import (
    DataError,
    NoiseData,
    NominalDevice,
    StepData,
    with_input_delay,
    write_csv,
)
from accel_jax.cli import main
from accel_jax.diagnose import diagnose_many, diagnose_step_set
from accel_jax.diagnose.step.fit import DELAY_LIMIT
from accel_jax.diagnose.step.nuisance import COLUMN_PHASE

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "studies"))
import step_truth  # noqa: E402

# Record 227 of the measured-input harness's draw (studies/measured_input_harness.py, 100
# per class, seed 2027): an output filter of 7.77 µs (3.9 samples at 0.5 MHz). Its input
# channel, drawn by the harness's stream, is 2.49 samples late with a 0.45-sample anti-alias
# lag: the fitted delay takes up the filter, and the record read `none` in the harness.
TRUTH_227 = {
    "effect": "output_filter",
    "device": {
        "J": 7.031208010872156e-09,
        "mu": 2.619619266094817e-05,
        "c": 0.0003060274065201262,
        "k_dm": 9.130850587559585e-06,
        "k_dp": 248972.63263584487,
        "k_y": 8.60877797711041,
        "test_gain": 1.008602006080645,
    },
    "levels_V": [1.2291513314451217, 2.4583026628902434, -2.4583026628902434,
                 2.4583026628902434, -1.2291513314451217, 0.0, -1.2291513314451217],
    "change_times_s": [0.001358104315448065, 0.002677664752035252, 0.004439005447691314,
                       0.00621593488017243, 0.008136068859229375, 0.009799429454229762],
    "rate": 500000.0,
    "noise_V": 0.0019790692161469384,
    "adc_step_V": 0.001220703125,
    "output_offset_V": 0.0009459853160088891,
    "output_sign": 1.0,
    "moment_Nm": 1.8054929700444286e-06,
    "start": 0.0005795177440360089,
    "start_level_V": 1.2291513314451217,
    "u_max_V": 2.4583026628902434,
    "lag_s": 7.766805848267942e-06,
}
NOMINAL = NominalDevice.reference(torquer_time_constant=0.0, filter_time_constant=0.0)


@pytest.fixture(scope="module")
def record_227():
    rng = np.random.default_rng([2027, 1, 227])  # the harness's stream of that record
    t, u, y, _ = step_truth.make(TRUTH_227, rng)
    column, channel = step_truth.measure_input(u, TRUTH_227["rate"], rng)
    assert channel["delay_samples"] == pytest.approx(2.488, abs=1e-3)
    return StepData(t, column, y), channel["delay_s"] + channel["antialias_tau_s"]


@pytest.mark.slow
def test_a_lag_hidden_behind_the_input_channels_delay_shows_once_the_delay_is_given(record_227):
    data, delay = record_227
    unknown, given = diagnose_many(
        [data, with_input_delay(data, delay)], NOMINAL, recommend=False
    )
    # Unknown delay: the fitted delay takes up the filter (the output on time, −0.5 sample).
    assert unknown.verdict == "none", unknown.reason
    assert unknown.refit["nuisance_test"]["known_input_delay_samples"] is None
    # … and says what that `none` cannot rule out, and how to rule it out.
    assert any("would hide in it" in n and "--input-delay" in n for n in unknown.notes)
    # … with the largest lag it cannot rule out, which covers the truth's filter: the
    # fitted delay is the channel's (≤ DELAY_LIMIT samples, and the sampling phase) less
    # the lag.
    hidden = unknown.refit["nuisance_test"]
    assert hidden["hidden_lag_s"] == pytest.approx(
        (DELAY_LIMIT + COLUMN_PHASE - hidden["input_delay_samples"]) / TRUTH_227["rate"]
    )
    assert hidden["hidden_lag_s"] > TRUTH_227["lag_s"]
    assert f"{hidden['hidden_lag_s'] * 1e6:.3g} µs" in unknown.summary()
    # Given: the output follows the drive ~3.5 samples later than the channel's delay
    # allows, and the filter model, fitted with the change times at their prior, recovers
    # the truth's time constant.
    test = given.refit["nuisance_test"]
    assert test["known_input_delay_samples"] == pytest.approx(delay * TRUTH_227["rate"])
    assert test["strained"] and test["largest"] == "input_delay", test
    assert given.verdict != "none"
    assert "later than its column shows" in given.reason and "(given: +2.94)" in given.summary()
    filtered = next(e for e in given.ranking if e["effect"] == "output_filter")
    assert filtered["params"]["filter_time_constant_s"] == pytest.approx(
        TRUTH_227["lag_s"], rel=0.05
    )


def test_a_bad_or_misplaced_input_delay_is_refused(record_227, tmp_path):
    data, _ = record_227
    assert with_input_delay(data, None) is data
    assert with_input_delay(data, 4e-6).input_delay == 4e-6
    for bad in (float("nan"), 1e-3, "soon"):
        with pytest.raises(DataError, match="input delay"):
            with_input_delay(data, bad)
    with pytest.raises(DataError, match="only for step records"):
        with_input_delay(NoiseData(t=np.arange(256) / 100.0, a_out=np.zeros(256)), 1e-6)
    # A set's joint fit takes the change times as the columns show them.
    with pytest.raises(DataError, match="diagnose that record alone"):
        diagnose_step_set([data, with_input_delay(data, 4e-6)], NOMINAL, names=["a", "b"])
    # The command line: one line and exit status 1, nothing written.
    path = write_csv(tmp_path / "r.csv", data)
    out = tmp_path / "d.json"
    result = CliRunner().invoke(
        main, ["diagnose", str(path), "--input-delay", "nan", "--json", str(out)]
    )
    assert result.exit_code == 1 and "input delay nan s must be a finite" in result.output
    assert len(result.output.strip().splitlines()) == 1 and not out.exists()
