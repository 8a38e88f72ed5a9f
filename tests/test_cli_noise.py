"""The `accel-jax noise` subcommand: a static record end to end (ADEV, IEEE terms, effects,
exports) and its refusals."""

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

import accel_jax as aj
from accel_jax.cli import main

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "studies"))
import noise_truth  # noqa: E402


@pytest.fixture(scope="module")
def noise_csv(tmp_path_factory):
    # 100 Hz, 160 s: white 2 mg + a random walk of the bias (K = 5e-4 g/√s, its ADEV
    # above the white one from τ ≈ 0.7 s) + an output grid of 2.5 mg, level ≈ −1 g.
    rng = np.random.default_rng(11)
    n, dt = 16000, 0.01
    x = noise_truth.record(
        rng, n, dt, {"white": 2e-3, "random_walk": 2.5e-7, "quantization": 2.5e-3, "level": -1}
    )
    path = tmp_path_factory.mktemp("noise") / "static.csv"
    aj.write_csv(path, aj.NoiseData(np.arange(n) * dt, x))
    return path


@pytest.fixture(scope="module")
def first_run(noise_csv, tmp_path_factory):
    """The command run once in full (--json, --plot, --export gnss-ins-sim), with a spy on
    the library's analysis that keeps what it computed: the tests of the other exports
    give the command that analysis back instead of computing it again (~1½ min of CPU
    each), so that they test what is theirs, the export and the files written."""
    import accel_jax.noise as noise_namespace

    real, seen = noise_namespace.analyse_static_record, []

    def spy(*args, **kwargs):
        seen.append((args, kwargs, real(*args, **kwargs)))
        return seen[-1][2]

    folder = tmp_path_factory.mktemp("first_run")
    out_json, out_png = folder / "n.json", folder / "n.png"
    args = ["noise", str(noise_csv), "--json", str(out_json), "--plot", str(out_png)]
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(noise_namespace, "analyse_static_record", spy)
        result = CliRunner().invoke(main, [*args, "--export", "gnss-ins-sim"])
    return result, out_json, out_png, seen


def test_noise_command_reports_terms_effects_and_exports(noise_csv, first_run):
    runner = CliRunner()
    result, out_json, out_png, seen = first_run
    assert result.exit_code == 0, result.output
    assert len(seen) == 1  # the command analysed the record once, through the library
    assert "IEEE noise terms" in result.output and "effects: " in result.output
    saved = json.loads(out_json.read_text())
    assert {"random_walk", "quantization"} <= set(saved["effects"]["effects"])
    assert saved["effects"]["quantization"]["step"] == pytest.approx(2.5e-3, rel=0.05)
    n_term, k_term = (saved["ieee_terms"]["terms"][k] for k in "NK")
    assert n_term["supported"] and k_term["supported"]
    assert n_term["lower"] <= n_term["value"] <= n_term["upper"]
    # the white density σ_w √Δt, σ_w² = white + the grid's q²/12: within its interval
    # widened by 5 % (the grid's noise is white only approximately)
    sigma = math.sqrt(2e-3**2 + 2.5e-3**2 / 12)
    assert 0.95 * n_term["lower"] <= sigma * math.sqrt(0.01) <= 1.05 * n_term["upper"]
    # K = √q = 5e-4 g/√s within its interval
    assert k_term["lower"] <= math.sqrt(2.5e-7) <= k_term["upper"]
    assert out_png.stat().st_size > 10_000
    # gnss-ins-sim has no random-walk bias: the export leaves K out, and says so (it did
    # not), with its Infinity correlation time (no correlated bias) explained
    assert "note: K is not in the gnss-ins-sim export (no random-walk bias" in result.output
    assert "note: accel_b_corr is Infinity" in result.output
    # gnss-ins-sim's accel_vrw [m/s/√h] is 60 × N [m/s²/√Hz] (N in g·√s × 9.80665)
    exported, _ = json.JSONDecoder().raw_decode(result.output[result.output.index("{") :])
    assert exported["accel_vrw"][0] == pytest.approx(60 * 9.80665 * n_term["value"], rel=1e-9)
    # a second run does not replace the JSON unasked
    again = runner.invoke(main, ["noise", str(noise_csv), "--json", str(out_json)])
    assert again.exit_code != 0 and "--force" in again.output


@pytest.mark.parametrize("fmt", ["kalibr", "ieee"])
def test_noise_command_other_exports(noise_csv, first_run, fmt, tmp_path, monkeypatch):
    import accel_jax.noise as noise_namespace

    (analysed_args, analysed_kwargs, analysed), = first_run[3]

    def analysis_of_the_first_run(*args, **kwargs):  # the same record, the same options
        assert np.array_equal(args[0], analysed_args[0]) and args[1:] == analysed_args[1:]
        assert kwargs == analysed_kwargs
        return analysed

    monkeypatch.setattr(noise_namespace, "analyse_static_record", analysis_of_the_first_run)
    if fmt == "ieee":
        result = CliRunner().invoke(main, ["noise", str(noise_csv), "--export", fmt])
        assert result.exit_code == 0, result.output
        assert "velocity random walk" in result.output
        return
    # --out DIR: everything under DIR, nothing replaced unasked.
    out = tmp_path / "out"
    args = ["noise", str(noise_csv), "--export", fmt, "--out", str(out)]
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in out.iterdir()) == [
        "noise.json",
        "noise.png",
        "noise.txt",
        "noise_imu.yaml",
    ]
    exported = (out / "noise_imu.yaml").read_text()
    assert "accelerometer_noise_density:" in exported and "update_rate: 100.0" in exported
    assert "accelerometer_noise_density:" not in result.output  # in the file, not printed
    assert "IEEE noise terms" in (out / "noise.txt").read_text()
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    again = CliRunner().invoke(main, args)
    assert again.exit_code != 0 and "--force" in again.output
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


def test_noise_command_bad_input(tmp_path):
    runner = CliRunner()
    missing = runner.invoke(main, ["noise", str(tmp_path / "none.csv")])
    assert missing.exit_code != 0 and "Traceback" not in missing.output
    step = tmp_path / "step.csv"
    step.write_text("t,u_test,u_out\n0,0,0\n1,1,1\n")
    wrong = runner.invoke(main, ["noise", str(step)])
    assert wrong.exit_code != 0 and "Error" in wrong.output
    short = tmp_path / "short.csv"
    short.write_text("t,a_out\n" + "".join(f"{k * 0.01},{np.sin(k)}\n" for k in range(40)))
    few = runner.invoke(main, ["noise", str(short)])
    assert few.exit_code != 0 and "at least" in few.output and "Traceback" not in few.output


def test_a_record_too_short_for_the_analysis_is_refused_in_its_terms(tmp_path):
    # 300 samples pass the reader (≥ 256) but not the five IEEE terms' octaves: the reason
    # named the library function (`fit_allan_terms: …`), not what the command needs.
    path = tmp_path / "short.csv"
    x = np.random.default_rng(0).normal(size=300)
    aj.write_csv(path, aj.NoiseData(np.arange(300) * 0.01, x))
    result = CliRunner().invoke(main, ["noise", str(path)])
    assert result.exit_code == 1
    [line] = [line for line in result.output.splitlines() if line.strip()]
    assert "300 samples is too short for the noise analysis" in line, line
    assert "at least 1024 samples" in line and "fit_allan_terms" not in line
