"""The sim-to-real diagnosis of vibration tables (accel_jax.diagnose.vibration and its
effects) and its CLI use, checked by simulate-then-diagnose-then-recover against
a truth generator that is not the diagnosis's own code (the time average of
`indicated_acceleration`)."""

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

import accel_jax as aj
from accel_jax._data import VibrationData, write_csv
from accel_jax.cli import main
from accel_jax.diagnose import (
    diagnose,
    diagnose_many,
    effect_library,
)
from accel_jax.diagnose.vibration import COEFFICIENTS, vibration_effects
from accel_jax.diagnose.vibration.table import prepare

ROOT = Path(__file__).resolve().parent.parent

LEVELS = (-1.0, -0.5, 0.0, 0.5, 1.0)
SINES = (0.0, 0.5, 1.0, 2.0, 4.0, 8.0)
RANDOMS = (2.0, 5.0)
ROW_NOISE = 3e-6  # g
SCHEMA = {"kind", "verdict", "ranking", "gap", "where", "refit"}
VIB_CASES = {
    "none": ({}, None),
    "k2": ({"k2": 3.0}, ("k2_ppm_per_g", 3.0)),
    "k3": ({"k3": -4.0}, ("k3_ppm_per_g2", -4.0)),
    "k4": ({"k4": 0.1}, ("k4_ppm_per_g3", 0.1)),
    "k5": ({"k5": 0.03}, ("k5_ppm_per_g4", 0.03)),
    "asymmetry": ({"asymmetry": 30.0}, ("A1_ppm", 30.0)),
    "cross_coupling": ({"m31": 8.0, "m32": -6.0}, ("m31_ppm_per_g", 8.0)),
}


def _plan(levels=LEVELS, sines=SINES, randoms=RANDOMS, cross=True):
    rows = []
    for a in levels:
        rows += [(a, b, 0.0, 0.0, 0.0) for b in sines]
        rows += [(a, 0.0, s, 0.0, 0.0) for s in randoms]
        if cross:
            rows += [(a, 4.0, 0.0, 4.0, 0.0), (a, 4.0, 0.0, 0.0, 4.0)]
    r = np.asarray(rows)
    plan = {"a_in": r[:, 0], "vib_amp": r[:, 1], "vib_rms": r[:, 2]}
    if cross:
        plan.update(vib_amp_oa=r[:, 3], vib_amp_pa=r[:, 4])
    return plan


def _time_average(tf, plan, seed, samples=16384):
    """Truth: the time average of a_F over a simulated record per row (sine over whole
    periods, centred independent Gaussian random vibration) — not the quadrature the
    diagnosis uses."""
    rng = np.random.default_rng(seed)
    theta = 2 * np.pi * 64 * np.arange(samples) / samples
    zero = np.zeros_like(plan["a_in"])
    out = []
    for i, a in enumerate(plan["a_in"]):
        sine = np.sin(theta + rng.uniform(0, 2 * np.pi))
        z = rng.normal(size=samples)
        a3 = a + plan["vib_amp"][i] * sine + plan["vib_rms"][i] * (z - z.mean())
        a1 = plan.get("vib_amp_oa", zero)[i] * sine
        a2 = plan.get("vib_amp_pa", zero)[i] * sine
        out.append(float(np.mean(aj.indicated_acceleration(tf, a3, a1, a2))))
    return np.asarray(out)


def _table(effect_ppm: dict, seed: int, plan=None, noise=ROW_NOISE) -> VibrationData:
    plan = _plan() if plan is None else plan
    tf = aj.StaticTransferFunction.from_ppm(bias_mg=0.8, scale_factor_error=-150, **effect_ppm)
    rng = np.random.default_rng(seed + 1000)
    a_out = _time_average(tf, plan, seed) + noise * rng.normal(size=plan["a_in"].size)
    freq = rng.uniform(20, 200, size=a_out.size)
    return VibrationData(a_out=a_out, vib_freq=freq, **plan)


@pytest.fixture(scope="module")
def vibration_results():
    # One table per case, diagnosed together (one compilation).
    cases = list(VIB_CASES)
    tables = [_table(VIB_CASES[c][0], seed=i) for i, c in enumerate(cases)]

    return dict(zip(cases, zip(tables, diagnose_many(tables), strict=True), strict=True))


def test_vibration_design_is_the_exact_expectation():
    # The diagnosis's linear model a_out = a_in + J θ equals `predict_table` of the
    # coefficients (the model is linear in them), and each effect is nominal at zero.
    data = _table({}, seed=0)
    table = prepare(data, vibration_effects())
    rng = np.random.default_rng(3)
    theta = rng.normal(size=len(COEFFICIENTS)) * np.array(
        [500, 100, 20, 5, 5, 0.1, 0.03, 5, 5]
    )
    tf = aj.StaticTransferFunction(
        **{c: t * 1e-6 for c, t in zip(COEFFICIENTS, theta, strict=True)}
    )
    zero_out = {**data.table(), "a_out": np.zeros(data.a_in.size)}
    exact = np.asarray(aj.vibration.predict_table(tf, zero_out)) - data.a_in
    np.testing.assert_allclose(table.design @ theta * 1e-6, exact, rtol=0, atol=1e-13)
    assert len(effect_library("vibration")) == 6
    assert table.candidates == ("nominal", "k2", "k3", "k4", "k5", "asymmetry", "cross_coupling")
    for mask, name in zip(table.masks[1:], table.candidates[1:], strict=True):
        effect = effect_library("vibration")[name]()
        # Exactly the nominal columns plus the effect's own coefficients are free.
        free = {COEFFICIENTS[j] for j in np.flatnonzero(mask)}
        assert free == {"bias", "scale_factor_error", *effect.coefficients}


def test_vibration_fit_agrees_with_fit_coefficients(vibration_results):
    data, result = vibration_results["k3"]
    table = {**data.table()}
    reference = aj.vibration.fit_coefficients(
        table, parameters=("bias", "scale_factor_error", "k3")
    )
    k3 = next(r for r in result.ranking if r["effect"] == "k3")
    assert k3["params"]["k3_ppm_per_g2"] == pytest.approx(
        float(reference.estimate_ppm[2]), rel=1e-7
    )
    assert k3["params"]["k3_ppm_per_g2_se"] == pytest.approx(
        float(reference.standard_error_ppm[2]), rel=1e-6
    )


def test_vibration_none(vibration_results):
    _, result = vibration_results["none"]
    assert result.verdict == "none", result.summary()
    assert all(r["evidence"] < 10 for r in result.ranking)
    assert result.gap["shrink"] == 0.0
    fit = result.refit["nominal_fit"]
    # The refit recovers a0 and δ (each to < 4 standard errors).
    assert abs(fit["bias_g"] - 0.8e-3) < 4 * fit["bias_se_g"]
    assert abs(fit["scale_factor_error"] + 150e-6) < 4 * fit["scale_factor_error_se"]
    assert result.refit["parameter_error"]  # a0 = 0.8 mg is a gap the refit closes
    assert result.where["whiteness"]["p_value"] > 1e-3


@pytest.mark.parametrize("case", [c for c in VIB_CASES if c != "none"])
def test_vibration_effect_named_and_recovered(vibration_results, case):
    _, result = vibration_results[case]
    assert result.verdict == case, result.summary()
    best = result.ranking[0]
    assert best["effect"] == case and best["evidence"] > 10
    name, truth = VIB_CASES[case][1]
    # Within 4 standard errors (the truth's finite records add a little model error).
    assert abs(best["params"][name] - truth) < 4 * best["params"][name + "_se"]
    assert abs(best["params"][name] - truth) < 0.15 * abs(truth)
    assert result.gap["shrink"] > 0.5
    assert result.gap["after"] < result.gap["before"]


def test_vibration_residual_localised(vibration_results):
    _, result = vibration_results["k4"]
    levels = result.where["by_vibration_level"]
    rms = {round(g["vibration_mean_square_g2"], 6): g["rms_residual_g"] for g in levels}
    # k4 rectifies as b⁴: the residual of the nominal model sits in the strongest rows.
    assert rms[32.0] > 3 * rms[0.0]
    assert result.where["whiteness_sorted_by_condition"]["p_value"] < 1e-3


def test_vibration_cannot_tell_with_one_input_level():
    # At one input level the rectified k2 (b²/2) and k3 (1.5 a b²) terms are the same
    # column up to the constant that the bias absorbs: equally good, both named.
    plan = _plan(
        levels=(1.0,), sines=(0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 8.0), randoms=(), cross=False
    )
    data = _table({"k2": 5.0}, seed=42, plan=plan)
    result = diagnose(data)
    assert result.verdict == "cannot_tell", result.summary()
    assert set(result.tied) == {"k2", "k3"}
    notes = " ".join(result.notes)
    assert "one input level" in notes and "cross_coupling left out" in notes
    assert "cross_coupling" not in [r["effect"] for r in result.ranking]
    assert result.gap["shrink"] > 0.5


def test_a_row_pasted_twice_is_noted():
    data = _table({}, seed=3)
    again = VibrationData(
        *(
            None if v is None else np.concatenate([v, v[:2]])
            for v in (getattr(data, f.name) for f in dataclasses.fields(data))
        )
    )
    notes = " ".join(prepare(again, vibration_effects()).notes)
    assert "2 row(s) equal another row in every column" in notes
    assert "equal another row" not in " ".join(prepare(data, vibration_effects()).notes)


def test_vibration_unobservable_effects_left_out():
    # No vibration at ±1 g only: every rectified term is a bias or scale-factor change.
    plan = {
        "a_in": np.tile([-1.0, 1.0], 5),
        "vib_amp": np.zeros(10),
        "vib_rms": np.zeros(10),
    }
    data = _table({}, seed=5, plan=plan)
    result = diagnose(data)
    assert result.verdict == "none"
    left_out = result.where["not_identifiable"]
    assert {"k2", "k3", "k4", "k5", "asymmetry", "cross_coupling"} == set(left_out)
    assert result.ranking == []


def test_cli_on_a_vibration_table(vibration_results, tmp_path):
    data, _ = vibration_results["asymmetry"]
    csv = write_csv(tmp_path / "vib.csv", data)
    assert "vib_amp_oa" in csv.read_text().splitlines()[0]
    out_json, out_png = tmp_path / "v.json", tmp_path / "v.png"
    result = CliRunner().invoke(
        main, ["diagnose", str(csv), "--json", str(out_json), "--plot", str(out_png)]
    )
    assert result.exit_code == 0, result.output
    assert "verdict: asymmetry" in result.output
    doc = json.loads(out_json.read_text())
    assert set(doc) >= SCHEMA and doc["kind"] == "vibration" and doc["verdict"] == "asymmetry"
    assert set(doc["gap"]) >= {"metric", "before", "after", "shrink"}
    assert set(doc["ranking"][0]) >= {"effect", "evidence", "gap_shrink", "params"}
    assert {"by_input_level", "by_vibration_level", "whiteness"} <= set(doc["where"])
    assert out_png.stat().st_size > 10_000


def test_cli_bad_vibration_and_noise_input(tmp_path):
    header = "a_in,vib_amp,vib_freq,vib_rms,a_out"
    files = {
        "sinusoid without frequency": header
        + "\n"
        + "\n".join(f"{i},1,0,0,{i}" for i in range(10)),
        "negative cross-axis amplitude": header
        + ",vib_amp_oa\n"
        + "\n".join(f"{i},1,50,0,{i},-1" for i in range(10)),
        "too few rows": header + "\n" + "\n".join(f"{i},1,50,0,{i}" for i in range(5)),
        "constant noise": "t,a_out\n" + "\n".join(f"{i * 0.01!r},1.0" for i in range(300)),
        # a dead output (0 g in every row) while a_in varies: it read `none` with δ = −1e6 ppm
        "dead vibration output": header
        + "\n"
        + "\n".join(f"{-1 + 0.25 * i!r},1,50,0,0" for i in range(10)),
        "short noise": "t,a_out\n" + "\n".join(f"{i * 0.01!r},{np.sin(i)!r}" for i in range(100)),
    }
    out_json = tmp_path / "never.json"
    for name, text in files.items():
        path = tmp_path / f"{name.replace(' ', '_')}.csv"
        path.write_text(text)
        result = CliRunner().invoke(main, ["diagnose", str(path), "--json", str(out_json)])
        assert result.exit_code != 0, name
        lines = [line for line in result.stderr.splitlines() if line.strip()]
        assert len(lines) == 1 and lines[0].startswith("Error:"), (name, result.stderr)
        assert not out_json.exists(), name
        if name == "dead vibration output":
            assert "disconnected or saturated channel" in lines[0], lines[0]
