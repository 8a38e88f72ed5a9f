"""Several step records of one device diagnosed together (accel_jax.diagnose.step.joint
and step.joint_verdict, issue 20): the joint fit on records of the independent SciPy truth simulator
(studies/step_truth.py), the expected evidence of a next experiment against a Monte Carlo of
2 ln B, acceleration records, and the CLI with several files."""

import dataclasses
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from accel_jax._data import DataError, NominalDevice, StepData, parse_csv, write_csv
from accel_jax.cli import main
from accel_jax.diagnose.step import design as sd
from accel_jax.diagnose.step import joint as sj
from accel_jax.diagnose.step import joint_verdict as sjv
from accel_jax.report.text.diagnose import diagnose_notes

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "studies"))
import step_truth  # noqa: E402

RATE = 500e3  # Hz: blocks of 5 samples (T/30 of the reference device)
NOMINAL = NominalDevice.reference()  # T_dm = T_f = 10 µs taken as known
# The device: off the reference by ~1σ of its prior, 2 % off in the pickoff, the test
# winding wired the other way.
DEVICE = {
    "J": 7.09e-9 * 1.03,
    "mu": 2.54e-5 * 0.97,
    "c": 3.02e-4 * 1.04,
    "k_dm": 9.23e-6 * 0.98,
    "k_dp": 2.5e5 * 1.02,
    "h_max": 1.9e-6 * 0.97,
    "T_dm": 1e-5,
    "T_f": 1e-5,
    "test_gain": -1.0,
}


def _record(
    seed, levels, *, device=None, accel=None, noise=4e-4, offset=0.02, n=4500, start="rest", **kw
):
    """A record of the truth simulator: changes off the sample grid, offset, ADC-free;
    `start` "rest" or the time [s] before the first sample at which its first level was
    switched on (from `start_level`, a keyword)."""
    rng = np.random.default_rng(seed)
    k = len(levels) if accel is None else len(accel)
    edges = (np.arange(1, k) / k * n + rng.uniform(0, 1, k - 1)) / RATE
    rec = step_truth.Record(
        levels=np.asarray(levels if accel is None else levels[:1], float),
        change_times=edges if accel is None else np.zeros(0),
        rate=RATE,
        n=n,
        noise=noise,
        output_offset=offset,
        moment=5e-7,
        accel_levels=None if accel is None else np.asarray(accel, float),
        accel_change_times=None if accel is None else edges,
        start=start,
        **kw,
    )
    dev = step_truth.Device(**{**DEVICE, **(device or {})})
    columns = step_truth.simulate(dev, rec, rng=rng)
    t, u, y = columns[:3]
    return StepData(t - t[0], u, y, a_in=columns[3] if len(columns) == 4 else None)


SMALL = [0.0, 2.0, -2.0, 1.0, -1.0, 0.0]
STOPS = [0.0, 5.5, -5.5, 5.5, 0.0]


@pytest.mark.parametrize("effect", ["torquer_lag", "output_filter"])
def test_stop_level_steps_separate_the_lags_and_the_joint_fit_recovers_the_device(effect):
    lag = 3e-5
    device = {"T_dm": lag} if effect == "torquer_lag" else {"T_f": lag}
    small = _record(1, SMALL, device=device)
    stops = _record(2, STOPS, device=device, offset=-0.01)
    alone = sjv.diagnose_step_set([small], NOMINAL, recommend=False)
    assert alone.verdict == "cannot_tell"  # the all-pole cubic: one small step cannot tell
    both = sjv.diagnose_step_set([small, stops], NOMINAL, recommend=False)
    assert both.verdict == effect, both.summary()
    by = {r["effect"]: r for r in both.ranking}
    other = "output_filter" if effect == "torquer_lag" else "torquer_lag"
    assert by[effect]["evidence"] - by[other]["evidence"] > 100
    assert [r["on_stops"] for r in both.records] == [False, True]
    assert all(r["at_floor"] for r in both.records)
    # Shared values recovered across the records.
    field = "torquer_time_constant" if effect == "torquer_lag" else "filter_time_constant"
    assert both.shared[field] == pytest.approx(lag, rel=0.05)
    truth_stop = DEVICE["k_dp"] * 8.5 * DEVICE["h_max"]
    assert both.shared["stop_voltage_V"] == pytest.approx(truth_stop, rel=2e-3)
    # eq. (11): k_dp·k_y from the stop level with the nominal h_max (3 % off by design).
    assert both.shared["pickoff_amplifier_gain_from_stops"] == pytest.approx(
        truth_stop / 1.9e-6, rel=1e-3
    )


def test_a_stop_record_that_starts_in_a_long_filters_transient_is_named_in_the_second_stage():
    # The stop-level record starts 0.5 ms after its first level was switched on from 2.8 V,
    # with a 50 µs output filter: the filter's state departs from the first-order start
    # rule (`initial_state`), so with that rule no candidate reaches the floor. The second
    # stage frees each record's initial lag states and names the filter.
    device = {"T_f": 5e-5}
    small = _record(1, SMALL, device=device)
    stops = _record(2, STOPS, device=device, offset=-0.01, start=5e-4, start_level=2.8)
    result = sjv.diagnose_step_set([small, stops], NOMINAL, recommend=False)
    assert result.verdict == "output_filter", result.summary()
    assert any("second stage" in note for note in result.notes)
    assert all(r["at_floor"] for r in result.records)
    assert result.shared["filter_time_constant"] == pytest.approx(5e-5, rel=0.01)


def test_an_acceleration_step_separates_the_lags():
    # Through W(p) the torquer lag adds a zero (1 + T_dm p) that the output filter does not.
    device = {"T_f": 3e-5}
    small = _record(3, SMALL, device=device)
    accel = _record(4, [0.0] * 5, accel=[0.0, 0.8, -0.8, 0.4, 0.0], device=device)
    assert accel.a_in is not None and np.ptp(accel.u_test) == 0
    result = sjv.diagnose_step_set([small, accel], NOMINAL, recommend=False)
    assert result.verdict == "output_filter", result.summary()
    assert result.shared["filter_time_constant"] == pytest.approx(3e-5, rel=0.05)
    # The acceleration's gain m l g₀/k_dm: the pendulosity's factor over the refitted k_dm
    # recovers the device's (k_dm 2 % below the nominal, m l nominal).
    k_dm = result.shared["torquer_gain"]
    ratio = result.shared["pendulosity_relative"] * k_dm["nominal"] / k_dm["value"]
    assert ratio == pytest.approx(1 / 0.98, rel=3e-3)


def test_the_default_device_is_none_across_records():
    small = _record(5, SMALL)
    stops = _record(6, STOPS, offset=0.03)
    result = sjv.diagnose_step_set([small, stops], NOMINAL, recommend=False)
    assert result.verdict == "none", result.summary()


def test_a_drift_outside_the_joint_model_is_not_named_a_lag():
    # A drifting external moment is not in the joint model: the honest answer is
    # `unexplained`, never a lag or `none`.
    rng = np.random.default_rng(7)
    n = 4500
    edges = (np.arange(1, 6) / 6 * n + rng.uniform(0, 1, 5)) / RATE
    rec = step_truth.Record(
        levels=np.asarray(SMALL),
        change_times=edges,
        rate=RATE,
        n=n,
        noise=4e-4,
        moment=5e-7,
        moment_rate=2e-3,
    )
    t, u, y = step_truth.simulate(step_truth.Device(**DEVICE), rec, rng=rng)
    drifting = StepData(t - t[0], u, y)
    result = sjv.diagnose_step_set([drifting, _record(8, STOPS)], NOMINAL, recommend=False)
    assert result.verdict == "unexplained", result.summary()


def test_expected_evidence_agrees_with_a_monte_carlo_of_2lnb():
    """The next experiment's expected 2 ln B (a noise-free simulation of the fitted truth,
    the rival refitted) against the mean 2 ln B of noisy replicates of it, each fitted by
    both models (χ² difference at the known noise)."""
    small = _record(9, SMALL, device={"T_dm": 3e-5}, noise=2e-3)
    prepared = sj.prepare_set([small], NOMINAL)
    fits = sj.fit_set(prepared, NOMINAL)
    design = sd.experiment_menu(NOMINAL, RATE, 0.0)[1]  # the acceleration steps
    assert design.accel_levels_g is not None
    design = dataclasses.replace(design, noise_V=0.2)  # V per sample: a 2 ln B of tens
    expected = sd.expected_evidence(prepared, NOMINAL, fits, "torquer_lag", "output_filter", design)
    assert 20 < expected < 500
    truth = sd._simulate_design(fits["torquer_lag"], prepared, NOMINAL, "torquer_lag", design)
    base = prepared.preps[0]
    clean = fits["torquer_lag"].prediction[0, : base.n]
    draws = []
    for k in range(10):
        rng = np.random.default_rng(100 + k)
        u_out = np.zeros_like(base.u_out)
        u_out[: base.n] = clean + rng.normal(size=clean.size) * base.sigma
        old = dataclasses.replace(base, u_out=u_out)
        noisy = StepData(
            truth.t,
            truth.u_test,
            truth.u_out + rng.normal(size=truth.t.size) * 0.2,
            a_in=truth.a_in,
        )
        new = sj.prepare_set([noisy], NOMINAL).preps[0]
        new = dataclasses.replace(new, sigma=0.2 / math.sqrt(new.block))
        combined = sj.stack([old, new], prepared.stop_voltage)
        chi2 = []
        for name in ("torquer_lag", "output_filter"):
            start = sj._transfer_start(fits[name].x, prepared, combined)
            fit = sj.fit_set(combined, NOMINAL, candidates=[name], starts={name: start})[name]
            chi2.append(
                sum(
                    float(
                        np.sum((combined.data[r, : p.n] - fit.prediction[r, : p.n]) ** 2)
                    )
                    / p.sigma**2
                    for r, p in enumerate(combined.preps)
                )
            )
        draws.append(chi2[1] - chi2[0])
    draws = np.asarray(draws)
    se = draws.std(ddof=1) / math.sqrt(draws.size)
    assert abs(draws.mean() - expected) < 3 * se + 0.05 * expected, (draws.mean(), se, expected)


def test_a_single_small_step_tie_carries_the_experiment_that_breaks_it(monkeypatch):
    small = _record(11, SMALL, device={"T_dm": 3e-5})
    shapes = []  # each design's set, as the refit sees it
    fit_set = sd.fit_set

    def recorded(prepared, *args, **kwargs):
        layout = prepared.layout
        shapes.append((layout.n_padded, layout.j_padded, prepared.ctx.max_block, layout.stops))
        return fit_set(prepared, *args, **kwargs)

    monkeypatch.setattr(sd, "fit_set", recorded)
    result = sjv.diagnose_step_set([small], NOMINAL)
    # Every design's set padded to the menu's largest shapes (the designs at 4× the rate
    # take larger blocks): one compiled refit for the designs off the stops, one on them.
    assert len(shapes) == 8 and len({s[:3] for s in shapes}) == 1, shapes
    assert len(set(shapes)) == 2, shapes
    assert result.verdict == "cannot_tell"
    menu = {e["description"]: e["expected_2lnB"] for e in result.next_experiment}
    assert len(menu) == 4
    best = result.next_experiment[0]
    assert "stops" in best["description"] or "acceleration" in best["description"]
    assert best["expected_2lnB"] > 1000
    # More small steps, or the same steps sampled faster, cannot separate an all-pole cubic
    # from an all-pole cubic: their expected evidence stays near zero.
    small_steps = [v for d, v in menu.items() if "±2 V" in d]
    assert len(small_steps) == 2 and max(small_steps) < 5
    assert "to separate torquer_lag from output_filter" in result.reason
    assert "next experiment:" in result.summary()


def test_the_designs_sets_are_padded_to_one_shape(monkeypatch):
    """On a 1 MHz record the menu's design at 4× the rate takes blocks of 39 samples
    (the largest block m padded to 64, the others' to 32): `next_experiments` pads every
    design's set to the menu's largest shapes, so that one compiled refit serves them
    (a program per shape before)."""
    import jax

    import accel_jax as aj

    n, rate = 5000, 1e6
    t = np.arange(n) / rate
    u_test = (np.arange(n) >= 200).astype(float)
    device = aj.ServoParams.reference(torquer_time_constant=3e-5)
    y = np.asarray(aj.simulate_linear(device, t, u_test, key=jax.random.key(0)))
    y = y + 1e-4 * np.random.default_rng(0).standard_normal(n)
    prepared = sj.prepare_set([StepData(t, u_test, y)], NOMINAL)
    asked = []
    monkeypatch.setattr(sd, "expected_evidence", lambda *args: asked.append(args) or 0.0)
    sd.next_experiments(prepared, NOMINAL, None, ("torquer_lag", "output_filter"))
    menu = list({id(a[5]): a[5] for a in asked}.values())  # (asked from threads)
    probes = [sd._design_probe(design, NOMINAL) for design in menu]
    shapes = [(p.shape.n_padded, p.shape.j_padded, p.shape.max_block) for p in probes]
    assert len(set(shapes)) > 1  # (unpadded, the designs would need programs of their own)
    at_least = tuple(max(c) for c in zip(*shapes, strict=True))
    assert all(a[6] == at_least for a in asked) and len(asked) == 2 * len(menu)
    for design in menu:
        probe = sj.prepare_set([sd._with_output(design.record, NOMINAL)], NOMINAL)
        combined = sj.stack(prepared.preps + probe.preps, prepared.stop_voltage, False, at_least)
        layout = combined.layout
        assert (layout.n_padded, layout.j_padded, combined.ctx.max_block) == at_least


def test_a_refit_compiled_ahead_that_fails_changes_nothing():
    """`compile_refits`' calls drop their errors (the real call raises where it happens):
    a failed warm-up never fails a diagnosis that would not have failed."""

    def fails():
        raise ValueError("a design that cannot be prepared")

    assert sd._quietly(fails)() is None


def test_acceleration_column_is_read_and_checked():
    text = "t,u_test,u_out,a_in\n" + "\n".join(
        f"{i * 1e-6},0,{0.1 * (i > 150)},{0.5 * (i > 150)}" for i in range(300)
    )
    data = parse_csv(text)
    assert data.kind == "step" and data.a_in is not None and data.a_in[-1] == 0.5
    constant = "t,u_test,u_out,a_in\n" + "\n".join(f"{i * 1e-6},0,0.1,0.5" for i in range(300))
    with pytest.raises(DataError, match="u_test and a_in are both constant"):
        parse_csv(constant)


def test_the_library_refuses_a_set_with_a_record_of_another_kind():
    """`diagnose_step_set` itself (not only the CLI) names each record's kind, before any
    fit, when one is not a step record."""
    step = _record(12, SMALL, device={"T_dm": 3e-5})
    noise = parse_csv("t,a_out\n" + "\n".join(f"{i * 1e-3},{i % 3}" for i in range(300)))
    with pytest.raises(DataError, match=r"every one is a step record.*a \(step\), b \(noise\)"):
        sjv.diagnose_step_set([step, noise], NOMINAL, names=["a", "b"])


def test_cli_diagnoses_several_files_together_and_refuses_bad_combinations(tmp_path):
    device = {"T_dm": 3e-5}
    small, stops = tmp_path / "small.csv", tmp_path / "stops.csv"
    write_csv(small, _record(12, SMALL, device=device))
    write_csv(stops, _record(13, STOPS, device=device))
    runner = CliRunner()
    out = tmp_path / "out.json"
    plot = tmp_path / "set.png"
    result = runner.invoke(
        main, ["diagnose", str(small), str(stops), "--json", str(out), "--plot", str(plot)]
    )
    assert result.exit_code == 0, result.output
    assert plot.stat().st_size > 10_000  # one row per record: data, model, residuals
    assert "joint diagnosis of 2 records" in result.output
    assert "verdict: torquer_lag" in result.output
    assert "a set of records is not searched" in result.output  # --discover is the default
    payload = json.loads(out.read_text())
    assert payload["verdict"] == "torquer_lag"
    assert payload["sources"] == [str(small), str(stops)]
    # A noise record among step records: one clear error, nothing written.
    noise = tmp_path / "noise.csv"
    noise.write_text("t,a_out\n" + "\n".join(f"{i * 1e-3},{i % 3}" for i in range(300)))
    bad = runner.invoke(main, ["diagnose", str(small), str(noise)])
    assert bad.exit_code != 0 and "Traceback" not in bad.output
    assert "every one is a step record" in bad.output and "noise.csv (noise)" in bad.output
    # The same file twice, or a forced non-step kind with several files.
    twice = runner.invoke(main, ["diagnose", str(small), str(small)])
    assert twice.exit_code != 0 and "named twice" in twice.output
    kind = runner.invoke(main, ["diagnose", str(small), str(stops), "--kind", "noise"])
    assert kind.exit_code != 0 and "takes one file" in kind.output
    # A file with another kind's columns.
    wrong = tmp_path / "wrong.csv"
    wrong.write_text("t,u_test,a_out\n" + "\n".join(f"{i * 1e-6},0,1" for i in range(300)))
    bad = runner.invoke(main, ["diagnose", str(small), str(wrong)])
    assert bad.exit_code != 0 and "wrong.csv" in bad.output and "Traceback" not in bad.output


def test_the_diagnose_commands_notes_name_the_options_that_did_not_apply():
    assert diagnose_notes(1, "step", True, True) == []
    (searched,) = diagnose_notes(2, "step", True, False)
    assert "--discover (and --ceiling) look at one record" in searched
    (params,) = diagnose_notes(1, "noise", False, True)
    assert "--params is not used by the noise diagnosis" in params


def test_identify_takes_the_stop_level_record_for_the_pickoff_gain(tmp_path):
    """`identify small.csv stops.csv`: the small step by the graph method, the stop-level
    record by eq. (11) with the device's h_max (here exact), whatever the recorder's
    polarity and offset."""
    device = {"h_max": 1.9e-6}
    small, stops, one_sided = (tmp_path / f"{n}.csv" for n in ("small", "stops", "one"))
    write_csv(small, _record(14, [0.0, 2.0], device=device, n=12000))  # one step, settled
    write_csv(stops, _record(15, STOPS, device=device, offset=0.03))
    write_csv(one_sided, _record(16, [0.0, 5.5, 0.0], device=device))
    out = tmp_path / "id.json"
    runner = CliRunner()
    result = runner.invoke(main, ["identify", str(small), str(stops), "--json", str(out)])
    assert result.exit_code == 0, result.output
    assert "eq. (11)" in result.output
    records = json.loads(out.read_text())["records"]
    gain = records[1]["stops"]["pickoff_amplifier_gain_V_per_m"]
    assert gain == pytest.approx(DEVICE["k_dp"] * 8.5, rel=2e-3)
    assert records[1]["stops"]["offset_V"] == pytest.approx(0.03, abs=2e-3)
    assert "K_a" in records[0] or "scale_factor" in json.dumps(records[0])
    bad = runner.invoke(main, ["identify", str(small), str(one_sided)])
    assert bad.exit_code != 0 and "Traceback" not in bad.output
    assert "does not reach that stop" in bad.output
