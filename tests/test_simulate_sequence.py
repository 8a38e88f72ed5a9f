"""The record simulator with sub-sample change times (accel_jax._simulate.sequence),
checked against simulators it does not share code with: `simulate_linear` on a grid 50×
finer (sub-sample change times), and the SciPy truth simulator of studies/step_truth.py (its own equations,
stops as exact events)."""

import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import accel_jax as aj
from accel_jax._simulate.sequence import (
    SequenceInputs,
    accel_moment,
    linear_record,
    stop_record,
)
from accel_jax.diagnose.step.effects import step_effects
from accel_jax.diagnose.step.fit import StepContext, innovation_terms, predict, unpack
from accel_jax.diagnose.step.layout import W

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "studies"))
import step_truth  # noqa: E402

RATE = 1e6
DT = 1 / RATE
LEVELS = np.array([0.5, 2.0, 0.0, -2.0, 2.0, 0.0])
SEGMENT = 1000
N = SEGMENT * LEVELS.size
INDEX = np.arange(1, LEVELS.size) * SEGMENT + np.array([3, -7, 0, 5, 1])
STEPS = np.diff(LEVELS)
IDEAL = aj.ServoParams.reference(torquer_time_constant=0.0, filter_time_constant=0.0)
KDM = float(IDEAL.torquer_gain)


def _shifts(seed=1):
    return np.random.default_rng(seed).uniform(-1, 1, INDEX.size)


def _still_device():
    """stop_record's arguments before the stops: the ideal device, gain 1, no moment, drift
    or initial offsets, the test sequence with its sub-sample shifts."""
    zeros = (0.0, 0.0, 0.0, 0.0)
    changes = (jnp.asarray(INDEX), jnp.asarray(STEPS), jnp.asarray(_shifts()))
    return (IDEAL, DT, N, SequenceInputs(LEVELS[0], 1.0, *zeros, *changes))


def _record(params, shift, *, moment=1e-6, rate=3e-7, gain=1.0, block=1, n=N):
    return np.asarray(
        linear_record(
            params,
            DT,
            n // block,
            SequenceInputs(
                LEVELS[0],
                gain,
                moment / KDM,
                rate / KDM,
                0.0,
                0.0,
                jnp.asarray(INDEX),
                jnp.asarray(STEPS),
                jnp.asarray(shift),
            ),
            block=block,
            duration=DT * (N - 1),
        )
    )


@pytest.mark.parametrize("lags", [(0.0, 0.0), (2e-5, 0.0), (0.0, 3e-5)])
def test_linear_record_matches_simulate_linear_on_a_finer_grid(lags):
    # Changes at multiples of 1/20 sample (exact on the fine grid), a drifting moment.
    params = aj.ServoParams.reference(torquer_time_constant=lags[0], filter_time_constant=lags[1])
    fine = 20
    shift = np.round(_shifts() * fine) / fine
    tf = np.arange(N * fine) * DT / fine
    uf = np.full(tf.size, LEVELS[0])
    for i, step, d in zip(INDEX, STEPS, shift, strict=True):
        uf[int(round((i + d) * fine)) :] += step
    moment = 1e-6 + 3e-7 * tf / (DT * (N - 1))
    start = aj.equilibrium_state(params, LEVELS[0], 0.0, 1e-6)
    reference = aj.simulate_linear(params, tf, uf, external_moment=moment, initial_state=start)
    ours = _record(params, shift)
    # The fine grid holds the moment ramp in steps of Δ/20: O(Δ/40) of its slope.
    np.testing.assert_allclose(ours, np.asarray(reference)[::fine], rtol=0, atol=3e-7)
    flat = _record(params, shift, rate=0.0)
    reference = aj.simulate_linear(params, tf, uf, external_moment=1e-6, initial_state=start)
    np.testing.assert_allclose(flat, np.asarray(reference)[::fine], rtol=0, atol=1e-10)


def test_block_means_are_exact_and_the_block_size_may_be_traced():
    params = aj.ServoParams.reference(filter_time_constant=2e-5)
    shift = _shifts(2)
    full = _record(params, shift)
    for m in (7, 10):
        blocks = _record(params, shift, block=m)
        reference = full[: N // m * m].reshape(-1, m).mean(axis=1)
        np.testing.assert_allclose(blocks, reference, rtol=0, atol=1e-12)
    # One compiled function for several block sizes (m traced, max_block static).
    traced = jax.jit(
        lambda m: linear_record(
            params,
            DT,
            500,
            SequenceInputs(
                LEVELS[0],
                1.0,
                0.0,
                0.0,
                0.0,
                0.0,
                jnp.asarray(INDEX),
                jnp.asarray(STEPS),
                jnp.asarray(shift),
            ),
            block=m,
            max_block=16,
            duration=DT * (N - 1),
        )
    )
    for m in (7, 10):
        static = _record(params, shift, moment=0.0, rate=0.0, block=m, n=500 * m)
        np.testing.assert_allclose(np.asarray(traced(m)), static, rtol=0, atol=1e-12)


def _truth(h_max=float("inf"), **record):
    rec = step_truth.Record(
        levels=LEVELS, change_times=(INDEX + _shifts()) * DT, rate=RATE, n=N, **record
    )
    return step_truth.simulate(step_truth.Device(h_max=h_max), rec, rng=np.random.default_rng(0))


def test_linear_record_matches_the_independent_truth_simulator():
    _, u, y = _truth(moment=1e-6)
    ours = _record(IDEAL, _shifts(), rate=0.0)
    np.testing.assert_allclose(ours, y, rtol=0, atol=1e-10)
    # The u_test column is the voltage sampled at the record's times.
    assert np.all(np.flatnonzero(np.diff(u)) + 1 == INDEX + (_shifts() > 0))


def test_acceleration_steps_match_the_independent_truth_simulator():
    # Input-acceleration steps at sub-sample times (no test-voltage change), both lags: the
    # truth simulator's m l g₀ a(t) against linear_record's moment jumps ΔM̃ = accel_moment·Δa.
    lags = dict(torquer_time_constant=3e-5, filter_time_constant=1e-5)
    params = aj.ServoParams.reference(**lags)
    accel = np.array([0.3, 1.0, -0.8, 0.0])  # g
    index, shift = INDEX[:3], _shifts()[:3]
    n = 4000
    u_level, moment = 0.5, 1e-6
    record = step_truth.Record(
        levels=np.array([u_level]),
        change_times=np.zeros(0),
        rate=RATE,
        n=n,
        moment=moment,
        accel_levels=accel,
        accel_change_times=(index + shift) * DT,
    )
    device = step_truth.Device(T_dm=lags["torquer_time_constant"], T_f=lags["filter_time_constant"])
    t, u, y, a = step_truth.simulate(device, record, rng=np.random.default_rng(0))
    assert np.all(u == u_level)
    assert np.all(np.flatnonzero(np.diff(a)) + 1 == index + (shift > 0))
    per_g = float(accel_moment(params))
    ours = linear_record(
        params,
        DT,
        n,
        SequenceInputs(
            u_level,
            1.0,
            moment / float(params.torquer_gain) + per_g * accel[0],
            0.0,
            0.0,
            0.0,
            jnp.asarray(index),
            jnp.zeros(index.size),
            jnp.asarray(shift),
            per_g * jnp.asarray(np.diff(accel)),
        ),
    )
    assert np.ptp(y) > 1.0  # the steps move the output by volts
    np.testing.assert_allclose(np.asarray(ours), y, rtol=0, atol=1e-9)


@pytest.mark.parametrize("effect", ["none", "output_filter"])
def test_device_sets_hold_the_small_stop_and_acceleration_records(effect):
    truth = step_truth.draw_device_set(np.random.default_rng(5), effect, accel=True)
    records = step_truth.make_set(truth, np.random.default_rng(6))
    assert [r["name"] for r in records] == ["small", "stops", "accel"]
    d = truth["device"]
    lags = {"T_dm": d["T_dm"], "T_f": d["T_f"]}
    if effect == "none":
        assert lags == {"T_dm": 1e-5, "T_f": 1e-5} and truth["lag_s"] is None
    else:
        assert lags == {"T_dm": 1e-5, "T_f": truth["lag_s"]}
    stop = d["k_dp"] * d["k_y"] * d["h_max"]  # the stop voltage
    for rec, spec in zip(records, truth["records"], strict=True):
        assert rec["t"][0] == 0.0 and rec["t"].size == rec["u_out"].size == spec["n"]
        assert set(np.unique(rec["u_test"])) <= set(spec["levels_V"])
        swing = np.max(np.abs(spec["output_sign"] * (rec["u_out"] - spec["output_offset_V"])))
        if rec["name"] == "stops":  # driven onto the stops: a plateau at the stop voltage
            assert swing == pytest.approx(stop, rel=0.02)
            plateau = np.abs(np.abs(rec["u_out"] - spec["output_offset_V"]) - stop) < 0.01
            assert plateau.mean() > 0.3
        else:
            assert swing < stop
        if rec["name"] == "accel":
            assert np.all(rec["u_test"] == 0.0)
            assert set(np.unique(rec["a_in"])) == set(spec["accel_levels_g"])
        else:
            assert rec["a_in"] is None
    without = step_truth.draw_device_set(np.random.default_rng(5), "none", accel=False)
    assert [r["name"] for r in without["records"]] == ["small", "stops"]


@pytest.mark.parametrize("stop_over_level", [0.9, 1.2])
def test_stop_record_matches_exact_inelastic_contact_events(stop_over_level):
    # 0.9: held on the stop at ±2 V; 1.2: touched only in the overshoots. Sub-sample
    # changes and contacts; released at the exact change times.
    gain = float(IDEAL.pickoff_gain * IDEAL.amplifier_gain)
    stop = stop_over_level * 2.0
    _, _, y = _truth(h_max=stop / gain)
    ours = stop_record(
        *_still_device(),
        stop,
        -stop,
    )
    assert np.max(np.abs(y)) <= stop * (1 + 1e-12)
    np.testing.assert_allclose(np.asarray(ours), y, rtol=0, atol=2e-6)
    # Stops out of reach: the linear record.
    far = stop_record(
        *_still_device(),
        1e6,
        -1e6,
    )
    np.testing.assert_allclose(
        np.asarray(far), _record(IDEAL, _shifts(), moment=0.0, rate=0.0), atol=1e-12
    )


@pytest.mark.parametrize("torquer_lag", [0.0, 2e-5])
def test_stop_record_blocks_taken_whole_are_the_sample_records_means(torquer_lag):
    """A free block without a change taken whole (`whole_blocks`, m ≥ 4, m traced under
    `max_block` as the diagnosis passes it) against the sample-by-sample record (m = 1):
    held on the stop at ±2 V and released (with a torquer lag: after the change)."""
    params = aj.ServoParams.reference(torquer_time_constant=torquer_lag, filter_time_constant=0.0)
    _, dt, n, sequence = _still_device()
    stop = 1.8
    samples = np.asarray(stop_record(params, dt, n, sequence, stop, -stop))
    blocks = 300
    blocked = jax.jit(
        lambda m: stop_record(
            params, dt, blocks, sequence, stop, -stop, block=m, max_block=32,
            duration=dt * (n - 1),
        )
    )
    for m in (4, 20):
        means = samples[: blocks * m].reshape(-1, m).mean(1)
        np.testing.assert_allclose(np.asarray(blocked(m)), means, rtol=0, atol=1e-12)
    # A traced m beyond `max_block` goes sample by sample (no power past the ones made).
    short = jax.jit(
        lambda m: stop_record(
            params, dt, 100, sequence, stop, -stop, block=m, max_block=8, duration=dt * (n - 1)
        )
    )
    means = samples[:2000].reshape(-1, 20).mean(1)
    np.testing.assert_allclose(np.asarray(short(20)), means, rtol=0, atol=1e-12)


def test_change_time_derivative_matches_finite_differences():
    def first_change(d):
        shift = jnp.asarray(_shifts()).at[0].set(d)
        return linear_record(
            IDEAL,
            DT,
            4000,
            SequenceInputs(
                LEVELS[0], 1.0, 0.0, 0.0, 0.0, 0.0, jnp.asarray(INDEX), jnp.asarray(STEPS), shift
            ),
        )

    for d in (-0.4, 0.3, 1.7):  # on either side of the sample where u_test shows it
        exact = jax.jacfwd(first_change)(jnp.asarray(d))
        h = 1e-6
        numeric = (first_change(d + h) - first_change(d - h)) / (2 * h)
        scale = float(jnp.max(jnp.abs(exact)))
        np.testing.assert_allclose(exact, numeric, rtol=0, atol=1e-6 * scale)
    # A continuous derivative (C¹) where the change crosses a sample instant.
    below, above = (jax.jacfwd(first_change)(jnp.asarray(x)) for x in (-1e-9, 1e-9))
    np.testing.assert_allclose(below, above, rtol=0, atol=1e-6 * float(jnp.max(jnp.abs(below))))


def _context(n_blocks, change_index, change_step):
    j = change_index.size
    return StepContext(
        dt=jnp.asarray(DT),
        duration=jnp.asarray(DT * (n_blocks - 1)),
        first_level=jnp.asarray(LEVELS[0]),
        polarity=jnp.asarray(1.0),
        sigma_ref=jnp.asarray(1e-3),
        scale=jnp.asarray(1.0),
        lag_unit=jnp.asarray(8.7e-6),
        mid=jnp.asarray(0.0),
        half=jnp.asarray(2.0),
        change_index=jnp.asarray(change_index),
        change_step=jnp.asarray(change_step),
        held_out_change=jnp.zeros(j),
        train=jnp.ones(n_blocks),
        test=jnp.zeros(n_blocks),
        block=jnp.asarray(1, jnp.int32),
        max_block=1,
    )


def test_every_effect_is_the_nominal_model_at_zero():
    effects = step_effects()
    assert [e.name for e in effects] == [
        "torquer_lag",
        "output_filter",
        "stop_saturation",
        "disturbance_drift",
        "colored_noise",
        "stop_contact",
        "moment_noise",
    ]
    ctx = _context(N, INDEX, STEPS)
    base = aj.ServoParams.reference()
    sigma = jnp.full(4, 0.05)
    w = jnp.zeros(W.FIXED + INDEX.size).at[1].set(0.3).at[W.FIXED :].set(jnp.asarray(_shifts()))
    nominal = unpack(w, 0, effects, base, sigma, ctx)
    y0 = predict(nominal, ctx, N, "linear")
    for i, effect in enumerate(effects, start=1):
        m = unpack(w, i, effects, base, sigma, ctx)
        mode = "contact" if effect.contact_stops else "clamp" if effect.nonlinear else "linear"
        y = predict(m, ctx, N, mode)
        np.testing.assert_allclose(y, y0, rtol=0, atol=1e-12, err_msg=effect.name)
        assert float(m.phi) == 0.0 and float(m.output_offset) == 0.0


def test_innovations_of_white_plus_ar1_noise():
    rng = np.random.default_rng(4)
    e = rng.normal(size=3000)
    a, log_v = innovation_terms(jnp.asarray(e), 0.0, 0.0, 0.0)
    np.testing.assert_allclose(a, e, atol=1e-15)
    assert float(log_v) == 0.0
    # The blocked recursion against a plain loop: a_k = e_k − φ e_{k−1} + θ a_{k−1}, the
    # first error scaled by the first block's variance, with θ of either sign.
    for phi, theta, variance in ((0.9, 0.36, 2.5), (0.97, -0.2, 9.0)):
        a, log_v = innovation_terms(jnp.asarray(e), phi, theta, np.log(variance))
        loop = np.empty_like(e)
        loop[0] = e[0] / np.sqrt(variance)
        for k in range(1, e.size):
            loop[k] = e[k] - phi * e[k - 1] + theta * loop[k - 1]
        np.testing.assert_allclose(a, loop, atol=1e-12)
        assert float(log_v) == pytest.approx(np.log(variance))
    # White + AR(1) noise per sample (blocks of one sample) is whitened: its innovations
    # have the predicted one-step variance.
    from accel_jax.diagnose.step.effects import block_noise

    sigma_w, ratio, phi = 1.0, 4.0, 0.95
    phi_b, theta, first, variance = block_noise(ratio, phi, 1, 16)
    ar = np.zeros(200_000)
    w = rng.normal(size=ar.size) * np.sqrt(ratio * (1 - phi**2))
    for k in range(1, ar.size):
        ar[k] = phi * ar[k - 1] + w[k]
    x = ar + sigma_w * rng.normal(size=ar.size)
    a, _ = innovation_terms(jnp.asarray(x), phi_b, theta, jnp.log(first))
    a = np.asarray(a)[100:]
    assert np.var(a) == pytest.approx(float(variance) * sigma_w**2, rel=0.02)
    assert abs(np.corrcoef(a[1:], a[:-1])[0, 1]) < 0.01


@pytest.mark.parametrize("n", [1, 15, 17, 257, 4099])
@pytest.mark.parametrize("theta", [0.0, -0.9, 0.999])
def test_the_blocked_first_order_filter_is_the_plain_recursion(n, theta):
    # Lengths that are not a multiple of the block, a negative and a near-unit pole.
    from accel_jax.diagnose.step.innovations import _first_order_filter

    b = np.random.default_rng(n).normal(size=n)
    loop = np.empty(n)
    loop[0] = b[0]
    for k in range(1, n):
        loop[k] = b[k] + theta * loop[k - 1]
    a = np.asarray(_first_order_filter(jnp.asarray(b), theta))
    np.testing.assert_allclose(a, loop, rtol=0, atol=1e-12 * max(1.0, np.max(np.abs(loop))))


@pytest.mark.parametrize("lags", [(3e-5, 1e-5), (1e-5, 3e-5)])
def test_stop_record_with_lags_releases_where_the_truth_simulator_does(lags):
    # Stop-level steps (±5.5 V onto stops at 4.04 V) with a lagged torquer and output
    # filter: after a change the lagged moment keeps the pendulum on the stop for a while,
    # and the release falls within a sample step. Released at the sample boundary instead,
    # the record was 12.8 mV off; with the release found within the step, 1.1e-5 V.
    t_dm, t_f = lags
    params = aj.ServoParams.reference(
        torquer_time_constant=t_dm, filter_time_constant=t_f, external_moment=0.0
    )
    levels = np.array([0.0, 5.5, -5.5, 5.5, 0.0])
    times = np.array([1.5003e-3, 3.3007e-3, 5.1002e-3, 6.9009e-3])
    n = 9000
    device = step_truth.Device(h_max=float(params.stop_displacement), T_dm=t_dm, T_f=t_f)
    record = step_truth.Record(levels=levels, change_times=times, rate=RATE, n=n)
    t, _, y = step_truth.simulate(device, record, rng=np.random.default_rng(0))
    index = np.searchsorted(t, times, side="right")
    sequence = SequenceInputs(
        0.0,
        1.0,
        0.0,
        0.0,
        0.0,
        0.0,
        jnp.asarray(index, jnp.int32),
        jnp.asarray(np.diff(levels)),
        jnp.asarray((times - t[index]) / DT),
    )
    stop = float(params.pickoff_gain * params.amplifier_gain * params.stop_displacement)
    ours = np.asarray(stop_record(params, DT, n, sequence, stop, -stop))
    assert np.sum(np.abs(y) > 0.999 * stop) > 0.3 * n  # on the stops for a third of it
    np.testing.assert_allclose(ours, y, rtol=0, atol=3e-5)
