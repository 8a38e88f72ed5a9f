"""The sim-to-real diagnosis of vibration tables and static noise records
(accel_jax.diagnose.vibration, accel_jax.diagnose.noise), their CLI use and the Table 5 gap
study. Checked by simulate-then-diagnose-then-recover against truth generators that are not
the diagnosis's own code (the time average of `indicated_acceleration` for tables,
`simulate_noise` for records), and the fast noise filter against the generic exact
likelihood of `accel_jax._noise`."""

import json
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from click.testing import CliRunner

import accel_jax as aj
from accel_jax._data import DataError, NoiseData, VibrationData, write_csv
from accel_jax._noise import log_likelihood
from accel_jax.cli import main
from accel_jax.diagnose import (
    CandidateFit,
    diagnose,
    diagnose_many,
    effect_library,
    noise_effects,
    noise_fit,
    rank_candidates,
)
from accel_jax.diagnose import vibration as vibration_kind

ROOT = Path(__file__).resolve().parent.parent

# --- vibration tables ------------------------------------------------------------------

LEVELS = (-1.0, -0.5, 0.0, 0.5, 1.0)
SINES = (0.0, 0.5, 1.0, 2.0, 4.0, 8.0)
RANDOMS = (2.0, 5.0)
ROW_NOISE = 3e-6  # g


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


VIB_CASES = {
    "none": ({}, None),
    "k2": ({"k2": 3.0}, ("k2_ppm_per_g", 3.0)),
    "k3": ({"k3": -4.0}, ("k3_ppm_per_g2", -4.0)),
    "k4": ({"k4": 0.1}, ("k4_ppm_per_g3", 0.1)),
    "k5": ({"k5": 0.03}, ("k5_ppm_per_g4", 0.03)),
    "asymmetry": ({"asymmetry": 30.0}, ("A1_ppm", 30.0)),
    "cross_coupling": ({"m31": 8.0, "m32": -6.0}, ("m31_ppm_per_g", 8.0)),
}


@pytest.fixture(scope="module")
def vibration_results():
    # One table per case, diagnosed together (one compilation).
    cases = list(VIB_CASES)
    tables = [_table(VIB_CASES[c][0], seed=i) for i, c in enumerate(cases)]
    from accel_jax.diagnose import diagnose_many

    return dict(zip(cases, zip(tables, diagnose_many(tables), strict=True), strict=True))


def test_vibration_design_is_the_exact_expectation():
    # The diagnosis's linear model a_out = a_in + J θ equals `predict_table` of the
    # coefficients (the model is linear in them), and each effect is nominal at zero.
    data = _table({}, seed=0)
    prep = vibration_kind._prepare(data, vibration_kind._effects())
    rng = np.random.default_rng(3)
    theta = rng.normal(size=len(vibration_kind.COEFFICIENTS)) * np.array(
        [500, 100, 20, 5, 5, 0.1, 0.03, 5, 5]
    )
    tf = aj.StaticTransferFunction(
        **{c: t * 1e-6 for c, t in zip(vibration_kind.COEFFICIENTS, theta, strict=True)}
    )
    table = {**data.table(), "a_out": np.zeros(data.a_in.size)}
    exact = np.asarray(aj.predict_table(tf, table)) - data.a_in
    np.testing.assert_allclose(prep["design"] @ theta * 1e-6, exact, rtol=0, atol=1e-13)
    assert len(effect_library("vibration")) == 6
    assert prep["candidates"] == ["nominal", "k2", "k3", "k4", "k5", "asymmetry", "cross_coupling"]
    for mask, name in zip(prep["masks"][1:], prep["candidates"][1:], strict=True):
        effect = effect_library("vibration")[name]()
        # Exactly the nominal columns plus the effect's own coefficients are free.
        free = {vibration_kind.COEFFICIENTS[j] for j in np.flatnonzero(mask)}
        assert free == {"bias", "scale_factor_error", *effect.coefficients}


def test_vibration_fit_agrees_with_fit_coefficients(vibration_results):
    data, result = vibration_results["k3"]
    table = {**data.table()}
    reference = aj.fit_coefficients(table, parameters=("bias", "scale_factor_error", "k3"))
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


# --- noise records -----------------------------------------------------------------------

DT = 0.01
N = 1500
WHITE = 2e-5  # g


def _record(model, seed) -> NoiseData:
    x = np.asarray(aj.simulate_noise(model, DT, N, key=jax.random.key(seed))) + 1.0003
    return NoiseData(np.arange(N) * DT, x)


NOISE_CASES = {
    "none": aj.WhiteNoise(WHITE),
    "gauss_markov": aj.NoiseSum((aj.WhiteNoise(WHITE), aj.GaussMarkov(WHITE, 0.1))),
    "exp_cosine": aj.NoiseSum((aj.WhiteNoise(WHITE), aj.ExponentialCosine(WHITE, 4.0, 50.0))),
    "random_walk": aj.NoiseSum((aj.WhiteNoise(WHITE), aj.RandomWalk((4 * WHITE) ** 2 / (N * DT)))),
}


@pytest.fixture(scope="module")
def noise_results():
    # Records one at a time: the same compiled fit serves the CLI test below.
    out = {}
    for i, (case, model) in enumerate(NOISE_CASES.items()):
        data = _record(model, seed=100 + i)
        out[case] = (data, diagnose(data))
    return out


def test_noise_filter_matches_the_generic_exact_likelihood():
    rng = np.random.default_rng(0)
    x = rng.normal(size=400).cumsum() * 0.05 + rng.normal(size=400)
    c = jnp.asarray(x - x.mean())
    diffuse = 1e6 * float(jnp.mean(c**2))  # `_noise`'s diffuse prior of the level
    white, sc, alpha, beta, q = 0.8, 0.6, 3.0, 20.0, 0.02
    parts = noise_effects.NoiseComponents(
        jnp.asarray(sc**2), jnp.exp(-alpha * DT), jnp.asarray(beta * DT), jnp.asarray(q * DT)
    )
    _, _, terms = noise_fit.filter_terms(jnp.asarray(white**2), parts, c, diffuse)
    reference = log_likelihood(
        aj.NoiseSum(
            (aj.WhiteNoise(white), aj.ExponentialCosine(sc, alpha, beta), aj.RandomWalk(q))
        ),
        x,
        DT,
    )
    assert float(jnp.sum(terms[1:])) == pytest.approx(float(reference), rel=1e-10)
    # θ = 0: the block is a Gauss–Markov noise.
    parts = eqx.tree_at(lambda p: p.rotation, parts, jnp.asarray(0.0))
    _, _, terms = noise_fit.filter_terms(jnp.asarray(white**2), parts, c, diffuse)
    reference = log_likelihood(
        aj.NoiseSum((aj.WhiteNoise(white), aj.GaussMarkov(sc, 1 / alpha), aj.RandomWalk(q))), x, DT
    )
    assert float(jnp.sum(terms[1:])) == pytest.approx(float(reference), rel=1e-10)


def test_noise_effects_are_nominal_at_zero():
    rng = np.random.default_rng(1)
    c = jnp.asarray(rng.normal(size=300))
    z = jnp.array([0.1, 0.0, -2.0, 0.7])  # ln σ_w, then the slot with the amplitude at 0
    nominal_white, nominal_parts = noise_fit._components(z, 0)
    _, _, nominal = noise_fit.filter_terms(nominal_white, nominal_parts, c, 1e6)
    assert len(effect_library("noise")) == 3
    for i in range(1, 4):
        white, parts = noise_fit._components(z, i)
        assert float(parts.variance) == 0.0 and float(parts.walk) == 0.0
        _, _, terms = noise_fit.filter_terms(white, parts, c, 1e6)
        np.testing.assert_array_equal(terms, nominal)


def test_noise_none(noise_results):
    _, result = noise_results["none"]
    assert result.verdict == "none", result.summary()
    assert all(r["evidence"] < 10 for r in result.ranking)
    assert result.refit["nominal_fit"]["white_sigma_g"] == pytest.approx(WHITE, rel=0.1)
    assert result.where["whiteness"]["p_value"] > 1e-3


@pytest.mark.parametrize(
    "case, name, truth, tolerance",
    [
        ("gauss_markov", "correlation_time_s", 0.1, 0.5),
        ("exp_cosine", "angular_frequency_rad_per_s", 50.0, 0.05),
        ("random_walk", "intensity_g2_per_s", (4 * WHITE) ** 2 / (N * DT), 1.0),
    ],
)
def test_noise_effect_named_and_recovered(noise_results, case, name, truth, tolerance):
    _, result = noise_results[case]
    assert result.verdict == case, result.summary()
    best = result.ranking[0]
    assert best["effect"] == case and best["evidence"] > 10 and best["converged"]
    assert best["params"][name] == pytest.approx(truth, rel=tolerance)
    assert best["params"]["white_sigma_g"] == pytest.approx(WHITE, rel=0.15)
    assert result.gap["after"] < result.gap["before"]


def test_noise_residual_localised(noise_results):
    _, colored = noise_results["exp_cosine"]
    _, walk = noise_results["random_walk"]
    # The exponential-cosine noise shows as a spectral peak near β/2π ≈ 8 Hz, far above
    # the white floor; both leave a correlated residual under the white model.
    assert colored.where["frequency"]["peak_excess_Hz"] == pytest.approx(50 / (2 * np.pi), rel=0.3)
    assert colored.where["frequency"]["peak_excess_ratio"] > 4
    assert colored.where["whiteness"]["p_value"] < 1e-6
    assert walk.where["whiteness"]["p_value"] < 1e-6
    low = walk.where["frequency"]["bands"][0]["psd_over_floor"]
    high = walk.where["frequency"]["bands"][-1]["psd_over_floor"]
    assert low > 4 * high  # a random walk's excess is at the lowest frequencies


def test_noise_constant_record_is_a_data_error():
    data = NoiseData(np.arange(400) * DT, np.full(400, 1.0))
    with pytest.raises(DataError, match="constant"):
        diagnose(data)


# --- the nested-effect rule of the ranking -------------------------------------------------


def _fit(name, k, log_like, held_out=0.5):
    return CandidateFit(name, k, log_like, 1000, held_out, np.zeros(3), 1.0, {})


def test_rank_candidates_resolves_nested_ties():
    nominal = _fit("nominal", 0, 0.0, held_out=1.0)
    nested = {"big": "small"}
    ln_n = np.log(1000)
    # The larger model gains 2 ln L = 2 over the smaller: not significant → the smaller.
    small, big = _fit("small", 1, 40.0), _fit("big", 2, 41.0)
    assert rank_candidates(nominal, [small, big])[0] == "cannot_tell"
    assert rank_candidates(nominal, [small, big], nested=nested)[0] == "small"
    # 2 ln L = 12 (p ≈ 5e-4) with evidence within 6: a real tie that stays cannot_tell.
    big = _fit("big", 2, 46.0)
    assert abs(2 * (46.0 - 40.0) - ln_n) < 6  # the evidence difference
    verdict, _, tied = rank_candidates(nominal, [small, big], nested=nested)
    assert verdict == "cannot_tell" and set(tied) == {"small", "big"}
    # Transitive: huge → big → small (2 ln L = 8.4 on 2 more parameters, p ≈ 0.015).
    huge = _fit("huge", 3, 44.2)
    assert rank_candidates(nominal, [small, huge])[0] == "cannot_tell"
    verdict, _, _ = rank_candidates(nominal, [small, huge], nested={"huge": "big", "big": "small"})
    assert verdict == "small"


# --- the CLI -----------------------------------------------------------------------------

SCHEMA = {"kind", "verdict", "ranking", "gap", "where", "refit"}


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


def test_cli_on_a_noise_record(noise_results, tmp_path):
    data, _ = noise_results["gauss_markov"]
    csv = write_csv(tmp_path / "noise.csv", data)
    out_json, out_png = tmp_path / "n.json", tmp_path / "n.png"
    result = CliRunner().invoke(
        main,
        ["diagnose", str(csv), "--kind", "noise", "--json", str(out_json), "--plot", str(out_png)],
    )
    assert result.exit_code == 0, result.output
    assert "verdict: gauss_markov" in result.output
    doc = json.loads(out_json.read_text())
    assert set(doc) >= SCHEMA and doc["kind"] == "noise" and doc["verdict"] == "gauss_markov"
    assert set(doc["gap"]) >= {"metric", "before", "after", "shrink"}
    assert {"frequency", "whiteness", "time"} <= set(doc["where"])
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


# --- the studies -------------------------------------------------------------------------


# --- a record the library did not make ----------------------------------------------------

MPU6050 = Path(__file__).parent / "data" / "mpu6050_static_az_counts.txt.gz"


def _mpu6050():
    # A real static record (InvenSense MPU-6050, 100 Hz, 44 930 samples, z axis, counts of
    # 1/16384 g; MIT licence, tests/data/LICENSE.mpu6050).
    counts = np.loadtxt(MPU6050, comments="#")
    return np.arange(counts.size) * 0.01, counts / 16384.0


def test_real_mems_record_and_a_line_the_library_does_not_model():
    t, a = _mpu6050()
    clean, lined = diagnose_many(
        [NoiseData(t, a), NoiseData(t, a + 1.5e-3 * np.sin(2 * np.pi * 0.56 * t + 0.3))]
    )
    # Its held-out part is white at 4.6 mg (the Allan deviation follows τ^-1/2 to 10 s):
    # `none` is the honest answer, with the remaining gap at the floor.
    assert clean.verdict == "none", clean.summary()
    assert clean.remaining_gap["over_floor"] <= 1.0
    # A 1.5 mg line at 0.56 Hz (1 % of the variance): no noise that cannot whiten it is named
    # for it. Either the narrow-band exp-cosine whitens it (then at the line's frequency) or
    # the verdict is `unexplained` with the line reported.
    assert lined.verdict in ("exp_cosine", "unexplained"), lined.summary()
    if lined.verdict == "exp_cosine":
        params = next(e for e in lined.ranking if e["effect"] == "exp_cosine")["params"]
        assert params["period_s"] == pytest.approx(1 / 0.56, rel=0.02)
    else:
        line = lined.remaining_gap["periodic_line"]
        assert line["frequency_Hz"] == pytest.approx(0.56, rel=0.01)


@pytest.mark.slow
def test_cli_on_a_real_record_prints_no_xla_logs(tmp_path):
    import subprocess
    import sys

    t, a = _mpu6050()
    csv = tmp_path / "mpu.csv"
    write_csv(csv, NoiseData(t, a))
    cli = Path(sys.executable).parent / "accel-jax"
    run = subprocess.run(
        [str(cli), "diagnose", str(csv)], capture_output=True, text=True, timeout=600
    )
    assert run.returncode == 0, run.stderr
    assert "verdict: none" in run.stdout
    assert run.stderr.strip() == ""  # nothing from XLA on the user's terminal
