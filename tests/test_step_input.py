"""A step record's measured inputs (accel_jax/diagnose/step/inputs.py): plateaus and change
times read from a digitised test-voltage column — noise, ADC steps, relay spikes, a delay,
an anti-alias edge, a drift — and the refusal of an input without plateaus. The measured
columns come from the independent truth's input-channel model (`step_truth.measure_input`,
written without this code), and the diagnosis of a measured twin is checked against the
clean record's."""

import math
import re
import sys
from pathlib import Path

import numpy as np
import pytest

from accel_jax._data import DataError, StepData
from accel_jax.diagnose.step.inputs import read_input, read_inputs
from accel_jax.diagnose.step.record import quantisation_bias

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "studies"))
import step_truth  # noqa: E402

N = 12_000
CHANGES = (1500, 3100, 4800, 6500, 8000, 9900)
LEVELS = (0.0, 2.0, -2.0, 1.0, -1.0, 0.0, 2.0)


def _column():
    column = np.full(N, LEVELS[0])
    for k, level in zip(CHANGES, LEVELS[1:], strict=True):
        column[k:] = level
    return column


def test_an_exact_input_is_used_as_it_is():
    column = _column()
    reading = read_input(column)
    assert not reading.measured and reading.note == ""
    np.testing.assert_array_equal(reading.values, column)
    assert reading.change_index.tolist() == list(CHANGES)
    data = StepData(np.arange(N) * 1e-6, column, column)
    assert read_inputs(data).data is data  # nothing rebuilt, nothing noted


@pytest.mark.parametrize("seed", range(12))
def test_measured_inputs_give_their_plateaus_and_change_times(seed):
    rng = np.random.default_rng(seed)
    measured, info = step_truth.measure_input(_column(), 1e6, rng)
    reading = read_input(measured)
    assert reading.measured
    assert reading.levels.size == len(LEVELS), info
    # Each level: the true one plus the channel's offset (and its drift, ±0.5 mV at most),
    # within 5 standard errors and the drift.
    expected = np.asarray(LEVELS) + info["offset_V"]
    tolerance = 5 * reading.level_sigma + abs(info["drift_V"]) + 1e-12
    assert np.all(np.abs(reading.levels - expected) <= tolerance), (reading.levels, info)
    # Each change where the channel shows it: the delay, its fraction and the filter's
    # edge put it up to 4 samples after the command's sample.
    shift = reading.change_index - np.asarray(CHANGES)
    assert np.all((shift >= 0) & (shift <= 4)), (shift, info)
    assert "plateaus" in reading.note and "7 plateaus" in reading.note
    # The reconstruction is the plateaus held between the changes.
    starts = np.concatenate([[0], reading.change_index])
    for k, (a, b) in enumerate(zip(starts, np.append(starts[1:], N), strict=True)):
        assert np.all(reading.values[a:b] == reading.levels[k])


def test_a_prbs_sequence_of_hundreds_of_changes():
    rng = np.random.default_rng(3)
    rate, duration = 1e6, 0.03
    levels, times = step_truth.prbs_levels(
        rng, n_changes=240, duration_s=duration, low_V=-1.0, high_V=1.0, min_bit_s=20e-6
    )
    t = np.arange(int(duration * rate)) / rate
    column = np.asarray(levels)[np.searchsorted(times, t, side="right")]
    measured, _ = step_truth.measure_input(column, rate, rng)
    reading = read_input(measured)
    true_changes = np.flatnonzero(np.diff(column)) + 1
    assert reading.change_index.size == true_changes.size >= 240
    assert np.all(np.abs(reading.change_index - true_changes) <= 4)
    assert set(np.round(reading.levels).astype(int)) == {-1, 1}
    # A cap on the changes is said plainly.
    with pytest.raises(DataError, match="changes 2[0-9][0-9] times; the step diagnosis takes"):
        read_input(measured, max_changes=64)


@pytest.mark.parametrize(
    "name",
    ["chirp", "slow sine", "random walk", "white noise"],
)
def test_an_input_without_plateaus_is_refused_with_one_message(name):
    rng = np.random.default_rng(1)
    t = np.arange(N) * 1e-6
    signals = {
        "chirp": step_truth.sweep_column(t, 50.0, 2000.0, 2.0),
        "slow sine": 2.0 * np.sin(2 * np.pi * 20.0 * t),
        "random walk": np.cumsum(rng.standard_normal(N)) * 0.01,
        "white noise": rng.standard_normal(N),
    }
    x = signals[name] + 1e-3 * rng.standard_normal(N)
    message = "no change of the test input" if name == "white noise" else "u_test has no plateaus"
    with pytest.raises(DataError, match=message):
        read_input(x)


def test_read_inputs_rebuilds_the_record_and_notes_what_it_read():
    rng = np.random.default_rng(7)
    measured, _ = step_truth.measure_input(_column(), 1e6, rng)
    t = np.arange(N) * 1e-6
    out = rng.standard_normal(N)
    inputs = read_inputs(StepData(t, measured, out, notes=("kept",)))
    assert inputs.data.notes == ("kept",)
    np.testing.assert_array_equal(inputs.data.u_out, out)
    # Each plateau read on its own (a return to a commanded level is a new estimate).
    assert np.unique(inputs.data.u_test).size == len(LEVELS)
    assert len(inputs.notes) == 1 and inputs.notes[0].startswith("u_test read as a measurement")
    assert inputs.level_sigma > 0 and inputs.level_sigmas.size == len(LEVELS)


def _telegraph(rng, drift_V: float, plateaus: int = 120, length: int = 60, noise: float = 1e-3):
    """A measured two-level random telegraph (±1.5 V, `plateaus` plateaus of `length`
    samples) with white noise and a linear channel drift of `drift_V` over the record."""
    levels = np.where(rng.uniform(size=plateaus) < 0.5, -1.5, 1.5)
    levels[1::2] = -levels[::2][: levels[1::2].size]  # every plateau a change
    x = np.repeat(levels, length)
    n = x.size
    return x + drift_V * np.arange(n) / (n - 1) + noise * rng.normal(size=n)


def test_a_repeated_level_pins_the_input_channel_drift():
    """A level the sequence returns to measures the channel's drift across the record: on a
    telegraph of 120 short plateaus the drift nuisance's allowance (the largest drift the
    record cannot rule out) is far below what the short plateaus' own slopes allow, and a
    real drift of 3 mV is found to within a tenth."""
    from accel_jax.diagnose.step.inputs import DRIFT_SIGMAS, read_input

    rng = np.random.default_rng(3)
    still = read_input(_telegraph(rng, 0.0))
    n = 120 * 60
    within_sigma = 1e-3 / math.sqrt(120 * np.sum((np.arange(60) - 29.5) ** 2))
    within_allowance = DRIFT_SIGMAS * within_sigma * n  # [V over the record]
    allowance = float(np.ptp(still.level_drift))  # shape = allowance × (place − centre)
    assert allowance < 0.1 * within_allowance
    assert "drifts" not in still.note
    drifting = read_input(_telegraph(rng, 3e-3))
    found = re.search(r"drifts by ([+-][0-9.e-]+) V", drifting.note)
    assert found and abs(float(found.group(1)) - 3e-3) < 3e-4, drifting.note


def _exact_bias_rms(sigma, q=1.0, places=400):
    """RMS over x of E[Q(x + σn)] − x from the normal CDF (each code's probability), the
    grid's rounding to nearest: an independent route to the Fourier series."""
    from scipy import stats

    x = (np.arange(places) + 0.5) / places * q
    codes = np.arange(-12, 13)[:, None] * q
    if sigma == 0:
        mean = np.round(x / q) * q
    else:
        upper = stats.norm.cdf((codes + q / 2 - x) / sigma)
        lower = stats.norm.cdf((codes - q / 2 - x) / sigma)
        mean = np.sum(codes * (upper - lower), axis=0)
    return float(np.sqrt(np.mean((mean - x) ** 2)))


@pytest.mark.parametrize("ratio", [0.0, 0.15, 0.25, 0.4])
def test_a_coarse_output_grid_leaves_a_plateau_bias_the_levels_allow_for(ratio):
    """A measured input's levels are known to the output only to the bias its ADC leaves in
    a plateau's mean (harness record 91: σₐ/q = 0.25 read level 3 off by −4.3 standard errors,
    a false alarm on a `none` truth). `quantisation_bias` against the exact mean of the
    quantised noise, from a record of settled plateaus at random places on the grid."""
    rng = np.random.default_rng(7)
    q = 1e-3
    places = rng.uniform(0, 1, 200) * q
    y = np.round((np.repeat(places, 400) + ratio * q * rng.standard_normal(80_000)) / q) * q
    got = quantisation_bias(y, q, np.ones(y.size, dtype=bool))
    exact = _exact_bias_rms(ratio * q, q)
    if ratio >= 0.25:  # σₐ read from the differences: the bias to a few per cent
        assert got == pytest.approx(exact, rel=0.06)
    else:  # a finer noise than the grid hides: σₐ under-read, the bias over-stated, up to
        assert 0.97 * exact <= got <= 1.01 * q / math.sqrt(12)  # the sawtooth's q/√12
    if ratio == 0:
        assert got == pytest.approx(q / math.sqrt(12), rel=0.01)
    assert quantisation_bias(y, 0.0, np.ones(y.size, dtype=bool)) == 0.0
