"""A sensor's signal chain in a static record: the white noise its ADC or amplifier adds
after the output low-pass (`filter_floor`, a part of `bandlimit`), fitted whether or not
the record lies on a grid. Records from the independent truth generator
(studies/noise_truth.py: `scipy.signal.butter` order 2 on the sensor's noise, white noise
added after it); the fitted levels checked against model-free estimates from the record's
own periodogram (Welch), below the corner and near the Nyquist frequency."""

import math
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import signal

import accel_jax as aj
from accel_jax._noise import chain_filters, sensor_refine
from accel_jax._noise.chain_filters import BesselLowPass, DecimatingAverage, MovingAverage
from accel_jax._noise.models import ButterworthLowPass, HighFrequencyNoise
from accel_jax.diagnose.noise.sensor import _describe
from accel_jax.report.text.noise import _selection_lines

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "studies"))
import noise_truth  # noqa: E402

DT = 0.01  # 100 Hz
CORNER = 18.0  # Hz
WHITE = 1e-3  # the sensor's white noise, ahead of the filter
AFTER = 3e-4  # the chain's white noise after it


@pytest.fixture(autouse=True)
def _x64():
    with jax.enable_x64(True):
        yield


def _band_density(x, lo, hi):
    """The record's two-sided density per sample (variance units) over [lo, hi] Hz, from
    Welch's averaged periodogram: model-free."""
    f, p = signal.welch(x, 1 / DT, nperseg=1024)
    band = (f >= lo) & (f <= hi)
    return float(np.mean(p[band])) / (2 * DT)


@pytest.mark.parametrize("order", [1, 2, 3, 4])
def test_butterworth_gain_is_scipys(order):
    """`ButterworthLowPass`'s power gain of order N is |H|² of `scipy.signal.butter(N)`
    (the bilinear design), to 1e-9 over the whole band."""
    corner = 18.0
    f = np.linspace(0.0, 0.5 / DT, 2001)
    sos = signal.butter(order, corner, fs=1 / DT, output="sos")
    _, h = signal.sosfreqz(sos, worN=f, fs=1 / DT)
    ours = ButterworthLowPass(corner, order=order).gain(2 * np.pi * f * DT, DT)
    np.testing.assert_allclose(np.asarray(ours), np.abs(h) ** 2, rtol=1e-9, atol=1e-14)


def test_butterworth_order_is_checked():
    with pytest.raises(ValueError, match="order must be 1, 2, 3 or 4"):
        ButterworthLowPass(18.0, order=5)


@pytest.mark.parametrize("order", [2, 3, 4])
def test_bessel_gain_is_scipys(order):
    """`BesselLowPass`'s power gain of order N at its −3 dB point f_b is |H|² of
    `scipy.signal.bessel(N, f_b, norm="mag")` (the bilinear design, prewarped), to 1e-9."""
    f = np.linspace(0.0, 0.5 / DT, 2001)
    for corner in (3.0, 18.0, 45.0):
        sos = signal.bessel(order, corner, norm="mag", fs=1 / DT, output="sos")
        _, h = signal.sosfreqz(sos, worN=f, fs=1 / DT)
        ours = BesselLowPass(corner, order=order).gain(2 * np.pi * f * DT, DT)
        np.testing.assert_allclose(np.asarray(ours), np.abs(h) ** 2, rtol=1e-9, atol=1e-14)


@pytest.mark.parametrize("taps", [2, 5, 8, 33])
def test_moving_average_gain_and_corner_are_scipys(taps):
    """`MovingAverage`'s power gain is |H|² of the boxcar FIR (`scipy.signal.freqz`), and its
    −3 dB point is where that gain is one half."""
    f = np.linspace(0.0, 0.5 / DT, 4001)
    _, h = signal.freqz(np.ones(taps) / taps, 1.0, worN=f, fs=1 / DT)
    ours = MovingAverage(taps).gain(2 * np.pi * f * DT, DT)
    np.testing.assert_allclose(np.asarray(ours), np.abs(h) ** 2, rtol=1e-9, atol=1e-14)
    corner = chain_filters.moving_average_corner(taps)
    _, at = signal.freqz(np.ones(taps) / taps, 1.0, worN=[corner], fs=1.0)
    assert abs(at[0]) ** 2 == pytest.approx(0.5, abs=1e-9)
    assert chain_filters.nearest_taps(corner * 1.01) == taps


def test_the_low_pass_code_selects_its_shape():
    """`low_pass_gain` of a traced code is the gain of the shape it names, and its corner
    derivative (the fits' gradient) matches a central difference."""
    omega = np.linspace(0.0, np.pi, 501)
    cases = {
        2: ButterworthLowPass.discrete_gain(omega, 0.4, 2),
        chain_filters.BESSEL_CODE + 3: BesselLowPass.discrete_gain(omega, 0.4, 3),
        chain_filters.MOVING_AVERAGE_CODE + 6: MovingAverage.discrete_gain(omega, 6),
        chain_filters.DECIMATION_CODE + 300 + 8: DecimatingAverage.discrete_gain(omega, 3, 8),
    }
    for code, expected in cases.items():
        ours = jax.jit(chain_filters.low_pass_gain)(omega, 0.4, float(code))
        np.testing.assert_allclose(np.asarray(ours), np.asarray(expected), rtol=1e-12, atol=1e-15)
    code = float(chain_filters.BESSEL_CODE + 4)
    total = lambda c: jnp.sum(chain_filters.low_pass_gain(omega, c, code))  # noqa: E731
    h = 1e-6
    assert float(jax.grad(total)(0.4)) == pytest.approx(
        float((total(0.4 + h) - total(0.4 - h)) / (2 * h)), rel=1e-6
    )
    with pytest.raises(ValueError, match="order must be 2, 3 or 4"):
        BesselLowPass(18.0, order=1)
    with pytest.raises(ValueError, match="taps must be an integer"):
        MovingAverage(1)
    with pytest.raises(ValueError, match="stages must be 2, 3 or 4"):
        DecimatingAverage(1, 4)
    with pytest.raises(ValueError, match="ratio must be an integer"):
        DecimatingAverage(2, 1)


def _cascade(stages, ratio):
    """K cascaded moving averages of R samples (the converter's rate), as one FIR."""
    h = np.ones(1)
    for _ in range(stages):
        h = signal.convolve(h, np.ones(ratio) / ratio)
    return h


@pytest.mark.parametrize(("stages", "ratio"), [(2, 2), (2, 5), (3, 4), (4, 16)])
def test_decimating_average_gain_is_the_folded_cascade(stages, ratio):
    """`DecimatingAverage`'s power gain is the sum of the R images of |H|² of the K
    cascaded boxcars at the converter's rate (`scipy.signal.freqz`), folded onto the logged
    band; its own −3 dB point (`decimation_corner`) is where the cascade's |H|² is one
    half, and the logged one (`folded_corner`) where the folded gain is."""
    h = _cascade(stages, ratio)
    f = np.linspace(0.0, 0.5, 2001)  # cycles per logged sample
    folded = sum(
        np.abs(signal.freqz(h, 1.0, worN=(f + k) / ratio, fs=1.0)[1]) ** 2 for k in range(ratio)
    )
    ours = DecimatingAverage(stages, ratio).gain(2 * np.pi * f, DT)
    np.testing.assert_allclose(np.asarray(ours), folded, rtol=1e-9, atol=1e-13)
    own = chain_filters.decimation_corner(stages, ratio)
    _, at = signal.freqz(h, 1.0, worN=[own / ratio], fs=1.0)
    assert abs(at[0]) ** 2 == pytest.approx(0.5, abs=1e-9)
    logged = chain_filters.folded_corner(stages, ratio)
    at = sum(
        np.abs(signal.freqz(h, 1.0, worN=[(logged + k) / ratio], fs=1.0)[1][0]) ** 2
        for k in range(ratio)
    )
    assert at == pytest.approx(0.5, abs=1e-9) or logged == 0.5


@pytest.mark.parametrize(
    "shape", ["bessel3", "taps5"], ids=["bessel-order-3", "moving-average-5"]
)
def test_a_bessel_low_pass_or_a_moving_average_is_found(shape):
    """The sensor's white noise through a third-order Bessel low-pass
    (`scipy.signal.bessel`, designed by its phase, as it is by default) or a moving average
    of 5 samples, with white noise after it: `bandlimit` alone, of that shape, its −3 dB
    point within 10 % (SciPy's), both white levels within 10 %. A second-order Butterworth
    low-pass fitted to them left an exp_cosine or Gauss–Markov companion, and on the moving
    average the white noise collapsed (docs/findings.md, signal chain)."""
    rng = np.random.default_rng(40)
    n = 20000
    if shape == "bessel3":
        sos = signal.bessel(3, CORNER, fs=1 / DT, output="sos")
        x = signal.sosfilt(sos, WHITE * rng.normal(size=n + 2000))[2000:]
        f = np.linspace(0.0, 0.5 / DT, 200001)
        gain = np.abs(signal.sosfreqz(sos, worN=f, fs=1 / DT)[1]) ** 2
    else:
        taps = np.ones(5) / 5
        x = signal.lfilter(taps, 1.0, WHITE * rng.normal(size=n + 2000))[2000:]
        f = np.linspace(0.0, 0.5 / DT, 200001)
        gain = np.abs(signal.freqz(taps, 1.0, worN=f, fs=1 / DT)[1]) ** 2
    f3 = float(f[np.argmax(gain <= 0.5)])
    x = x + AFTER * rng.normal(size=n)
    found = aj.noise.select_sensor_noise(x, DT)
    assert found.effects == ("bandlimit",), found.steps
    p = found.parameters["bandlimit"]
    if shape == "bessel3":
        assert (p["shape"], p["order"]) == ("bessel", 3)
    else:
        assert (p["shape"], p["taps"], p["order"]) == ("moving_average", 5, None)
    assert p["corner_Hz"] == pytest.approx(f3, rel=0.1)
    assert p["white_after_filter_sigma"] == pytest.approx(AFTER, rel=0.1)
    assert found.parameters["white_sigma"] == pytest.approx(WHITE, rel=0.1)
    words = "Bessel, order 3" if shape == "bessel3" else "a moving average of 5 samples"
    assert f"bandlimit ({words}, −3 dB at" in _describe(found)


@pytest.mark.parametrize(
    ("stages", "ratio"), [(3, 8), (2, 2)], ids=["three-stages", "first-order-average"]
)
def test_a_decimated_record_is_found(stages, ratio):
    """The sensor's white noise at R times the logged rate through K cascaded moving
    averages of R samples (a CIC decimator, `scipy.signal.lfilter`), every R-th sample
    logged, white noise added after it: `bandlimit` alone, a decimating average of K
    stages named or among the shapes the record cannot tell apart (here a first-order
    Butterworth low-pass is named on both, the decimating averages within 0.1 in 2 ln B),
    the white floor not collapsed, the low band's level (white ahead of the filter and
    after it) within 10 % and the white ahead within a factor 2. The split between the
    two whites is not identified where the logged response is a first-order moving
    average (K = 2): its spectrum c_0 + c_1 cos ω gives two numbers for three unknowns
    (both whites and R), so it is not asserted. Before the decimating average, K = 2,
    R = 2 read `exp_cosine` with the white floor collapsed (blind harness record
    decimated_0007: σ_w 1.5e-5 against 0.030)."""
    rng = np.random.default_rng(50 + stages)
    n, warm = 20000, 200
    fast = signal.lfilter(
        _cascade(stages, ratio), 1.0, WHITE * np.sqrt(ratio) * rng.normal(size=(n + warm) * ratio)
    )
    x = fast[warm * ratio :: ratio][:n] + AFTER * rng.normal(size=n)
    found = aj.noise.select_sensor_noise(x, DT)
    assert found.effects == ("bandlimit",), found.steps
    p = found.parameters["bandlimit"]
    ties = found.held_out.low_pass_ties
    assert (p["shape"], p["order"]) == ("decimating_average", stages) or any(
        (t["shape"], t["order"]) == ("decimating_average", stages) for t in ties
    ), (p, ties)
    white = found.parameters["white_sigma"]
    level = white**2 + p["white_after_filter_sigma"] ** 2
    assert level == pytest.approx(WHITE**2 + AFTER**2, rel=0.1)
    assert 0.5 < white / WHITE < 2.0
    assert found.held_out.white_floor is None  # no coloured process left
    assert found.held_out.to_dict()["low_pass_ties"] == ties
    if p["shape"] == "decimating_average":
        assert f"bandlimit (a decimating average of {p['order']} stages, ratio" in _describe(
            found
        )
    if ties:
        assert "The record fits these low-passes as well" in _describe(found)
    printed = _selection_lines(found)  # `accel-jax noise`
    assert any(line.startswith("  low-pass: ") and "−3 dB at" in line for line in printed)


def test_a_white_floor_gone_into_a_coloured_process_is_flagged():
    """`_white_floor`: an exponential-cosine process white over the record's low band
    (decay and frequency near a sample's) with the white noise at 1e-4 of it is a
    collapsed floor; the same process beside a white noise of its size is not; a
    Gauss–Markov process of 50 samples is not flat over the low band, so the white noise
    below it is no failure; a random walk leaves nothing to judge."""
    z = np.zeros(12)
    z[3], z[4], z[5] = math.log(1.0), math.log(1.2), math.log(0.8)  # σ_e², αΔ, θ
    model = sensor_refine._Model(("exp_cosine",), (), None, z, 0.0, 0.0, None, True)
    for white, collapsed in ((1e-8, True), (1.0, False)):
        z[0] = math.log(white)
        check = sensor_refine._white_floor(model, DT)
        assert check["low_band_flat"] and check["carried_by"] == "exp_cosine"
        assert check["collapsed"] is collapsed
        assert check["white_sigma"] == pytest.approx(math.sqrt(white))
    z = np.zeros(12)
    z[0], z[1], z[2] = math.log(1e-8), 0.0, math.log(50.0)
    slow = sensor_refine._Model(("gauss_markov",), (), None, z, 0.0, 0.0, None, True)
    check = sensor_refine._white_floor(slow, DT)
    assert not check["low_band_flat"] and not check["collapsed"]
    walk = sensor_refine._Model(("random_walk",), (), None, z, 0.0, 0.0, None, True)
    assert sensor_refine._white_floor(walk, DT) is None


@pytest.mark.parametrize("order", [1, 3, 4])
def test_the_low_pass_order_is_found(order):
    """A low-pass of order 1, 3 or 4 (`scipy.signal.butter`) with white noise after it:
    `bandlimit` alone, of that order, its corner within 10 % (a second-order low-pass
    fitted to them left an exp_cosine companion). Order 1 read exp_cosine+bandlimit
    (order 1, corner 35 Hz, the white noise collapsed) until the order's trial without
    the companion was also fitted from its own starts, not only from the optimum whose
    white slot the companion had emptied (`sensor_refine._low_pass_order`)."""
    rng = np.random.default_rng(30 + order)
    n = 20000
    sos = signal.butter(order, CORNER, fs=1 / DT, output="sos")
    x = signal.sosfilt(sos, WHITE * rng.normal(size=n + 2000))[2000:]
    x = x + AFTER * rng.normal(size=n)
    found = aj.noise.select_sensor_noise(x, DT)
    assert found.effects == ("bandlimit",), found.steps
    assert found.steps[-1]["model"].split("+") == ["white", "bandlimit", "filter_floor"]
    p = found.parameters["bandlimit"]
    assert (p["shape"], p["order"]) == ("butterworth", order)
    assert p["corner_Hz"] == pytest.approx(CORNER, rel=0.1)
    assert p["white_after_filter_sigma"] == pytest.approx(AFTER, rel=0.1)
    assert found.parameters["white_sigma"] == pytest.approx(WHITE, rel=0.1)


@pytest.mark.parametrize("step", [None, 2e-4], ids=["off-grid", "on-a-grid"])
def test_white_noise_after_the_low_pass_is_found(step):
    """Without the fitted floor this record (no grid) was named
    exp_cosine+gauss_markov with σ_w = 2e-10 (the white noise collapsed: an oscillating
    and a short Gauss–Markov process drew the spectrum's shape)."""
    truth = {"white": WHITE, "bandlimit": CORNER, "white_after_filter": AFTER}
    if step is not None:
        truth["quantization"] = step
    x = noise_truth.record(np.random.default_rng(11), 20000, DT, truth)
    found = aj.noise.select_sensor_noise(x, DT)
    assert set(found.effects) - {"quantization"} == {"bandlimit"}, found.steps
    p = found.parameters
    assert p["bandlimit"]["corner_Hz"] == pytest.approx(CORNER, rel=0.1)
    assert p["white_sigma"] == pytest.approx(WHITE, rel=0.1)
    grid = 0.0 if step is None else step**2 / 12
    after = math.sqrt(p["post_filter_floor_variance"])
    assert after == pytest.approx(math.sqrt(AFTER**2 + grid), rel=0.1)
    # against the record alone: the flat band below the corner (σ_w² + p) and the band
    # near Nyquist, where the filter leaves 1e-3 of σ_w² (p alone)
    low = _band_density(x, 0.5, 6.0)
    assert math.sqrt(p["white_sigma"] ** 2 + after**2) == pytest.approx(math.sqrt(low), rel=0.1)
    high = _band_density(x, 45.0, 50.0)
    assert after == pytest.approx(math.sqrt(high), rel=0.15)


def test_no_white_noise_after_the_filter_adds_none():
    """The same low-pass without white noise after it: `bandlimit` alone, no fitted floor
    (its one parameter does not pay its price)."""
    truth = {"white": WHITE, "bandlimit": CORNER}
    x = noise_truth.record(np.random.default_rng(11), 20000, DT, truth)
    found = aj.noise.select_sensor_noise(x, DT)
    assert found.effects == ("bandlimit",), found.steps
    assert "white_after_filter_sigma" not in found.parameters["bandlimit"]
    assert found.parameters["bandlimit"]["order"] == 2
    assert found.parameters["bandlimit"]["corner_Hz"] == pytest.approx(CORNER, rel=0.1)


def test_high_frequency_noise_is_scipys_high_pass():
    """`HighFrequencyNoise`'s spectrum is σ_h² |H|² of `scipy.signal.butter(2, btype="high")`."""
    f = np.linspace(0.0, 0.5 / DT, 2001)
    sos = signal.butter(2, 30.0, btype="high", fs=1 / DT, output="sos")
    _, h = signal.sosfreqz(sos, worN=f, fs=1 / DT)
    ours = HighFrequencyNoise(2.0, 30.0).spectrum(2 * np.pi * f * DT, DT)
    np.testing.assert_allclose(np.asarray(ours), 4.0 * np.abs(h) ** 2, rtol=1e-9, atol=1e-12)


def test_a_spectrum_rising_towards_nyquist():
    """A stand-in for a navigation IMU's static record (200 Hz): flat near 10 µg/√Hz below
    a few Hz, rising to ~50 µg/√Hz towards the Nyquist frequency (white noise through a
    second-order high-pass at 40 Hz, `scipy.signal.butter`, beside the white noise).
    Without `high_frequency_noise` it read exp_cosine+unexplained with the white noise
    collapsed to 2e-10 g. Now that effect alone, its corner within 10 %, and the white
    noise within 10 % of the truth and of a model-free estimate from the flat band."""
    dt, n = 0.005, 20000
    white = 10e-6 * math.sqrt(0.5 / dt)  # 10 µg/√Hz one-sided
    hump = 49e-6 * math.sqrt(0.5 / dt)
    rng = np.random.default_rng(3)
    sos = signal.butter(2, 40.0, btype="high", fs=1 / dt, output="sos")
    x = white * rng.normal(size=n) + signal.sosfilt(sos, hump * rng.normal(size=n + 2000))[2000:]
    found = aj.noise.select_sensor_noise(x, dt)
    assert found.effects == ("high_frequency_noise",), found.steps
    p = found.parameters
    assert p["high_frequency_noise"]["corner_Hz"] == pytest.approx(40.0, rel=0.1)
    assert p["high_frequency_noise"]["sigma"] == pytest.approx(hump, rel=0.1)
    assert p["white_sigma"] == pytest.approx(white, rel=0.1)
    f, psd = signal.welch(x, 1 / dt, nperseg=1024)
    flat = math.sqrt(float(np.mean(psd[(f > 0.5) & (f < 3.0)])) / (2 * dt))
    assert p["white_sigma"] == pytest.approx(flat, rel=0.1)


def test_the_low_pass_shapes_in_words():
    """`sensor_text`: each shape in words (the diagnosis's summary and `accel-jax noise`),
    the shapes the record cannot tell apart, and a collapsed white floor as a fit failure."""
    from accel_jax._noise import sensor_text

    words = sensor_text.low_pass_words
    assert words({"shape": "butterworth", "order": 2}) == "Butterworth, order 2"
    assert words({"shape": "moving_average", "order": None, "taps": 5}) == (
        "a moving average of 5 samples"
    )
    assert words({"shape": "decimating_average", "order": 3, "ratio": 4}) == (
        "a decimating average of 3 stages, ratio 4"
    )
    tie = {"shape": "decimating_average", "order": 2, "ratios": [4, 8], "evidence": 0.25}
    assert sensor_text.low_pass_ties_sentence([tie]) == (
        "the record fits these low-passes as well, within the bar: a decimating average of "
        "2 stages, ratio 4/8 (2 ln B 0.2)"
    )
    floor = {"white_sigma": 1e-5, "low_band_sigma": 3e-2, "carried_by": "exp_cosine"}
    assert sensor_text.white_floor_sentence(floor).startswith(
        "fit failure: the white noise (σ 1e-05 g) lies far below the 0.03 g"
    )
