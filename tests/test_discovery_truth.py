"""The discovery truth simulator (studies/discovery_truth.py), checked against other
computations: step_truth's records with each effect's magnitude at 0, step_truth's loop
with a scaled torquer (asymmetry, until the torquer's moment first changes sign) or a
shifted moment (the pickoff's play, until the first turning point), the exact peak ratio
of a step under dry friction, the exact settled levels of the play, and an exact
matrix-exponential solution of the loop with a second mode; and the integration refined
(rtol and the largest step halved). NumPy/SciPy only."""

import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.linalg import expm

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "studies"))
import discovery_truth as dt  # noqa: E402
import step_truth  # noqa: E402

EFFECTS = dt.CLASSES[1:]
ZERO = {
    "torquer_asymmetry": {"asymmetry": 0.0},
    "coulomb_friction": {"friction_Nm": 0.0},
    "pickoff_hysteresis": {"play_rad": 0.0},
    "second_mode": {"mode_coupling": 0.0},
}
U = 2.0  # V
M = 1e-6  # N·m
CHANGE = 1.0003e-3  # s: off the sample grid


def _quiet(truth):
    return {**truth, "noise_V": 0.0, "adc_step_V": 0.0}


def _record(levels, times, *, rate=1e6, duration=6e-3, moment=M):
    return step_truth.Record(
        levels=np.asarray(levels, dtype=float),
        change_times=np.asarray(times, dtype=float),
        rate=rate,
        n=int(round(duration * rate)),
        moment=moment,
    )


def _device(**values):
    device = step_truth.Device(**values)
    gain = device.k_dp * device.k_y * device.l
    return device, gain, device.c + device.k_dm * gain


@pytest.mark.parametrize("effect", dt.CLASSES)
def test_draw_is_step_truths_world(effect):
    """The same draws in the same order as step_truth.draw_truth(rng, "none"), then the
    effect's magnitudes in their ranges; JSON-able."""
    truth = dt.draw(np.random.default_rng(3), effect, measure=False)
    ref = step_truth.draw_truth(np.random.default_rng(3), "none")
    assert all(truth[key] == ref[key] for key in ref if key != "effect")
    assert truth["effect"] == effect
    json.dumps(truth)
    ranges = {
        "torquer_asymmetry": [("asymmetry", dt.ASYMMETRY, abs)],
        "coulomb_friction": [("friction_ratio", dt.FRICTION_RATIO, None)],
        "pickoff_hysteresis": [("play_ratio", dt.PLAY_RATIO, None)],
        "second_mode": [
            ("mode_ratio", dt.MODE_RATIO, None),
            ("mode_zeta", dt.MODE_ZETA, None),
            ("mode_coupling", dt.MODE_COUPLING, None),
        ],
    }
    for key, (low, high), f in ranges.get(effect, []):
        value = f(truth[key]) if f else truth[key]
        assert low <= value <= high


@pytest.mark.parametrize("effect", EFFECTS)
def test_zero_magnitude_is_step_truths_record(effect):
    """With the effect's magnitude at 0 (noise and ADC off), a drawn record is
    step_truth.make's record of the same world (same seed), to 1e-9 V."""
    truth = _quiet({**dt.draw(np.random.default_rng(11), effect, measure=False), **ZERO[effect]})
    t, u, y = dt.make(truth, np.random.default_rng(1))
    ref = _quiet(step_truth.draw_truth(np.random.default_rng(11), "none"))
    t_ref, u_ref, y_ref, _ = step_truth.make(ref, np.random.default_rng(1))
    error = float(np.max(np.abs(y - y_ref)))
    print(f"{effect}: |record − step_truth's| ≤ {error:.2e} V over {y.size} samples")
    assert np.array_equal(t, t_ref) and np.array_equal(u, u_ref)
    assert error < 1e-9


def test_none_at_another_duration():
    """"none" cut short runs this simulator: step_truth.simulate's record, to 1e-9 V."""
    truth = _quiet(dt.draw(np.random.default_rng(5), "none", duration_s=4e-3))
    _, _, y = dt.make(truth, np.random.default_rng(1))
    device, rec, _ = dt.world(truth)
    _, _, y_ref = step_truth.simulate(device, rec, rng=np.random.default_rng(1))
    assert y.size == rec.n == int(round(4e-3 * truth["rate"]))
    assert np.max(np.abs(y - y_ref)) < 1e-9


@pytest.mark.parametrize("effect", EFFECTS)
def test_refined_integration(effect):
    """Halving rtol, and halving rtol and the largest step, changes a drawn record by
    < 1e-7 V (the events are located on the dense output, not by the steps)."""
    truth = dt.draw(np.random.default_rng(2), effect, measure=False, duration_s=6e-3)
    device, rec, effects = dt.world(truth)
    _, _, base, log = dt.run(device, rec, effects)
    _, _, tight, _ = dt.run(device, rec, effects, rtol=5e-11)
    _, _, fine, _ = dt.run(device, rec, effects, rtol=5e-11, step_scale=0.5)
    tol_change = float(np.max(np.abs(tight - base)))
    step_change = float(np.max(np.abs(fine - base)))
    print(
        f"{effect}: {len(log)} events; rtol/2 changes ≤ {tol_change:.2e} V, "
        f"rtol/2 and step/2 ≤ {step_change:.2e} V"
    )
    assert tol_change < 1e-7 and step_change < 1e-7
    if effect != "second_mode":
        assert len(log) > 0


@pytest.mark.parametrize("a", [0.03, -0.03])
@pytest.mark.parametrize("direction", [1.0, -1.0])
def test_asymmetry_is_a_scaled_torquer_until_its_moment_reverses(a, direction):
    """From rest at 0 V with no moment (M_dm = 0), a step of the test voltage drives the
    torquer one way: until its moment first crosses 0 the loop is step_truth's with the
    torquer gain k_dm (1 + a σ), σ the sign of g_w ΔU."""
    device, gain, _ = _device(test_gain=-1.0)
    rec = _record([0.0, direction * U], [CHANGE], moment=0.0)
    t, _, y, log = dt.run(device, rec, dt.Effects(asymmetry=a))
    sigma = np.sign(device.test_gain * direction)
    scaled = dataclasses.replace(device, k_dm=device.k_dm * (1 + a * sigma))
    _, _, y_ref = step_truth.simulate(scaled, rec, rng=np.random.default_rng(0))
    assert log[0][1] == "torquer"
    k = np.searchsorted(t, log[0][0])  # samples before the first reversal
    # The reference's own crossing: its output reaches g_w U (M_dm = 0) there too.
    k_ref = np.argmax(sigma * y_ref >= sigma * device.test_gain * direction * U)
    error = float(np.max(np.abs(y[:k] - y_ref[:k])))
    print(f"a={a} step {direction:+}: {k} samples match to {error:.2e} V")
    assert abs(k - k_ref) <= 1 and k > 100
    assert error < 1e-9
    assert np.max(np.abs(y[k + 50 :] - y_ref[k + 50 :])) > 1e-4  # after it, not


@pytest.mark.parametrize("ratio", [0.002, 0.02])
def test_friction_lowers_the_peak_and_sticks(ratio):
    """From rest (stuck at the frictionless rest), a step's first swing is the frictionless
    one with the step reduced by F/C: the first peak over the step is 1 − F/(C Δθ) of the
    frictionless one, exactly. At the end of a long level the pendulum is stuck: the output
    frozen, within G F/C of the frictionless level."""
    device, gain, stiffness = _device()
    rec = _record([0.0, U], [CHANGE], duration=12e-3)
    dtheta = device.k_dm * device.test_gain * U / stiffness
    friction = ratio * stiffness * dtheta
    t, _, y, log = dt.run(device, rec, dt.Effects(friction=friction))
    _, _, y0, _ = dt.run(device, rec, dt.Effects())
    peaks = (y.max() - y[0]) / (y0.max() - y0[0])
    print(
        f"F ratio {ratio}: peak ratio {peaks:.12f} (exact {1 - friction / (stiffness * dtheta)}), "
        f"final offset {y[-1] - y0[-1]:.3e} V (bound {gain * friction / stiffness:.3e}), "
        f"events {[kind for _, kind in log]}"
    )
    assert y.max() < y0.max()
    assert abs(peaks - (1 - friction / (stiffness * dtheta))) < 1e-8
    tail = y[t > t[-1] - 2e-3]
    assert np.ptp(tail) == 0.0  # stuck: θ frozen exactly
    assert abs(y[-1] - y0[-1]) <= gain * friction / stiffness
    assert np.ptp(y0[t > t[-1] - 2e-3]) > 0


@pytest.mark.parametrize("step", [U, -U])
def test_play_is_an_offset_loop_until_the_turn_then_freezes(step):
    """At rest after an approach from the side s of the coming step, the pickoff tracks
    θ − s b: until θ first turns, the record is step_truth's with the moment
    M + k_dm G s b, less G s b. At the turn the output freezes (flat top)."""
    device, gain, stiffness = _device(test_gain=-1.0)
    play = 0.02 * device.k_dm * U / stiffness
    s = float(np.sign(device.test_gain * step))
    rec = _record([0.0, step], [CHANGE])
    t, _, y, log = dt.run(device, rec, dt.Effects(play=play, approach_sign=s))
    shifted = dataclasses.replace(rec, moment=M + device.k_dm * gain * s * play)
    _, _, y_ref = step_truth.simulate(device, shifted, rng=np.random.default_rng(0))
    y_ref = y_ref - gain * s * play
    assert log[0][1] == "slip"
    k = np.searchsorted(t, log[0][0])
    error = float(np.max(np.abs(y[:k] - y_ref[:k])))
    flat = int(np.argmax(y[k + 1 :] != y[k]))  # samples frozen after the turn
    frozen_for = log[1][0] - log[0][0]
    print(f"step {step:+}: {k} samples match to {error:.2e} V; frozen {flat} samples")
    assert error < 1e-9
    assert flat >= int(frozen_for * rec.rate) - 1 and flat > 10
    assert np.ptp(y_ref[k : k + flat]) > 1e-4


def test_play_level_depends_on_the_direction_of_approach():
    """On a nearly critically damped loop (ζ = 1.05: no overshoot), the level under 0 V
    approached from above settles at G (M + c b)/C, from below at G (M − c b)/C (the
    static play, reduced by the mechanical spring's share c/C of the loop's stiffness)."""
    device, gain, stiffness = _device()
    device.mu = 2 * 1.05 * np.sqrt(device.J * stiffness)
    play = 0.03 * device.k_dm * U / stiffness
    segment = 8e-3
    rec = _record(
        [0.0, U, 0.0, -U, 0.0],
        np.arange(1, 5) * segment + 3.3e-7,
        rate=5e5,
        duration=5 * segment,
    )
    t, _, y, _ = dt.run(device, rec, dt.Effects(play=play, approach_sign=1.0))
    from_above = y[np.searchsorted(t, 3 * segment) - 1]
    from_below = y[-1]
    expect_above = gain * (M + device.c * play) / stiffness
    expect_below = gain * (M - device.c * play) / stiffness
    print(
        f"from above {from_above:.9f} (exact {expect_above:.9f}), from below "
        f"{from_below:.9f} (exact {expect_below:.9f}), split {from_above - from_below:.3e} V"
    )
    assert abs(from_above - expect_above) < 1e-7 and abs(from_below - expect_below) < 1e-7
    assert from_above - from_below > 100 * 1e-7


def _exact_with_mode(device, rec, gain, omega, zeta, kappa):
    """U_out = G (θ + θ₂) of the loop with a second mode (T_dm = T_f = 0), exactly: the
    linear system x = (θ, θ', θ₂, θ₂', 1) solved by matrix exponentials."""
    stiffness = device.c + device.k_dm * gain

    def generator(u):
        a = np.zeros((5, 5))
        row = np.array(
            [
                -stiffness / device.J,
                -device.mu / device.J,
                -device.k_dm * gain / device.J,
                0.0,
                (device.k_dm * device.test_gain * u + rec.moment) / device.J,
            ]
        )
        a[0, 1] = a[2, 3] = 1.0
        a[1] = row
        a[3] = -kappa * row
        a[3, 2] -= omega**2
        a[3, 3] -= 2 * zeta * omega
        return a

    t = rec.t0 + np.arange(rec.n) / rec.rate
    levels, changes = rec.levels, list(rec.change_times) + [np.inf]
    rest = (device.k_dm * device.test_gain * levels[0] + rec.moment) / stiffness
    x = np.array([rest, 0.0, 0.0, 0.0, 1.0])
    out, before, j = np.empty(rec.n), t[0], 0
    for i, ti in enumerate(t):
        while changes[j] <= ti:
            x = expm(generator(levels[j]) * (changes[j] - before)) @ x
            before, j = changes[j], j + 1
        x = expm(generator(levels[j]) * (ti - before)) @ x
        before = ti
        out[i] = gain * (x[0] + x[2])
    return out


@pytest.mark.parametrize("ratio,zeta,kappa", [(3.0, 0.02, 0.03), (10.0, 0.1, 0.005)])
def test_second_mode_exact_and_its_signature(ratio, zeta, kappa):
    """The loop with a second mode is the exact (matrix-exponential) solution to 1e-9 V; a
    step's first rise is (1 − κ) of the plain loop's (θ₂ ≈ −κ θ'' τ²/2 at first); a
    lightly damped mode rings in the difference at its damped frequency."""
    device, gain, stiffness = _device(test_gain=-1.0)
    omega = ratio * np.sqrt(stiffness / device.J)
    rec = _record([0.0, U, -U, 0.0], [CHANGE, 2.5007e-3, 4.1e-3], rate=5e5)
    effects = dt.Effects(mode_omega=omega, mode_zeta=zeta, mode_coupling=kappa)
    t, _, y, _ = dt.run(device, rec, effects)
    _, _, y0, _ = dt.run(device, rec, dt.Effects())
    exact = _exact_with_mode(device, rec, gain, omega, zeta, kappa)
    error = float(np.max(np.abs(y - exact)))
    k = np.searchsorted(t, CHANGE)
    rise = (y[k] - y[k - 1]) / (y0[k] - y0[k - 1])
    tail = (y - y0)[t > 4.1e-3]
    spectrum = np.abs(np.fft.rfft(tail * np.hanning(tail.size), 32 * tail.size))
    peak = np.fft.rfftfreq(32 * tail.size, 1 / rec.rate)[np.argmax(spectrum)]
    ring = omega / (2 * np.pi) * np.sqrt(1 - zeta**2)
    print(
        f"f2/fn={ratio} ζ2={zeta} κ={kappa}: |sim − exact| ≤ {error:.2e} V; first rise "
        f"{rise:.6f} (1 − κ = {1 - kappa}); difference peaks at {peak:.0f} Hz (ring {ring:.0f})"
    )
    assert error < 1e-9
    assert abs(rise - (1 - kappa)) < 0.05 * kappa
    if zeta < 0.05:
        assert abs(peak / ring - 1) < 0.01


def test_make_applies_the_recorder_and_measures_the_effect():
    """make's record is the noise-free record plus step_truth's noise draws, quantised; the
    truth holds the effect's RMS over the noise-free records, its ratio to σ, visible."""
    truth = dt.draw(np.random.default_rng(4), "coulomb_friction", duration_s=4e-3)
    t, u, y = dt.make(truth, np.random.default_rng(9))
    _, _, clean = dt.clean_record(truth)
    _, _, without = dt.clean_record(truth, effect=False)
    noise = np.random.default_rng(9).normal(size=y.size) * truth["noise_V"]
    assert t[0] == 0 and y.size == u.size == int(round(4e-3 * truth["rate"]))
    assert np.max(np.abs(y - (clean + noise))) <= truth["adc_step_V"] / 2 * (1 + 1e-9)
    rms = np.sqrt(np.mean((clean - without) ** 2))
    assert truth["effect_rms_V"] == pytest.approx(rms, rel=1e-12)
    assert truth["effect_over_noise"] == pytest.approx(rms / truth["noise_V"], rel=1e-12)
    assert truth["visible"] == (truth["effect_over_noise"] >= dt.VISIBLE_OVER_NOISE)
