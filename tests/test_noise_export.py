"""Export of an identified accelerometer noise model (accel_jax/_noise/export.py): kalibr,
gnss-ins-sim and IEEE units against hand-computed values, the conversions' round trips and
their cross-checks with the noise models' discrete forms, N = σ√Δt against the Allan
deviation (and the one-sided Welch PSD, 2N²) of a simulated record, and bad input."""

import math

import numpy as np
import pytest
import scipy.signal

import accel_jax as aj
from accel_jax._noise import GaussMarkov, RandomWalk, WhiteNoise
from accel_jax._noise.export import (
    AccelNoiseTerms,
    density_to_discrete,
    density_to_one_sided_asd,
    density_to_vrw,
    discrete_to_density,
    discrete_to_gauss_markov,
    discrete_to_random_walk,
    gauss_markov_to_discrete,
    kalibr_yaml,
    micro_g_to_si,
    one_sided_asd_to_density,
    random_walk_to_discrete,
    si_to_micro_g,
    to_gnss_ins_sim,
    to_ieee,
    to_kalibr,
    unit_to_si,
    vrw_to_density,
)

G = 9.80665

# A navigation-grade axis in g: N = 60 µg/√Hz, K = 2 µg/√s, B = 25 µg (GM, τ_c = 300 s),
# Q = 10 µg·s, recorded at 200 Hz.
TERMS = AccelNoiseTerms(
    noise_density=60e-6,
    random_walk=2e-6,
    bias_instability=25e-6,
    bias_correlation_time=300.0,
    quantization=10e-6,
    sample_rate=200.0,
    unit="g",
)
# The same in SI, by hand.
N_SI = 60e-6 * 9.80665  # 5.88399e-4 m/s²/√Hz
K_SI = 2e-6 * 9.80665  # 1.96133e-5 m/s²/√s = m/s³/√Hz
B_SI = 25e-6 * 9.80665  # 2.4516625e-4 m/s²
Q_SI = 10e-6 * 9.80665  # 9.80665e-5 m/s


def test_hand_values():
    # The constants above, written out.
    assert N_SI == pytest.approx(5.88399e-4, rel=1e-12)
    assert K_SI == pytest.approx(1.96133e-5, rel=1e-12)
    assert B_SI == pytest.approx(2.4516625e-4, rel=1e-12)


def test_in_si_and_units():
    si = TERMS.in_si()
    assert si.unit == "m/s^2"
    assert si.noise_density == pytest.approx(N_SI, rel=1e-14)
    assert si.random_walk == pytest.approx(K_SI, rel=1e-14)
    assert si.bias_instability == pytest.approx(B_SI, rel=1e-14)
    assert si.quantization == pytest.approx(Q_SI, rel=1e-14)
    assert (si.bias_correlation_time, si.sample_rate) == (300.0, 200.0)
    assert si.in_si() == si
    assert AccelNoiseTerms(noise_density=1.0, unit="m/s²").unit == "m/s^2"
    assert aj.STANDARD_GRAVITY == G


def test_kalibr_entries():
    out = to_kalibr(TERMS)
    assert out["accelerometer_noise_density"] == pytest.approx(5.88399e-4, rel=1e-12)
    assert out["accelerometer_random_walk"] == pytest.approx(1.96133e-5, rel=1e-12)
    assert out["update_rate"] == 200.0
    # Discrete (kalibr wiki): σ_wd = σ_w/√Δt = 5.88399e-4·√200, σ_bd = σ_b·√Δt = 1.96133e-5/√200.
    assert out["accelerometer_noise_density_discrete"] == pytest.approx(
        5.88399e-4 * 200**0.5, rel=1e-12
    )
    assert out["accelerometer_noise_density_discrete"] == pytest.approx(8.3212e-3, rel=1e-4)
    assert out["accelerometer_random_walk_discrete"] == pytest.approx(
        1.96133e-5 / 200**0.5, rel=1e-12
    )
    # kalibr's own discrete rule (ConfigReader.py: density / sqrt(1/update_rate)).
    assert out["accelerometer_noise_density_discrete"] == pytest.approx(
        out["accelerometer_noise_density"] / math.sqrt(1.0 / out["update_rate"]), rel=1e-14
    )
    # The IMU's message rate overrides the record's.
    assert to_kalibr(TERMS, update_rate=100.0)["accelerometer_noise_density_discrete"] == (
        pytest.approx(5.88399e-4 * 10.0, rel=1e-12)
    )
    # kalibr's model has no B or Q: dropped, or refused when strict.
    with pytest.raises(ValueError, match="kalibr cannot carry B .*; Q"):
        to_kalibr(TERMS, strict=True)
    plain = AccelNoiseTerms(noise_density=1e-3, random_walk=1e-4, unit="m/s^2")
    assert to_kalibr(plain, update_rate=50, strict=True)["update_rate"] == 50.0


def _parse_flat_yaml(text):
    """A minimal reader of the flat `key: value` YAML kalibr_yaml writes (comments skipped)."""
    out = {}
    for line in text.splitlines():
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        key, _, value = line.partition(": ")
        value = value.strip()
        out[key] = value.strip('"') if value.startswith('"') else float(value)
    return out


def test_kalibr_yaml_parses():
    text = kalibr_yaml(TERMS, rostopic="/imu0")
    expected = {
        "rostopic": "/imu0",
        "accelerometer_noise_density": to_kalibr(TERMS)["accelerometer_noise_density"],
        "accelerometer_random_walk": to_kalibr(TERMS)["accelerometer_random_walk"],
        "update_rate": 200.0,
    }
    assert _parse_flat_yaml(text) == expected  # floats round-trip exactly
    assert "Not in kalibr's model: bias instability" in text
    assert "quantization" in text
    # Exponent forms carry a '.': PyYAML (YAML 1.1) reads "1e-05" as a string.
    tiny = AccelNoiseTerms(noise_density=1e-5, random_walk=1e-7, unit="m/s^2", sample_rate=100)
    tiny_text = kalibr_yaml(tiny)
    assert "accelerometer_noise_density: 1.0e-05\n" in tiny_text
    assert "accelerometer_random_walk: 1.0e-07\n" in tiny_text
    yaml = pytest.importorskip("yaml")
    assert yaml.safe_load(text) == expected
    loaded = yaml.safe_load(tiny_text)
    assert loaded["accelerometer_noise_density"] == 1e-5
    assert loaded["accelerometer_random_walk"] == 1e-7
    assert isinstance(loaded["update_rate"], float)


def test_gnss_ins_sim_entries():
    out = to_gnss_ins_sim(TERMS)
    assert set(out) == {"accel_b", "accel_vrw", "accel_b_stability", "accel_b_corr"}
    for value in out.values():
        assert value.shape == (3,)
    np.testing.assert_array_equal(out["accel_b"], 0.0)
    # accel_vrw [m/s/√hr] = 60·N: 5.88399e-4·60 = 0.03530394; gnss-ins-sim divides by 60 and
    # draws vrw/√dt per sample (imu_model.py, pathgen.py acc_gen).
    np.testing.assert_allclose(out["accel_vrw"], 0.03530394, rtol=1e-12)
    np.testing.assert_allclose(out["accel_vrw"] / 60 / math.sqrt(1 / 200), 8.3212e-3, rtol=1e-4)
    np.testing.assert_allclose(out["accel_b_stability"], 2.4516625e-4, rtol=1e-12)
    np.testing.assert_allclose(out["accel_b_corr"], 300.0)
    # No random-walk bias or quantization in gnss-ins-sim.
    with pytest.raises(ValueError, match="gnss-ins-sim cannot carry K .*; Q"):
        to_gnss_ins_sim(TERMS, strict=True)
    # A bias instability without a correlation time is not a GM: left out (inf, 0) or refused.
    flicker = AccelNoiseTerms(noise_density=60e-6, bias_instability=25e-6, unit="g")
    out = to_gnss_ins_sim(flicker)
    np.testing.assert_array_equal(out["accel_b_stability"], 0.0)
    assert np.all(np.isinf(out["accel_b_corr"]))
    with pytest.raises(ValueError, match="bias_correlation_time"):
        to_gnss_ins_sim(flicker, strict=True)
    white = AccelNoiseTerms(noise_density=1e-3, unit="m/s^2")
    np.testing.assert_allclose(to_gnss_ins_sim(white, strict=True)["accel_vrw"], 0.06)


def test_ieee_entries():
    out = to_ieee(TERMS)
    values = {key: entry["value"] for key, entry in out.items()}
    units = {key: entry["unit"] for key, entry in out.items()}
    assert values["N"] == pytest.approx(5.88399e-4 * 60, rel=1e-12)  # 0.03530394 m/s/√h
    assert units["N"] == "m/s/√h"
    assert values["N_ug"] == pytest.approx(60.0, rel=1e-12)
    assert units["N_ug"] == "µg/√Hz"
    assert values["N_si"] == pytest.approx(5.88399e-4, rel=1e-12)
    assert values["B"] == pytest.approx(25.0, rel=1e-12) and units["B"] == "µg"
    assert values["B_si"] == pytest.approx(2.4516625e-4, rel=1e-12)
    # K: 1.96133e-5 m/s²/√s · 3600^{3/2} = 1.96133e-5·216000 = 4.2364728 m/s/h^{3/2};
    # 2 µg/√s · 60 = 120 µg/√h.
    assert values["K"] == pytest.approx(4.2364728, rel=1e-12)
    assert units["K"] == "m/s/h^(3/2)"
    assert values["K_ug"] == pytest.approx(120.0, rel=1e-12) and units["K_ug"] == "µg/√h"
    assert values["K_si"] == pytest.approx(1.96133e-5, rel=1e-12)
    assert values["Q"] == pytest.approx(9.80665e-5, rel=1e-12) and units["Q"] == "m/s"
    assert values["tau_c"] == 300.0
    assert out["N"]["name"] == "velocity random walk" and out["N"]["symbol"] == "N"
    assert out["K"]["name"] == "acceleration random walk"
    assert out["B"]["name"] == "bias instability"
    assert out["Q"]["name"] == "quantization noise"
    # Absent terms are absent.
    assert set(to_ieee(AccelNoiseTerms(noise_density=1e-3, unit="m/s^2"))) == {
        "N",
        "N_ug",
        "N_si",
    }


def test_conversions_hand_values_and_round_trips():
    assert unit_to_si(60e-6, "g") == pytest.approx(5.88399e-4, rel=1e-14)
    assert unit_to_si(3.0, "m/s^2") == 3.0
    assert si_to_micro_g(9.80665e-6) == pytest.approx(1.0, rel=1e-14)
    assert micro_g_to_si(1.0) == pytest.approx(9.80665e-6, rel=1e-14)
    assert density_to_discrete(1e-3, 400) == pytest.approx(0.02, rel=1e-14)  # 1e-3·√400
    assert random_walk_to_discrete(1e-3, 400) == pytest.approx(5e-5, rel=1e-14)  # 1e-3/√400
    assert density_to_vrw(1e-3) == pytest.approx(0.06, rel=1e-14)
    assert density_to_one_sided_asd(1.0) == pytest.approx(math.sqrt(2), rel=1e-14)
    x = np.array([1e-6, 3e-4, 2.5])
    for fs in (1.0, 100.0, 1000.0):
        np.testing.assert_allclose(discrete_to_density(density_to_discrete(x, fs), fs), x)
        np.testing.assert_allclose(
            discrete_to_random_walk(random_walk_to_discrete(x, fs), fs), x, rtol=1e-14
        )
    np.testing.assert_allclose(vrw_to_density(density_to_vrw(x)), x, rtol=1e-14)
    np.testing.assert_allclose(micro_g_to_si(si_to_micro_g(x)), x, rtol=1e-14)
    np.testing.assert_allclose(one_sided_asd_to_density(density_to_one_sided_asd(x)), x)
    # GM: ρ = e^{−Δt/τ_c}, σ_w = σ_b √(1 − ρ²); at 200 Hz, τ_c = 300 s: ρ = e^{−1/60000}.
    rho, drive = gauss_markov_to_discrete(2.4516625e-4, 300.0, 200.0)
    assert rho == pytest.approx(math.exp(-1 / 60000), rel=1e-15)
    assert drive == pytest.approx(2.4516625e-4 * math.sqrt(1 - math.exp(-2 / 60000)), rel=1e-12)
    sigma, tau = discrete_to_gauss_markov(rho, drive, 200.0)
    assert sigma == pytest.approx(2.4516625e-4, rel=1e-9)
    assert tau == pytest.approx(300.0, rel=1e-9)


def test_conversions_match_the_noise_models_discrete_forms():
    dt = 1 / 200
    f, q, *_ = GaussMarkov(sigma=0.3, correlation_time=2.0).state_space(dt)
    rho, drive = gauss_markov_to_discrete(0.3, 2.0, 200)
    assert rho == pytest.approx(float(f[0, 0]), rel=1e-14)
    assert drive**2 == pytest.approx(float(q[0, 0]), rel=1e-12)
    # RandomWalk(q): var(x_{k+1} − x_k) = qΔ, K = √q.
    _, q, *_ = RandomWalk(intensity=4e-6).state_space(dt)
    assert random_walk_to_discrete(2e-3, 200) ** 2 == pytest.approx(float(q[0, 0]), rel=1e-12)
    # WhiteNoise(σ_d) is the per-sample σ: N = σ_d √Δt.
    *_, r = WhiteNoise(sigma=0.05).state_space(dt)
    assert density_to_discrete(0.05 * math.sqrt(dt), 200) ** 2 == pytest.approx(float(r))


def test_density_is_the_allan_deviation_of_a_white_record():
    # White noise of per-sample σ_d at f_s: ADEV(τ = Δt) = σ_d, ADEV(τ) = N/√τ with
    # N = σ_d·√Δt = σ_d/√f_s; the one-sided Welch PSD is 2N² (the ASD √2·N).
    fs, sigma_d, n = 100.0, 0.01, 200_000
    x = np.random.default_rng(7).normal(0.0, sigma_d, n)
    density = discrete_to_density(sigma_d, fs)
    assert density == pytest.approx(0.001, rel=1e-14)
    taus, adev = aj.noise.allan_deviation(x, 1 / fs, [1, 10, 100])
    taus, adev = np.asarray(taus), np.asarray(adev)
    assert adev[0] == pytest.approx(sigma_d, rel=0.02)
    np.testing.assert_allclose(adev * np.sqrt(taus), density, rtol=0.05)
    assert adev[2] == pytest.approx(density, rel=0.05)  # τ = 1 s
    _, psd = scipy.signal.welch(x, fs=fs, nperseg=4096)
    one_sided = math.sqrt(np.mean(psd[1:-1]))
    assert one_sided == pytest.approx(density_to_one_sided_asd(density), rel=0.02)
    assert one_sided_asd_to_density(one_sided) == pytest.approx(density, rel=0.02)
    # Back through kalibr's rule: σ_d = density/√Δt.
    kalibr = to_kalibr(
        AccelNoiseTerms(noise_density=density, random_walk=1e-6, unit="m/s^2"), update_rate=fs
    )
    assert kalibr["accelerometer_noise_density_discrete"] == pytest.approx(sigma_d, rel=1e-14)


def test_random_walk_is_the_allan_slope_of_a_simulated_bias():
    # b_{k+1} = b_k + K√Δt ξ: ADEV(τ) = K √(τ/3) for τ ≫ Δt.
    fs, k, n = 10.0, 1e-3, 100_000
    steps = np.random.default_rng(3).normal(0.0, random_walk_to_discrete(k, fs), n)
    taus, adev = aj.noise.allan_deviation(np.cumsum(steps), 1 / fs, [100, 300, 1000])
    np.testing.assert_allclose(np.asarray(adev), k * np.sqrt(np.asarray(taus) / 3), rtol=0.3)


def test_from_mapping():
    terms = AccelNoiseTerms.from_mapping(
        {"N": 60e-6, "K": None, "B": {"value": 25e-6, "supported": True}, "Q": 1e-5},
        "g",
        200.0,
        bias_correlation_time=300.0,
    )
    assert terms == AccelNoiseTerms(
        noise_density=60e-6,
        bias_instability=25e-6,
        bias_correlation_time=300.0,
        quantization=1e-5,
        sample_rate=200.0,
        unit="g",
    )
    fit_like = {
        "N": {"value": 1e-3, "lower": 9e-4, "upper": 1.1e-3, "supported": True, "unit": "m/s^2"},
        "K": {"value": 5e-5, "supported": False},
        "R": {"value": 1e-9, "supported": False},
    }
    terms = AccelNoiseTerms.from_mapping(fit_like, "m/s^2")
    assert (terms.noise_density, terms.random_walk) == (1e-3, None)
    with pytest.raises(ValueError, match="Unknown Allan term"):
        AccelNoiseTerms.from_mapping({"N": 1.0, "X": 2.0}, "g")
    with pytest.raises(ValueError, match="rate ramp"):
        AccelNoiseTerms.from_mapping({"N": 1.0, "R": 2.0}, "g")
    with pytest.raises(ValueError, match="'N'"):
        AccelNoiseTerms.from_mapping({"K": 1.0}, "g")
    with pytest.raises(ValueError, match="without 'value'"):
        AccelNoiseTerms.from_mapping({"N": {"lower": 1.0}}, "g")


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"noise_density": float("nan")}, "noise_density must be finite"),
        ({"noise_density": -1.0}, "noise_density must be finite and ≥ 0"),
        ({"noise_density": None}, "noise_density must be a real number"),
        ({"noise_density": "1e-3"}, "noise_density must be a real number"),
        ({"noise_density": [1.0, 2.0]}, "noise_density must be a real number"),
        ({"random_walk": float("inf")}, "random_walk must be finite"),
        ({"quantization": -1e-6}, "quantization must be finite"),
        ({"sample_rate": 0.0}, "sample_rate must be > 0"),
        ({"unit": "ft/s^2"}, "Unknown unit"),
        ({"unit": None}, "unit must be a string"),
        ({"bias_correlation_time": 10.0}, "needs bias_instability"),
        ({"bias_instability": 1e-6, "bias_correlation_time": 0.0}, "must be > 0"),
    ],
)
def test_bad_terms(kwargs, match):
    base = {"noise_density": 1e-3, "unit": "m/s^2"}
    with pytest.raises(ValueError, match=match):
        AccelNoiseTerms(**{**base, **kwargs})


def test_bad_export_input():
    no_rate = AccelNoiseTerms(noise_density=1e-3, random_walk=1e-5, unit="m/s^2")
    with pytest.raises(ValueError, match="update_rate"):
        to_kalibr(no_rate)
    with pytest.raises(ValueError, match="update_rate must be finite and > 0"):
        to_kalibr(no_rate, update_rate=-5.0)
    no_walk = AccelNoiseTerms(noise_density=1e-3, unit="m/s^2", sample_rate=100)
    with pytest.raises(ValueError, match="accelerometer_random_walk > 0"):
        to_kalibr(no_walk)
    with pytest.raises(ValueError, match="Expected AccelNoiseTerms"):
        to_ieee({"N": 1e-3})
    with pytest.raises(ValueError, match="rostopic"):
        kalibr_yaml(TERMS, rostopic="a\nb")
    with pytest.raises(ValueError, match="sample_rate"):
        density_to_discrete(1e-3, 0.0)
    with pytest.raises(ValueError, match="correlation_time"):
        gauss_markov_to_discrete(1.0, -1.0, 100.0)
    with pytest.raises(ValueError, match="rho"):
        discrete_to_gauss_markov(1.0, 0.1, 100.0)
    with pytest.raises(ValueError, match="Unknown unit"):
        unit_to_si(1.0, "mg")


def test_public_names():
    for name in ("AccelNoiseTerms", "to_kalibr", "kalibr_yaml", "to_gnss_ins_sim", "to_ieee"):
        assert getattr(aj.noise, name) is getattr(aj._noise, name)
