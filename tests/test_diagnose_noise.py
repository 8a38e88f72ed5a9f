"""The sim-to-real diagnosis of static noise records (accel_jax.diagnose.noise, its
effects, fit), the ranking's nested-effect rule, its CLI use and a real MEMS
record: simulate-then-diagnose-then-recover against `simulate_noise`, and the fast noise
filter against the generic exact likelihood of `accel_jax._noise`."""

import json
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from click.testing import CliRunner

import accel_jax as aj
from accel_jax._data import DataError, NoiseData, write_csv
from accel_jax._noise import log_likelihood
from accel_jax.cli import main
from accel_jax.diagnose import (
    CandidateFit,
    diagnose,
    diagnose_many,
    effect_library,
    rank_candidates,
)
from accel_jax.diagnose.noise import fit as noise_fit
from accel_jax.diagnose.noise.effects import NoiseComponents

ROOT = Path(__file__).resolve().parent.parent

DT = 0.01
N = 1500
WHITE = 2e-5  # g
NOISE_CASES = {
    "none": aj.noise.WhiteNoise(WHITE),
    "gauss_markov": aj.noise.NoiseSum(
        (aj.noise.WhiteNoise(WHITE), aj.noise.GaussMarkov(WHITE, 0.1))
    ),
    "exp_cosine": aj.noise.NoiseSum(
        (aj.noise.WhiteNoise(WHITE), aj.noise.ExponentialCosine(WHITE, 4.0, 50.0))
    ),
    "random_walk": aj.noise.NoiseSum(
        (aj.noise.WhiteNoise(WHITE), aj.noise.RandomWalk((4 * WHITE) ** 2 / (N * DT)))
    ),
}
SCHEMA = {"kind", "verdict", "ranking", "gap", "where", "refit"}
MPU6050 = Path(__file__).parent / "data" / "mpu6050_static_az_counts.txt.gz"


def _record(model, seed) -> NoiseData:
    x = np.asarray(aj.noise.simulate_noise(model, DT, N, key=jax.random.key(seed))) + 1.0003
    return NoiseData(np.arange(N) * DT, x)


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
    parts = NoiseComponents(
        jnp.asarray(sc**2), jnp.exp(-alpha * DT), jnp.asarray(beta * DT), jnp.asarray(q * DT)
    )
    _, _, terms = noise_fit.filter_terms(jnp.asarray(white**2), parts, c, diffuse)
    reference = log_likelihood(
        aj.noise.NoiseSum(
            (
                aj.noise.WhiteNoise(white),
                aj.noise.ExponentialCosine(sc, alpha, beta),
                aj.noise.RandomWalk(q),
            )
        ),
        x,
        DT,
    )
    assert float(jnp.sum(terms[1:])) == pytest.approx(float(reference), rel=1e-10)
    # θ = 0: the block is a Gauss–Markov noise.
    parts = eqx.tree_at(lambda p: p.rotation, parts, jnp.asarray(0.0))
    _, _, terms = noise_fit.filter_terms(jnp.asarray(white**2), parts, c, diffuse)
    reference = log_likelihood(
        aj.noise.NoiseSum(
            (
                aj.noise.WhiteNoise(white),
                aj.noise.GaussMarkov(sc, 1 / alpha),
                aj.noise.RandomWalk(q),
            )
        ),
        x,
        DT,
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


def test_fitted_model_intervals_cover_the_truth():
    """The numbers a Kalman filter needs, with 95 % intervals from the observed
    information: simulate 24 white + Gauss–Markov records, diagnose them, and count how
    often each interval holds the truth. Calibrated intervals hold it 95 % of the time:
    "at most 5 misses of 24" then fails with probability 0.1 % (binomial). It is a check
    against gross errors (a variance instead of a standard deviation, a missing factor n):
    intervals 1.5× too narrow (coverage 81 %) still pass it with probability 0.7."""
    truth = {"white_sigma_g": WHITE, "sigma_g": 1.5 * WHITE, "correlation_time_s": 0.1}
    model = aj.noise.NoiseSum(
        (aj.noise.WhiteNoise(truth["white_sigma_g"]), aj.noise.GaussMarkov(truth["sigma_g"], 0.1))
    )
    results = diagnose_many([_record(model, seed=500 + i) for i in range(24)])
    hits = {name: 0 for name in truth}
    counted = 0
    for result in results:
        fitted = result.refit["model_parameters"]
        if fitted["model"] != "white+gauss_markov":
            continue
        counted += 1
        for name, value in truth.items():
            entry = fitted["parameters"][name]
            assert entry["low"] < entry["value"] < entry["high"]
            hits[name] += entry["low"] <= value <= entry["high"]
        rate = fitted["parameters"]["rate_per_s"]
        tau = fitted["parameters"]["correlation_time_s"]
        assert rate["value"] * tau["value"] == pytest.approx(1.0)
        assert rate["low"] * tau["high"] == pytest.approx(1.0)
    assert counted >= 20, [r.verdict for r in results]
    for name, hit in hits.items():
        assert hit >= counted - 5, (name, hit, counted)
    named = next(r for r in results if r.verdict == "gauss_markov")
    line = next(x for x in named.summary().splitlines() if x.startswith("model ("))
    assert "95% intervals" in line and "τ_c = " in line and "σ_w = " in line


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
    assert "model (white+gauss_markov; 95% intervals): σ = " in result.output
    doc = json.loads(out_json.read_text())
    assert set(doc) >= SCHEMA and doc["kind"] == "noise" and doc["verdict"] == "gauss_markov"
    assert set(doc["gap"]) >= {"metric", "before", "after", "shrink"}
    assert {"frequency", "whiteness", "time"} <= set(doc["where"])
    assert out_png.stat().st_size > 10_000
    # --out DIR: json, plot and the printed summary under DIR; a relative --json goes there.
    out = tmp_path / "out"
    args = ["diagnose", str(csv), "--kind", "noise", "--out", str(out), "--json", "d.json"]
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in out.iterdir()) == ["d.json", "diagnosis.png", "diagnosis.txt"]
    assert "verdict: gauss_markov" in (out / "diagnosis.txt").read_text()
    again = CliRunner().invoke(main, args)
    assert again.exit_code != 0 and "--force" in again.output


def _mpu6050():
    # A real static record (InvenSense MPU-6050, 100 Hz, 44 930 samples, z axis, counts of
    # 1/16384 g; MIT licence, tests/data/LICENSE.mpu6050).
    counts = np.loadtxt(MPU6050, comments="#")
    return np.arange(counts.size) * 0.01, counts / 16384.0


def test_real_mems_record_and_a_line_the_library_does_not_model():
    t, a = _mpu6050()
    jump = 49 / 16384 * (t >= 150.0)  # a bias jump of 49 counts (3.0 mg) at 150 s
    clean, lined, stepped = diagnose_many(
        [
            NoiseData(t, a),
            NoiseData(t, a + 1.5e-3 * np.sin(2 * np.pi * 0.56 * t + 0.3)),
            NoiseData(t, a + jump),
        ]
    )
    # The real record with a step in its level (outside the library; its spectrum is a
    # random walk's): unexplained, the step found where it is and as large, on the grid.
    assert "unexplained" in stepped.verdict and "random_walk" not in stepped.verdict
    (shift,) = stepped.where["sensor_effects"]["held_out"]["level_shifts"]
    assert shift["time_s"] == pytest.approx(150.0, abs=0.5)
    assert shift["size"] == pytest.approx(49 / 16384, rel=0.1)
    assert "level steps by" in stepped.reason
    # Its held-out part is white at 4.6 mg (the Allan deviation follows τ^-1/2 to 10 s):
    # `none` is the honest answer, with the remaining gap at the floor.
    assert clean.verdict == "none", clean.summary()
    assert clean.remaining_gap["over_floor"] <= 1.0
    # A 1.5 mg line at 0.56 Hz (1 % of the variance): no noise that cannot whiten it is named
    # for it. The exact one-effect diagnosis leaves it unexplained (or a narrow-band
    # exp-cosine whitens it), and the forward selection names the line, at its frequency.
    assert lined.verdict in ("exp_cosine", "sinusoid"), lined.summary()
    if lined.verdict == "exp_cosine":
        params = next(e for e in lined.ranking if e["effect"] == "exp_cosine")["params"]
        assert params["period_s"] == pytest.approx(1 / 0.56, rel=0.02)
    else:
        found = lined.where["sensor_effects"]["parameters"]["sinusoid"][0]
        assert found["frequency_Hz"] == pytest.approx(0.56, rel=0.01)
        assert found["amplitude"] == pytest.approx(1.5e-3, rel=0.2)
    assert clean.where["allan"]["tau_s"][0] == pytest.approx(t[1] - t[0])


def test_composite_and_long_records(tmp_path):
    """Beyond the three library noises: a record on a coarse output grid with a line gets
    the composite verdict of the forward selection; a record longer than the exact limit
    is diagnosed by the selection alone (named, plotted, JSON)."""
    import sys

    from accel_jax.diagnose.noise import EXACT_LIMIT
    from accel_jax.diagnose.report import write_json
    from accel_jax.report.figures.diagnosis import save_plot

    sys.path.insert(0, str(ROOT / "studies"))
    import noise_truth

    rng = np.random.default_rng(21)
    n = 6000
    x = noise_truth.record(
        rng, n, DT, {"white": 2e-3, "lines": [(2.2, 1e-3)], "quantization": 3e-3, "level": 1}
    )
    composite = diagnose(NoiseData(np.arange(n) * DT, x))
    assert set(composite.verdict.split("+")) >= {"sinusoid", "quantization"}, composite.summary()
    assert composite.where["sensor_effects"]["quantization"]["step"] == pytest.approx(3e-3, 0.05)
    n = EXACT_LIMIT + 5000
    x = noise_truth.record(rng, n, DT, {"white": 2e-3, "gauss_markov": (2e-3, 0.1), "level": -1})
    long = diagnose(NoiseData(np.arange(n) * DT, x))
    assert long.verdict == "gauss_markov", long.summary()
    assert "forward selection alone" in long.notes[0]
    gm = long.where["sensor_effects"]["parameters"]["gauss_markov"]
    assert gm["correlation_time_s"] == pytest.approx(0.1, rel=0.15)
    save_plot(long, tmp_path / "long.png")
    write_json(long, tmp_path / "long.json")
    assert json.loads((tmp_path / "long.json").read_text())["verdict"] == "gauss_markov"


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


def test_fitted_model_spectrum_integrates_to_its_variance():
    """The diagnose figure draws the fitted model's spectrum on the Welch scale (2Δσ² for
    white noise): over 0 … 1/(2Δ) it integrates to the model's variance, σ_w² + σ²."""
    from accel_jax.report.figures.diagnosis import _model_psd

    dt = 0.01
    f = np.linspace(0, 0.5 / dt, 200001)
    for extra in (
        {"sigma_g": {"value": 3e-5}, "correlation_time_s": {"value": 0.05}},
        {
            "sigma_g": {"value": 3e-5},
            "decay_rate_per_s": {"value": 4.0},
            "angular_frequency_rad_per_s": {"value": 50.0},
        },
    ):
        model = {"model": "m", "parameters": {"white_sigma_g": {"value": 2e-5}, **extra}}
        variance = np.trapezoid(_model_psd(model, f, dt), f)
        assert variance == pytest.approx(2e-5**2 + 3e-5**2, rel=1e-4)
