"""The independent truth simulator's test-stand additions (studies/step_truth.py): the
measured input channel (`measure_input`: delay, anti-alias filter, noise, ADC grid, relay
spikes, offset and drift), the calibration sequences (`prbs_levels`, `sweep_column`,
`sweep_levels`) and the records that start with the pendulum resting on a stop
(`Record.start` "on_stop_high"/"on_stop_low", `draw_truth_on_stop`). NumPy/SciPy only."""

import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "studies"))
import step_truth  # noqa: E402


def _steps_column(n=400, changes=(50, 120, 260, 300), levels=(0.0, 1.5, -0.75, 2.0, 0.25)):
    """A sampled piecewise-constant column [V]: levels[j] from sample changes[j − 1]."""
    column = np.full(n, levels[0])
    for k, level in zip(changes, levels[1:], strict=True):
        column[k:] = level
    return column


_QUIET = {"noise_V": 0.0, "lsb_V": 0.0, "spikes": [], "drift_V": 0.0, "offset_V": 0.0}


def test_measure_input_deterministic_is_the_column_one_sample_late():
    column = _steps_column()
    measured, info = step_truth.measure_input(
        column,
        1e6,
        np.random.default_rng(0),
        delay_samples=1,
        antialias=0.0,
        change_phase=0.0,
        **_QUIET,
    )
    assert measured[0] == column[0]
    np.testing.assert_array_equal(measured[1:], column[:-1])
    assert info["change_index"] == [50, 120, 260, 300]
    assert info["delay_samples"] == 1.0 and info["delay_s"] == pytest.approx(1e-6)
    json.dumps(info)  # JSON-able


def test_measure_input_filter_is_exact_for_an_off_grid_step():
    column = _steps_column(n=40, changes=(10,), levels=(0.0, 1.0))
    tau, phase, delay = 0.6, 0.3, 1.25
    measured, _ = step_truth.measure_input(
        column,
        1e6,
        np.random.default_rng(1),
        delay_samples=delay,
        antialias=tau,
        change_phase=phase,
        **_QUIET,
    )
    k = np.arange(40)
    since = k - delay - (10 - phase)
    expected = np.where(since >= 0, 1 - np.exp(-np.clip(since, 0, None) / tau), 0.0)
    np.testing.assert_allclose(measured, expected, atol=1e-15)


def test_measure_input_noise_level_away_from_changes():
    n = 5000
    column = _steps_column(n=n, changes=(1000, 2500, 4000), levels=(0.0, 2.0, -1.0, 0.5))
    sigma = 8e-4
    measured, info = step_truth.measure_input(
        column, 1e6, np.random.default_rng(2), noise_V=sigma, lsb_V=0.0, spikes=[]
    )
    # Away from the changes (10 samples ≥ 10 filter time constants after each delayed
    # change) the channel is the level, the offset and the drift ramp, plus the noise.
    delay = int(np.ceil(info["delay_samples"]))
    level = np.concatenate([np.full(delay, column[0]), column[: n - delay]])
    near = np.zeros(n, bool)
    for k in info["change_index"]:
        near[k - 1 : k + delay + 12] = True
    ramp = np.arange(n) / (n - 1)
    residual = measured - level - info["offset_V"] - info["drift_V"] * ramp
    assert residual[~near].std() == pytest.approx(sigma, rel=0.2)
    assert abs(residual[~near].mean()) < 5 * sigma / np.sqrt((~near).sum())


def test_measure_input_quantisation_on_the_lsb_grid_offset_included():
    column = _steps_column()
    lsb = 4.7e-4
    measured, info = step_truth.measure_input(
        column, 1e6, np.random.default_rng(3), lsb_V=lsb, offset_V=1.31e-3
    )
    steps = measured / lsb
    np.testing.assert_allclose(steps, np.round(steps), rtol=0, atol=1e-9)
    assert info["lsb_V"] == lsb and info["offset_V"] == 1.31e-3
    # A drawn world with an ADC step: also on its grid.
    for seed in range(10):
        measured, info = step_truth.measure_input(column, 1e6, np.random.default_rng(seed))
        if info["lsb_V"] > 0:
            steps = measured / info["lsb_V"]
            np.testing.assert_allclose(steps, np.round(steps), rtol=0, atol=1e-9)


def test_measure_input_spikes_right_after_the_changes():
    column = _steps_column()
    given = [(0, 2, 0.03), {"change": 2, "samples": 1, "amplitude_V": -0.02}]
    common = {"delay_samples": 1, "antialias": 0.0, "change_phase": 0.0}
    quiet = {key: value for key, value in _QUIET.items() if key != "spikes"}
    with_spikes, info = step_truth.measure_input(
        column, 1e6, np.random.default_rng(4), spikes=given, **common, **quiet
    )
    without, _ = step_truth.measure_input(
        column, 1e6, np.random.default_rng(4), spikes=[], **common, **quiet
    )
    spike = with_spikes - without
    expected = np.zeros(column.size)
    expected[51:53] = 0.03  # change 0 at sample 50, seen one sample late
    expected[261] = -0.02  # change 2 at sample 260
    np.testing.assert_allclose(spike, expected, atol=1e-15)
    assert info["spikes"][1] == {"change": 2, "samples": 1, "amplitude_V": -0.02}

    # Drawn spikes (same rng: everything else equal) sit on the first 1–2 samples at or
    # after each delayed change, with 5–50 mV.
    for seed in range(5):
        drawn, info = step_truth.measure_input(
            column, 1e6, np.random.default_rng(seed), noise_V=0.0, lsb_V=0.0
        )
        bare, _ = step_truth.measure_input(
            column, 1e6, np.random.default_rng(seed), noise_V=0.0, lsb_V=0.0, spikes=[]
        )
        spike = drawn - bare
        expected_at = np.zeros(column.size, bool)
        for s in info["spikes"]:
            j = s["change"]
            delayed = info["change_index"][j] - info["change_phase"][j] + info["delay_samples"]
            first = int(np.ceil(delayed - 1e-9))
            assert 0 <= first - delayed < 1
            assert 5e-3 <= abs(s["amplitude_V"]) <= 5e-2 and s["samples"] in (1, 2)
            np.testing.assert_allclose(spike[first : first + s["samples"]], s["amplitude_V"])
            expected_at[first : first + s["samples"]] = True
        assert np.all(spike[~expected_at] == 0)


def test_measure_input_draws_do_not_depend_on_what_is_given():
    column = _steps_column()
    _, drawn = step_truth.measure_input(column, 1e6, np.random.default_rng(5))
    _, partly = step_truth.measure_input(column, 1e6, np.random.default_rng(5), noise_V=1e-3)
    assert {k: v for k, v in drawn.items() if k != "noise_V"} == {
        k: v for k, v in partly.items() if k != "noise_V"
    }
    assert drawn["delay_samples"] - int(drawn["delay_samples"]) < 1
    assert int(drawn["delay_samples"]) in (0, 1, 2)
    assert 0.2 <= drawn["antialias_tau_samples"] <= 1.0
    assert 3e-4 <= drawn["noise_V"] <= 1.5e-3
    assert abs(drawn["offset_V"]) <= 2e-3 and abs(drawn["drift_V"]) <= 5e-4


def test_prbs_levels():
    rng = np.random.default_rng(6)
    min_bit = 1e-4
    levels, times = step_truth.prbs_levels(
        rng, n_changes=200, duration_s=0.1, low_V=-1.0, high_V=2.0, min_bit_s=min_bit
    )
    times = np.asarray(times)
    assert times.size >= 200 and len(levels) == times.size + 1
    assert set(levels) == {-1.0, 2.0}
    assert all(a != b for a, b in zip(levels[:-1], levels[1:], strict=True))
    plateaus = np.diff(np.concatenate([[0.0], times, [0.1]]))
    assert plateaus.min() >= min_bit
    bit = np.diff(times).min()  # the bit time: every plateau a whole number of bits
    np.testing.assert_allclose(np.diff(times) / bit, np.round(np.diff(times) / bit), atol=1e-6)
    # Off any sample grid of the rates in use.
    for rate in step_truth.RATES:
        assert np.all(np.abs(times * rate - np.round(times * rate)) > 1e-9)
    with pytest.raises(ValueError):
        step_truth.prbs_levels(
            rng, n_changes=200, duration_s=0.01, low_V=0.0, high_V=1.0, min_bit_s=min_bit
        )


def test_sweep_has_no_plateaus():
    t = np.arange(20000) / 1e6
    column = step_truth.sweep_column(t, 100.0, 3000.0, 1.5)
    assert np.all(np.diff(column) != 0) and np.abs(column).max() <= 1.5
    assert column[0] == 0.0 and np.abs(column).max() > 1.49
    levels, times = step_truth.sweep_levels(100.0, 3000.0, 1.5, 20e-3, 50e3, dac_phase=0.37)
    assert len(levels) == len(times) + 1 and np.all(np.diff(times) > 0) and times[-1] < 20e-3
    u = np.asarray(levels)[np.searchsorted(times, t, side="right")]
    assert np.abs(u - column).max() < 2 * np.pi * 3000 * 1.5 / 50e3  # one DAC step


# --------------------------------------------------------------------------------------
# Records that start on a stop
# --------------------------------------------------------------------------------------

H_MAX = 1.9e-6


def _on_stop(start, levels, change_times, *, hold=None, n=3000, **device):
    dev = step_truth.Device(h_max=H_MAX, **device)
    rec = step_truth.Record(
        levels=np.asarray(levels, float),
        change_times=np.asarray(change_times, float),
        rate=1e6,
        n=n,
        output_offset=0.02,
        output_sign=-1.0,
        start=start,
        hold_level=hold,
    )
    t, u, y = step_truth.simulate(dev, rec, rng=np.random.default_rng(0))
    stop = dev.k_dp * dev.k_y * H_MAX * (1 if start == "on_stop_high" else -1)
    return t, u, y, -stop + 0.02  # the stop's output: output_sign · U_stop + offset


def test_start_on_stop_driven_off_by_the_first_level():
    # Held there by 6 V until t0; from t0, 1 V (settles at ≈ 1 V, inside ≈ 4 V stops).
    t, _, y, at_stop = _on_stop("on_stop_high", [1.0], [], hold=6.0)
    gap = abs(at_stop - (-1.0 + 0.02))
    assert y[0] == pytest.approx(at_stop, abs=1e-12)
    assert np.all(np.abs(y[:5] - at_stop) < 1e-3 * gap)  # from rest: quadratic departure
    assert np.abs(y[1000:] - at_stop).min() > 0.3 * gap  # left it
    t, _, y, at_stop = _on_stop("on_stop_low", [-0.5], [], hold=-6.0)
    assert y[0] == pytest.approx(at_stop, abs=1e-12) and at_stop > 0  # inverting recorder
    assert np.abs(y[1000:] - at_stop).min() > 0.3 * abs(at_stop - (0.5 + 0.02))


def test_start_on_stop_held_while_pressed():
    # The first level (6 V) itself presses it there: it stays until 1.0005 ms, then leaves.
    t, u, y, at_stop = _on_stop("on_stop_high", [6.0, 0.0], [1.0005e-3])
    held = t <= 1.0005e-3
    np.testing.assert_allclose(y[held], at_stop, rtol=0, atol=1e-12)
    assert np.abs(y[2000:] - at_stop).min() > 1.0
    # With a torquer lag the holding voltage's moment decays first: held for a while.
    t, _, y, at_stop = _on_stop("on_stop_high", [0.0], [], hold=6.0, T_dm=20e-6)
    on = np.flatnonzero(np.abs(y - at_stop) > 1e-12)
    assert y[0] == pytest.approx(at_stop, abs=1e-12) and 3 <= on[0] < 100


def test_start_on_stop_refuses_an_inconsistent_start():
    with pytest.raises(ValueError, match="does not press"):
        _on_stop("on_stop_high", [0.0], [], hold=1.0)
    with pytest.raises(ValueError, match="stops"):
        dev = step_truth.Device()
        rec = step_truth.Record(np.zeros(1), np.zeros(0), 1e6, 10, start="on_stop_low")
        step_truth.simulate(dev, rec, rng=np.random.default_rng(0))


def test_draw_truth_on_stop_and_make():
    truth = step_truth.draw_truth_on_stop(np.random.default_rng(11))
    reference = step_truth.draw_truth(np.random.default_rng(11), "none")
    assert set(reference) <= set(truth)
    assert truth["effect"] == step_truth.ON_STOP_EFFECT
    assert truth["start"] in ("on_stop_high", "on_stop_low")
    assert 1.8 <= truth["stop_over_u_max"] <= 2.3
    json.dumps(truth)
    t, u, y, noise = step_truth.make(truth, np.random.default_rng(12))
    d = truth["device"]
    gain = d["k_dp"] * d["k_y"] * step_truth.Device().l
    k_test = d["k_dm"] * gain / (d["c"] + d["k_dm"] * gain)
    stop = truth["stop_over_u_max"] * truth["u_max_V"] * k_test  # k_dp k_y h_max
    side = 1 if truth["start"] == "on_stop_high" else -1
    at_stop = truth["output_sign"] * side * stop + truth["output_offset_V"]
    clean = y - noise
    assert clean[0] == pytest.approx(at_stop, abs=1e-9)
    slack = 5 * truth["noise_V"] + truth["adc_step_V"]
    assert abs(y[0] - at_stop) < slack
    assert np.abs(clean - at_stop)[int(2e-3 * truth["rate"]) :].min() > 0.1 * stop
    # Off the starting stop, it never reaches either stop again.
    out = (clean - truth["output_offset_V"]) * truth["output_sign"]
    away = np.argmax(side * out < 0.5 * stop)
    assert away > 0 and np.abs(out[away:]).max() < stop


def test_draw_truth_held_on_stop_rests_on_it_until_the_first_change():
    """`draw_truth_on_stop(held=True)`: the record's first level presses the pendulum onto
    the stop, so the output sits at the stop voltage through the first segment and leaves
    it after the first change, never to return."""
    truth = step_truth.draw_truth_on_stop(np.random.default_rng(21), held=True)
    assert truth["effect"] == step_truth.ON_STOP_HELD_EFFECT
    assert truth["levels_V"][0] == truth["start_level_V"]
    json.dumps(truth)
    t, u, y, noise = step_truth.make(truth, np.random.default_rng(22))
    d = truth["device"]
    gain = d["k_dp"] * d["k_y"] * step_truth.Device().l
    k_test = d["k_dm"] * gain / (d["c"] + d["k_dm"] * gain)
    stop = truth["stop_over_u_max"] * truth["u_max_V"] * k_test
    side = 1 if truth["start"] == "on_stop_high" else -1
    at_stop = truth["output_sign"] * side * stop + truth["output_offset_V"]
    clean = y - noise
    first = int(np.searchsorted(t, truth["change_times_s"][0]))
    assert np.allclose(clean[:first], at_stop, atol=1e-9)
    out = (clean - truth["output_offset_V"]) * truth["output_sign"]
    later = first + int(2e-3 * truth["rate"])
    assert np.abs(out[later:]).max() < 0.9 * stop
