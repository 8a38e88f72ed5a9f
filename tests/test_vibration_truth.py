"""The vibration-table truth simulator (studies/vibration_truth.py), checked against time
averages derived by hand (E[sin²] = 1/2, E[sin⁴] = 3/8, E[sin⁶] = 5/16, odd powers 0;
Gaussian E[r⁴] = 3 s⁴, E[r⁶] = 15 s⁶) and against its own tables. NumPy only; no code of
the package's vibration diagnosis is used."""

import json
import sys
from math import comb
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "studies"))
import vibration_truth as vt  # noqa: E402

SINE_MOMENT = {0: 1.0, 2: 0.5, 4: 3 / 8, 6: 5 / 16}  # E[sinᵏ], odd k: 0


def _sine_power(a, b, n):
    """E[(a + b sin)ⁿ] over a whole period, by the binomial expansion."""
    return sum(comb(n, k) * a ** (n - k) * b**k * SINE_MOMENT.get(k, 0.0) for k in range(n + 1))


@pytest.mark.parametrize("a_in, b3, samples, cycles, phase",
                         [(0.0, 2.0, 4096, 16, 0.3), (0.5, 3.0, 8192, 77, 2.1),
                          (-1.0, 10.0, 16384, 128, 5.9)])
def test_sine_row_matches_hand_averages(a_in, b3, samples, cycles, phase):
    b1, b2 = 1.7, 2.3
    m = vt.row_average(a_in, b3, b1, b2, samples=samples, cycles=cycles, phase=phase)
    want = {f"k{n}": _sine_power(a_in, b3, n) for n in range(2, 8)}
    want |= {"a3": a_in, "m31": b3 * b1 / 2, "m32": b3 * b2 / 2, "oa_square": b1**2 / 2,
             "pa_square": b2**2 / 2, "oa_pa": b1 * b2 / 2, "ia_oa_square": a_in * b1**2 / 2,
             "frequency_dependent": a_in**2 + b3**2 / 2}
    for k, v in want.items():
        scale = (abs(a_in) + abs(b3) + b1 + b2) ** (int(k[1]) if k[0] == "k" else 3)
        assert m[k] == pytest.approx(v, rel=1e-9, abs=1e-12 * scale), k


def test_pure_cases():
    kw = dict(samples=4096, cycles=37, phase=1.234)
    assert vt.row_average(0.0, 2.0, **kw)["k6"] == pytest.approx(20.0, rel=1e-12)  # 5/16·2⁶
    assert abs(vt.row_average(0.0, 2.0, **kw)["k7"]) < 1e-9 * 2**7
    assert vt.row_average(0.8, 0.0, 3.0, **kw)["ia_oa_square"] == pytest.approx(0.8 * 4.5, 1e-12)
    # |a3| a3 with a3 > 0 throughout is a3²; with a_in = 0 it averages to 0.
    m = vt.row_average(1.5, 1.0, **kw)
    assert m["abs_square"] == pytest.approx(1.5**2 + 0.5, rel=1e-12)
    assert m["asymmetry"] == pytest.approx(0.75, rel=1e-12)
    assert abs(vt.row_average(0.0, 3.0, **kw)["abs_square"]) < 1e-12
    # The resonance scales the vibration of the quadratic, not the static input.
    g = float(vt.resonance_gain(300.0, 250.0, 4.0))
    m = vt.row_average(0.7, 2.0, gain=g, **kw)
    assert m["frequency_dependent"] == pytest.approx(0.49 + g**2 * 2.0, rel=1e-12)
    assert vt.resonance_gain(0.0, 250.0, 4.0) == 1.0
    assert vt.resonance_gain(250.0, 250.0, 4.0) == pytest.approx(4.0, rel=1e-12)
    # indicated(): bias, scale factor and ppm coefficients combine linearly.
    m = vt.row_average(0.5, 3.0, **kw)
    got = vt.indicated(m, {"k6": 2.0, "k2": -1.0}, bias=1e-3, scale_factor_error=50e-6)
    want = 1e-3 + (1 + 50e-6) * 0.5 + 1e-6 * (2 * _sine_power(0.5, 3, 6) - _sine_power(0.5, 3, 2))
    assert got == pytest.approx(want, rel=1e-14)


@pytest.mark.parametrize("kind", ["white", "bandlimited"])
@pytest.mark.parametrize("mode", ["gaussian", "quantile"])
def test_random_record(kind, mode):
    rng = np.random.default_rng(5)
    x = vt.unit_random(rng, 8192, kind, order=3, cutoff=0.1, mode=mode)
    assert abs(x.mean()) < 1e-14 and np.mean(x**2) == pytest.approx(1.0, rel=1e-12)
    assert np.mean(x**4) == pytest.approx(3.0, rel=0.3)
    if mode == "quantile":
        assert abs(np.mean(x**3)) < 1e-12 and np.mean(x**4) == pytest.approx(3.0, rel=0.02)
    s, a = 4.0, -0.5  # a random row's k2 average is exactly a² + s² (E[r] = 0, E[r²] = s²)
    m = vt.row_average(a, s=s, samples=8192, unit_random=x)
    assert m["k2"] == pytest.approx(a**2 + s**2, rel=1e-12)
    # The expectation (quadrature) against the Gaussian moments.
    e = vt.row_expectation(a, s=s)
    assert e["k4"] == pytest.approx(a**4 + 6 * a**2 * s**2 + 3 * s**4, rel=1e-12)
    assert e["k6"] == pytest.approx(_sine_power(a, 0, 6) + 15 * a**4 * s**2
                                    + 45 * a**2 * s**4 + 15 * s**6, rel=1e-12)
    e = vt.row_expectation(a, 3.0, 1.0, 2.0)
    assert e["k7"] == pytest.approx(_sine_power(a, 3.0, 7), rel=1e-12)


def _analytic(data, truth):
    """a_out's expectation from the columns and the truth, for records whose terms all have
    closed-form averages (k2, k3 without random rows, the cross-axis and resonance terms)."""
    a, b3, s = data.a_in, data.vib_amp, data.vib_rms
    z = np.zeros_like(a)
    b1 = z if data.vib_amp_oa is None else data.vib_amp_oa
    b2 = z if data.vib_amp_pa is None else data.vib_amp_pa
    v2 = b3**2 / 2 + s**2
    g = vt.resonance_gain(data.vib_freq, truth["f_r"], truth["Q"]) if truth["f_r"] else 1.0
    terms = {"k2": a**2 + v2, "k3": a**3 + 3 * a * v2, "oa_square": b1**2 / 2,
             "pa_square": b2**2 / 2, "oa_pa": b1 * b2 / 2, "ia_oa_square": a * b1**2 / 2,
             "frequency_dependent": a**2 + g**2 * v2}
    out = truth["bias_g"] + (1 + truth["scale_factor_error"]) * a
    return out + 1e-6 * sum(truth[k] * v for k, v in terms.items() if truth[k])


@pytest.fixture(scope="module")
def drawn():
    return {cls: vt.draw(11, cls) for cls in vt.CLASSES}


def test_every_class_draws(drawn):
    for cls, (data, truth) in drawn.items():
        json.dumps(truth)
        assert truth["class"] == cls and len(data.a_out) == truth["rows"] >= 10
        assert np.all(np.abs(data.a_in) <= 1)
        assert np.all((data.vib_freq >= 20) & (data.vib_freq <= 500))
        assert (data.vib_amp_oa is None) == (not truth["inclined"])
        if cls == "none":
            assert truth["snr"] is None
        else:
            assert vt.SNR_RANGE[0] <= truth["snr"] <= vt.SNR_RANGE[1]
            for term in vt.TERM_OF_CLASS.get(cls, (cls,)):
                assert truth[term] != 0
        assert set(truth["terms"]) <= set(vt.TERMS)


@pytest.mark.parametrize("cls", ["oa_square", "pa_square", "oa_pa", "ia_oa_square",
                                 "frequency_dependent"])
def test_table_against_closed_form(cls, drawn):
    data, truth = drawn[cls]
    if truth["k3"] and truth["random_rms"]:  # E[r³] of a finite record is not 0
        data, truth = next(d for d in (vt.draw(s, cls) for s in range(20, 40))
                           if not (d[1]["k3"] and d[1]["random_rms"]))
    resid = data.a_out - _analytic(data, truth)
    ratio = np.sqrt(np.mean(resid**2)) / truth["row_noise_g"]
    assert 0.5 < ratio < 1.6, ratio
    # The snr, recomputed from the columns: the effect's RMS beyond a0 + δ a_in over σ.
    clean = _analytic(data, {**truth, "bias_g": 0.0, "scale_factor_error": 0.0,
                             **{k: 0.0 for k in ("k2", "k3")}})
    basis = np.column_stack([np.ones_like(data.a_in), data.a_in])
    fit = basis @ np.linalg.lstsq(basis, clean, rcond=None)[0]
    snr = np.sqrt(np.mean((clean - fit) ** 2)) / truth["row_noise_g"]
    assert snr == pytest.approx(truth["snr"], rel=1e-6)


def test_deterministic():
    (d1, t1), (d2, t2) = vt.draw(3, "k7"), vt.draw(3, "k7")
    assert t1 == t2
    for c in ("a_in", "vib_amp", "vib_freq", "vib_rms", "a_out"):
        np.testing.assert_array_equal(getattr(d1, c), getattr(d2, c))
    assert vt.draw(4, "k7")[1] != t1
    many = vt.draw_many(3, "none", 2)
    assert many[1][1] == vt.draw(many[1][1]["seed"], "none")[1]
