"""The `accel-jax identify` subcommand: a user's own step record, end to end."""

import json

import jax
import numpy as np
import pytest
from click.testing import CliRunner

import accel_jax as aj
from accel_jax.cli import main

PRE = 200  # samples at rest before the test step


@pytest.fixture(scope="module")
def step_csv(tmp_path_factory):
    # The reference device (T_dm, T_f in the loop, noise 1e-5 V), 1 MHz, 10 ms after a 1 V
    # step, with 200 settled samples before it: the format a test stand would write.
    params = aj.ServoParams.reference()
    ts, u = aj.step_response(
        params, duration=10e-3, sample_rate=1e6, test_voltage=1.0, key=jax.random.key(3)
    )
    ts, u = np.asarray(ts), np.asarray(u)
    dt = ts[1] - ts[0]
    # The settled level is the noise-free first sample (u[0] itself carries a noise draw).
    level = float(aj.step_response(params, duration=10e-3, sample_rate=1e6)[1][0])
    rest = level + 1e-5 * np.random.default_rng(0).standard_normal(PRE)
    data = aj.StepData(
        np.concatenate([np.arange(PRE) * dt, ts + PRE * dt]),
        np.concatenate([np.zeros(PRE), np.ones(len(ts))]),
        np.concatenate([rest, u]),
    )
    path = tmp_path_factory.mktemp("identify") / "step.csv"
    aj.write_csv(path, data)
    return path, float(aj.scale_factor(params))


def test_identify_recovers_the_scale_factor(step_csv, tmp_path):
    path, truth = step_csv
    out = tmp_path / "id.json"
    result = CliRunner().invoke(main, ["identify", str(path), "--json", str(out)])
    assert result.exit_code == 0, result.output
    doc = json.loads(out.read_text())
    assert doc["segment"]["step_time_s"] == pytest.approx(PRE * 1e-6)
    assert doc["graph"]["method"].startswith("oscillatory")
    # The graph method carries the T_dm bias of the reference device (0.12-0.14 %, docs/models.md
    # §1 and the scale-factor study) plus noise scatter (±0.02 %).
    assert 0.05 < doc["graph"]["dKa_percent"] < 0.25
    # The order-3 fit with the known T_f is unbiased: within 4σ of the true K_a.
    fit = doc["fit"]
    assert abs(fit["scale_factor"] - truth) < 4 * fit["scale_factor_std"]
    assert fit["torquer_time_constant_s"] == pytest.approx(1e-5, rel=0.05)
    assert "δK_a" in result.output
    # An existing output is not replaced unless asked.
    again = CliRunner().invoke(main, ["identify", str(path), "--json", str(out)])
    assert again.exit_code == 1 and "already exists" in again.output
    forced = CliRunner().invoke(main, ["identify", str(path), "--json", str(out), "--force"])
    assert forced.exit_code == 0, forced.output


def test_identify_bad_input(step_csv, tmp_path):
    path, _ = step_csv
    runner = CliRunner()

    def run(*args):
        return runner.invoke(main, ["identify", *map(str, args)])

    missing = run(tmp_path / "nope.csv")
    assert missing.exit_code == 1 and "no such file" in missing.output
    wrong = tmp_path / "wrong.csv"
    wrong.write_text("t,a_out\n" + "\n".join(f"{i * 1e-3},{0.0}" for i in range(300)))
    result = run(wrong)
    assert result.exit_code == 1 and "Error:" in result.output and "Traceback" not in result.output
    flat = tmp_path / "flat.csv"
    t = np.arange(400) * 1e-6
    aj.write_csv(flat, aj.StepData(t, np.zeros_like(t), np.zeros_like(t)))
    result = run(flat)
    assert result.exit_code == 1 and "u_test is constant" in result.output
    result = run(path, "--gamma", "foo")
    assert result.exit_code == 2 and "--gamma" in result.output
    result = run(path, "--gamma", "-1")
    assert result.exit_code == 1 and "positive" in result.output
    # The oscillatory record is refused by the aperiodic method with the paper's reason.
    result = run(path, "--method", "aperiodic")
    assert result.exit_code == 1 and "overshoots" in result.output


CYCLONE4 = ["--budget", "5e-4", "--mean-accel", "2", "--sine", "1.2", "1.2", "0.5"]


def test_tolerance_reproduces_the_paper_method_and_checks_a_unit(tmp_path):
    out = tmp_path / "limits.json"
    result = CliRunner().invoke(
        main, ["tolerance", *CYCLONE4, "--rms", "1.4", "--unit", "aks05", "--json", str(out)]
    )
    assert result.exit_code == 0, result.output
    limits = json.loads(out.read_text())["limits_ppm"]
    # docs/models.md §3's reconstruction: A1 ≤ 0.44δ*/(0.673 b3 + 0.125 σ3) ≈ 430 ppm; m ≈ 48.7 ppm/g.
    assert limits["asymmetry"]["paper_method"] == pytest.approx(
        0.44 * 5e-4 / (0.673 * 0.5 + 0.125 * 1.4) * 1e6
    )
    assert limits["m31"]["paper_method"] == pytest.approx(
        0.22 * 5e-4 / (0.5 * 0.5 * 1.2 + 1.4 * 1.4) * 1e6
    )
    # Where the exact sensitivity is the paper's denominator (k2), both methods agree.
    assert limits["k2"]["gradient_paper_shares"] == pytest.approx(
        limits["k2"]["paper_method"], rel=1e-9
    )
    assert limits["k3"]["passport"] == 7 and limits["k3"]["within"] is True
    assert "EXCEEDS" not in result.output


def test_tolerance_from_a_psd_file_and_bad_input(tmp_path):
    runner = CliRunner()
    psd = tmp_path / "psd.csv"
    psd.write_text(
        "f_low,f_high,psd,eta\n20,40,0.0165,1.6\n40,80,0.0185,1.8\n80,160,0.045,0.4\n"
        "160,320,0.095,0.1\n320,640,0.12,0.05\n"
    )
    result = runner.invoke(main, ["tolerance", *CYCLONE4, "--psd", str(psd)])
    assert result.exit_code == 0, result.output
    # σ = sqrt((1/n) Σ η S Δf) of the paper's Table 1 (midpoint PSDs): 1.16 g.
    assert "random σ = 1.16" in result.output
    overlapping = tmp_path / "overlap.csv"
    overlapping.write_text("f_low,f_high,psd\n20,50,0.01\n40,80,0.02\n")
    bad = {
        ("--budget", "0"): "budget must be positive",
        ("--psd", str(overlapping)): "overlap",
        ("--psd", str(tmp_path / "none.csv")): "no such file",
        ("--rms", "1", "--psd", str(psd)): "not both",
        ("--rms", "-1"): "non-negative",
    }
    for extra, message in bad.items():
        args = ["tolerance", *CYCLONE4, *extra]
        if extra[0] == "--budget":
            args = ["tolerance", "--budget", "0", "--mean-accel", "2"]
        result = runner.invoke(main, args)
        assert result.exit_code in (1, 2), (extra, result.output)
        assert message in result.output, (extra, result.output)
        assert "Traceback" not in result.output


def test_subcommands_keep_compiled_programs_in_the_cache(tmp_path):
    """`accel-jax info` (like diagnose and identify) writes compiled programs to the
    persistent cache, reads them back with the same output, and runs without a cache under
    ACCEL_JAX_CACHE_DIR=off. Fresh processes: JAX's cache configuration is process-global."""
    import os
    import subprocess
    import sys

    def run(value):
        env = {**os.environ, "ACCEL_JAX_CACHE_DIR": value}
        env.pop("JAX_COMPILATION_CACHE_DIR", None)
        env.pop("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", None)
        code = "from accel_jax.cli import main; main(['info'])"
        out = subprocess.run(
            [sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120
        )
        assert out.returncode == 0, out.stderr
        return out.stdout

    folder = tmp_path / "xla"
    first = run(str(folder))
    assert any(p.is_file() for p in folder.rglob("*")), "nothing written to the cache"
    assert run(str(folder)) == first  # same output from cached programs
    assert run("off") == first
