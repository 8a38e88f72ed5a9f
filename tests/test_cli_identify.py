"""`accel-jax identify` as System Identification Toolbox users read it (issue 25): the
--plot figure, the fit percentage and NRMSE, the parameter table against the nominal
device and the residual whiteness test, each checked against an independent computation."""

import dataclasses
import json
import re

import equinox as eqx
import jax
import numpy as np
import pytest
import scipy.signal
from click.testing import CliRunner

import accel_jax as aj
from accel_jax import report
from accel_jax._identify.step_record import identify_step_record
from accel_jax._identify.step_result import FitFailure
from accel_jax.cli import main
from accel_jax.report.text import identification

N, PRE = 5000, 200  # samples per record (one length: one compilation), at rest before the step


def _record(params, sample_rate, noise, *, ar_std=0.0, seed=0):
    """A 1 V test step after PRE samples at rest: the library's simulation (with the
    device's own 1e-5 V output noise) plus white Gaussian noise of std `noise` [V] and,
    with `ar_std`, an AR(1) disturbance u_k = 0.95 u_{k−1} + w_k, std(w) = `ar_std` [V]."""
    ts = np.arange(N) / sample_rate
    u_test = (np.arange(N) >= PRE).astype(float)
    u = np.asarray(aj.simulate_linear(params, ts, u_test, key=jax.random.key(seed)))
    rng = np.random.default_rng(seed)
    u = u + noise * rng.standard_normal(N)
    if ar_std:
        u = u + scipy.signal.lfilter([1.0], [1.0, -0.95], ar_std * rng.standard_normal(N))
    return aj.StepData(ts, u_test, u)


@pytest.fixture(scope="module")
def records(tmp_path_factory):
    reference = aj.ServoParams.reference()
    # ξ = 0.1: A2 is half the step, so the graph method still reads it through 50 mV of noise.
    ringing = eqx.tree_at(lambda p: p.damping, reference, aj.damping_for_ratio(reference, 0.1))
    folder = tmp_path_factory.mktemp("identify_sitb")
    paths = {}
    for name, data in {
        "low_noise": _record(reference, 1e6, 1e-4),
        "noisy": _record(ringing, 2.5e5, 0.05),
        "coloured": _record(reference, 1e6, 1e-4, ar_std=2e-4),
    }.items():
        paths[name] = folder / f"{name}.csv"
        aj.write_csv(paths[name], data)
    return paths


def _identify(csv, folder, *extra):
    plot, out = folder / "p.png", folder / "j.json"
    args = ["identify", str(csv), "--plot", str(plot), "--json", str(out), *extra]
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 0, result.output
    return result.output, json.loads(out.read_text()), plot


def _independent_model(doc, data):
    """ŷ of the fitted order-3 model from the JSON's parameters, by SciPy's exact step
    response of U0 + G/[(T²p² + 2ξTp + 1 − K)(T_dm p + 1) + K] · 1/(T_f p + 1)."""
    fit = doc["fit"]
    t, xi, tdm = fit["time_constant_s"], fit["damping_ratio"], fit["torquer_time_constant_s"]
    k, tf = fit["known_feedback_fraction"], fit["known_filter_time_constant_s"]
    loop = np.polyadd(np.polymul([t**2, 2 * xi * t, 1 - k], [tdm, 1.0]), [k])
    system = scipy.signal.lti([1.0], np.polymul(loop, [tf, 1.0]))
    ts = np.asarray(data.t)
    tau = ts - doc["segment"]["step_time_s"]
    after = tau >= 0
    _, shape = scipy.signal.step(system, T=tau[after])
    model = np.full(ts.shape, fit["offset_V"])
    model[after] += fit["gain_V"] * shape
    return model


def _fit_percent(y, model):
    """MATLAB's compare: 100 (1 − ‖y − ŷ‖/‖y − mean(y)‖)."""
    return 100 * (1 - np.linalg.norm(y - model) / np.linalg.norm(y - y.mean()))


def _printed_fit_percent(output):
    return float(re.search(r"^  fit (\d+\.\d+) % \(MATLAB compare", output, re.M).group(1))


def test_identify_reports_the_fit_as_system_identification_users_read_it(records, tmp_path):
    csv = records["low_noise"]
    output, doc, plot = _identify(csv, tmp_path)
    assert plot.stat().st_size > 10_000
    assert "traces" not in doc  # the sample-by-sample curves stay out of the JSON

    # Fit percentage and NRMSE, against NumPy on SciPy's response of the fitted model.
    data = aj.read_csv(csv, kind="step")
    y = np.asarray(data.u_out)
    model = _independent_model(doc, data)
    quality = doc["fit"]["quality"]
    assert quality["fit_percent"] == pytest.approx(_fit_percent(y, model), abs=1e-6)
    assert quality["nrmse"] == pytest.approx(1 - quality["fit_percent"] / 100, rel=1e-12)
    assert 90 < quality["fit_percent"] < 100
    assert _printed_fit_percent(output) == pytest.approx(quality["fit_percent"], abs=0.005)
    assert "NRMSE" in output

    # The parameter table: one aligned row per fitted or reported parameter, human units.
    lines = output.splitlines()
    header = next(i for i, line in enumerate(lines) if "parameter" in line and "±σ" in line)
    for column in ("nominal", "estimate", "±σ", "shift"):
        assert column in lines[header]
    rows = lines[header + 1 : header + 7]
    assert [row.split()[0] for row in rows] == ["T", "ξ", "T_dm", "G", "U0", "K_a"]
    assert len({row.index("σ  ") for row in rows if "σ  " in row}) == 1  # shift column aligned
    assert "µs" in rows[0] and "µs" in rows[2]  # T and T_dm in µs, not 0.00029 s
    assert not re.search(r"\d{8,}", output)  # no 17-digit floats anywhere
    table = {row["name"]: row for row in doc["fit"]["parameters"]}
    assert set(table) == {"T", "ξ", "T_dm", "G", "U0", "K_a"}
    for row in table.values():
        if row["nominal"] is not None:
            shift = (row["estimate"] - row["nominal"]) / row["std"]
            assert row["shift_in_std"] == pytest.approx(shift)
            # The noise-only record of the nominal device: every parameter within 4σ.
            assert abs(row["shift_in_std"]) < 4, row
    assert table["U0"]["nominal"] is None and table["U0"]["shift_in_std"] is None

    # Whiteness: the reported Ljung-Box test is that of the independent residual.
    whiteness = quality["whiteness"]
    independent = aj.noise.ljung_box(y - model, lags=whiteness["lags"])
    assert whiteness["p_value"] == pytest.approx(independent["p_value"], rel=1e-3, abs=1e-6)
    assert whiteness["white"] and whiteness["p_value"] >= 0.05
    line = next(line for line in lines if "residual whiteness: Ljung-Box" in line)
    assert f"over {whiteness['lags']} lags, p = " in line and line.endswith(": white")

    # ξ: the graph method reads the lag-biased extrema, far outside the fit's ±2σ.
    graph_xi, fit = doc["graph"]["damping_ratio"], doc["fit"]
    shift = (graph_xi - fit["damping_ratio"]) / fit["damping_ratio_std"]
    assert abs(shift) > 2
    note = next(line for line in lines if line.startswith("note: graph ξ"))
    assert f"differ by -{abs(shift):.0f}σ" in note and "extrema" in note and "lag" in note
    # The graph method's read-off points are in the JSON for the plot.
    graph = doc["graph"]
    assert graph["crossing_t1_s"] < graph["overshoot_A1_time_s"] < graph["undershoot_A2_time_s"]
    assert graph["undershoot_A2_time_s"] < graph["crossing_t2_s"]


def test_identify_fit_percent_drops_with_noise(records, tmp_path):
    output, doc, plot = _identify(records["noisy"], tmp_path)
    assert plot.stat().st_size > 10_000
    data = aj.read_csv(records["noisy"], kind="step")
    y = np.asarray(data.u_out)
    fit_percent = doc["fit"]["quality"]["fit_percent"]
    assert fit_percent == pytest.approx(_fit_percent(y, _independent_model(doc, data)), abs=1e-6)
    # 50 mV of white noise on a ringing 1 V step: NRMSE ≈ σ/std(y) ≈ 0.17.
    assert 50 < fit_percent < 90
    assert _printed_fit_percent(output) == pytest.approx(fit_percent, abs=0.005)
    assert doc["fit"]["quality"]["whiteness"]["white"]  # more noise, still white


def test_identify_flags_a_coloured_residual(records, tmp_path):
    output, doc, _ = _identify(records["coloured"], tmp_path)
    whiteness = doc["fit"]["quality"]["whiteness"]
    assert whiteness["p_value"] < 0.05 and not whiteness["white"]
    line = next(line for line in output.splitlines() if "residual whiteness" in line)
    assert line.endswith("not white at 5 %")
    # The AR(1) disturbance is correlated at lag 1 far beyond the 95 % band.
    assert whiteness["autocorrelation"][0] > 10 * whiteness["band_95"]


def test_identify_plot_refuses_an_existing_file(records, tmp_path):
    plot, out = tmp_path / "p.png", tmp_path / "j.json"
    plot.write_bytes(b"the user's own figure")
    args = ["identify", str(records["low_noise"]), "--plot", str(plot), "--json", str(out)]
    refused = CliRunner().invoke(main, args)
    assert refused.exit_code == 1
    assert refused.output.strip().splitlines() == [
        f"Error: --plot {plot} already exists; pass --force to replace it, or choose another path."
    ]
    assert plot.read_bytes() == b"the user's own figure"
    assert not out.exists()  # refused before any work: nothing half done
    forced = CliRunner().invoke(main, [*args, "--force"])
    assert forced.exit_code == 0, forced.output
    assert plot.stat().st_size > 10_000
    assert sorted(p.name for p in tmp_path.iterdir()) == ["j.json", "p.png"]  # no temporaries


@pytest.mark.parametrize(
    "options, message",
    [
        (["--json", "same.x", "--plot", "same.x"], "--json and --plot are the same file"),
        (["--plot", "p.jpg"], "the figure is written as .png, .pdf, .svg"),
        (["--json", "a_file/j.json"], "a_file is a file, so nothing can be written below it"),
        (["--json", "new.json", "--plot", "a_file/p.png"], "a_file is a file"),
        (["--out", "a_folder", "--json", "../a_file/j.json"], "a_file is a file"),
    ],
)
def test_outputs_that_cannot_be_written_are_refused_before_any_work(
    records, tmp_path, monkeypatch, options, message
):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "a_file").write_text("the user's")
    (tmp_path / "a_folder").mkdir()
    result = CliRunner().invoke(main, ["identify", str(records["low_noise"]), *options])
    assert result.exit_code == 1, result.output
    assert "Traceback" not in result.output
    [line] = result.output.strip().splitlines()
    assert line.startswith("Error: ") and message in line, line
    # nothing written, nothing replaced
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file", "a_folder"]
    assert (tmp_path / "a_file").read_text() == "the user's"


def test_identify_plot_as_pdf_is_a_pdf(records, tmp_path):
    plot = tmp_path / "p.pdf"
    result = CliRunner().invoke(main, ["identify", str(records["low_noise"]), "--plot", str(plot)])
    assert result.exit_code == 0, result.output
    assert plot.read_bytes().startswith(b"%PDF")


def test_identify_out_puts_everything_under_the_folder(records, tmp_path):
    out = tmp_path / "run"
    result = CliRunner().invoke(main, ["identify", str(records["low_noise"]), "--out", str(out)])
    assert result.exit_code == 0, result.output
    names = sorted(p.name for p in out.iterdir())
    assert names == ["identify.json", "identify.png", "identify.txt"]
    assert "fit " in (out / "identify.txt").read_text()
    (out / "identify.txt").write_text("mine")
    again = CliRunner().invoke(main, ["identify", str(records["low_noise"]), "--out", str(out)])
    assert again.exit_code != 0 and "--force" in again.output
    assert (out / "identify.txt").read_text() == "mine"


def test_report_without_a_fit(records):
    """A failed fit still prints the graph method and draws the record (no residual)."""
    data = aj.read_csv(records["low_noise"], kind="step")
    result = identify_step_record(data, aj.ServoParams.reference())
    result = dataclasses.replace(
        result,
        fit=FitFailure("The least-squares fit did not converge within max_steps."),
        traces=dataclasses.replace(result.traces, model_V=None),
    )
    text = report.identification_summary(result)
    assert "least-squares fit failed" in text and "δK_a" in text
    assert (
        identification.parameter_table(result) == [] and identification.damping_note(result) is None
    )
    figure = report.identification_figure(result, title="no fit")
    assert len(figure.axes) == 3


def test_a_time_constant_far_from_the_nominal_is_noted():
    # A record whose time column is in ms read as s: T 1000× the nominal device's. Without the
    # note, identify printed δK_a = +99.9999 % and nothing else (a user's trial).
    from accel_jax.report.text.identification import time_scale_note

    note = time_scale_note(0.2879, 290.1e-6)
    assert note is not None and "992× the nominal device's 290.1 µs" in note
    assert "--params" in note and "seconds" in note
    assert "is 0.001× the nominal" in (time_scale_note(0.29e-6, 290e-6) or "")
    assert time_scale_note(2.9 * 290e-6, 290e-6) is None  # within the factor 3
    assert time_scale_note(290e-6 / 2.9, 290e-6) is None
    assert time_scale_note(float("nan"), 290e-6) is None


def test_an_unsettled_record_is_told_what_to_record_not_which_keyword_to_pass(records):
    # The record cut 1.3 ms after its step (4.5 T: still ringing). identify's reason said
    # "pass `steady_state`", a keyword of the Python methods the command does not have.
    data = aj.read_csv(records["low_noise"], kind="step")
    start = int(np.flatnonzero(np.diff(np.asarray(data.u_test)) != 0)[0])
    stop = start + int(round(1.3e-3 / data.sample_period))
    short = aj.StepData(data.t[:stop], data.u_test[:stop], data.u_out[:stop])
    with pytest.raises(aj.DataError) as refused:
        identify_step_record(short, aj.ServoParams.reference())
    message = str(refused.value)
    assert "Record for longer after the step" in message, message
    assert "steady_state" not in message and "tail_fraction" not in message
    assert "identify_" not in message
