"""The compliant-stop truth simulator (studies/contact_truth.py), checked against other
computations: step_truth's simulator and an exact matrix-exponential solution of the free
loop (far stops), step_truth's inelastic stop (a stiff, heavily damped contact), the free
response (the side without a stop), the contact law itself on the dense solution, and the
integration refined (rtol and the largest steps halved). NumPy/SciPy only."""

import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.linalg import expm

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "studies"))
import contact_truth  # noqa: E402
import step_truth  # noqa: E402


def _quiet(rec):
    """The record's clean output: no noise, ADC, offset or sign change."""
    return dataclasses.replace(
        rec, noise=0.0, adc_step=0.0, output_offset=0.0, output_sign=1.0, gm=(0.0, 1.0)
    )


def _step_device(d: dict, h_max=float("inf")):
    device = step_truth.Device(
        J=d["J"], mu=d["mu"], c=d["c"], k_dm=d["k_dm"], k_dp=d["k_dp"], k_y=d["k_y"], h_max=h_max
    )
    device.test_gain = d["test_gain"]
    return device


def _contact_device(d: dict, **values):
    """A `ContactDevice` of a drawn device's values (no stops unless given)."""
    return dataclasses.replace(contact_truth._base_device(d), **values)


def _drawn_start(truth):
    """The truth with its drawn start (not the start against a stop)."""
    return {
        **truth,
        "start": truth["drawn_start"],
        "start_level_V": truth["drawn_start_level_V"],
        "start_against_stop": False,
    }


def _exact_free(device: contact_truth.ContactDevice, rec, start=None):
    """U_out of the free loop (no stops, T_dm = T_f = 0) at the record's times, exactly:
    x' = A x + b(u) solved by matrix exponentials from level change to level change;
    from the record's start, or from `start` = (t_begin, (θ, θ')) (NaN before t_begin)."""
    a = np.array([[0.0, 1.0], [-device.k_loop / device.J, -device.mu / device.J]])
    t = rec.t0 + np.arange(rec.n) / rec.rate
    levels, changes = np.asarray(rec.levels), np.asarray(rec.change_times)

    def rest(u):
        return np.array([(device.k_dm * device.test_gain * u + rec.moment) / device.k_loop, 0.0])

    if start is not None:
        t_begin, x = start[0], np.asarray(start[1], dtype=float)
    elif rec.start == "rest":
        t_begin, x = t[0], rest(levels[0])
    else:
        t_begin, x = t[0] - float(rec.start), rest(rec.start_level)
    edges = np.concatenate([[t_begin], changes[(changes > t_begin) & (changes < t[-1])], [np.inf]])
    out = np.full(rec.n, np.nan)
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        x_end = rest(levels[np.searchsorted(changes, lo, side="right")])
        for k in np.flatnonzero((t >= lo) & (t < hi)):
            out[k] = (x_end + expm(a * (t[k] - lo)) @ (x - x_end))[0]
        if np.isfinite(hi):
            x = x_end + expm(a * (hi - lo)) @ (x - x_end)
    return device.gain * out


def _restitution(zeta):
    """e(ζ_c): the velocity a unilateral Kelvin–Voigt contact returns, of a unit impact
    velocity, in the contact's own time (δ'' = −δ − 2ζ δ' until δ + 2ζ δ' = 0)."""

    def release(t, y):
        return y[0] + 2 * zeta * y[1]

    release.terminal, release.direction = True, -1
    sol = solve_ivp(
        lambda t, y: [y[1], -y[0] - 2 * zeta * y[1]],
        (0.0, 100.0),
        [0.0, 1.0],
        events=release,
        rtol=1e-12,
        atol=1e-14,
        max_step=0.01,
    )
    return float(-sol.y[1, -1])


# --------------------------------------------------------------------------------------
# 1. Far stops: step_truth's "none" world
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("effect", contact_truth.CONTACT_CLASSES)
def test_draws_are_step_truths_world(effect):
    """The device, sequence and conventions are step_truth.draw_truth's, draw for draw."""
    for seed in (0, 1, 2):
        truth = contact_truth.draw_truth(np.random.default_rng(seed), effect)
        world = step_truth.draw_truth(np.random.default_rng(seed), "none")
        for key, value in world.items():
            if key == "effect":
                continue
            mine = truth[
                {"start": "drawn_start", "start_level_V": "drawn_start_level_V"}.get(key, key)
            ]
            assert mine == value, key


def test_far_stops_give_step_truths_none_record():
    """h = ∞ on both sides: the clean record equals step_truth's (no stops) and the exact
    matrix-exponential solution, to 1e-9 V."""
    worst = {"step_truth": 0.0, "exact": 0.0}
    for seed in (0, 1, 2):
        truth = contact_truth.draw_truth(np.random.default_rng(seed), "stop_compliant")
        rec = _quiet(contact_truth.contact_record(_drawn_start(truth)))
        device = contact_truth.contact_device(truth)
        device.h_hi = device.h_lo = float("inf")
        mine = contact_truth.run(device, rec)["clean"]
        _, _, theirs = step_truth.simulate(
            _step_device(truth["device"]), rec, rng=np.random.default_rng(0)
        )
        worst["step_truth"] = max(worst["step_truth"], float(np.max(np.abs(mine - theirs))))
        worst["exact"] = max(worst["exact"], float(np.max(np.abs(mine - _exact_free(device, rec)))))
    print(
        f"far stops: max |contact_truth − step_truth| = {worst['step_truth']:.2e} V, "
        f"max |contact_truth − exact| = {worst['exact']:.2e} V"
    )
    assert worst["step_truth"] < 1e-9
    assert worst["exact"] < 1e-9


def test_far_stops_make_is_step_truths_make():
    """make(): the same columns, noise stream and output conventions as step_truth.make of
    the "none" world (the outputs equal but where the clean outputs' ≤ 1e-9 V difference
    tips an ADC rounding)."""
    truth = _drawn_start(contact_truth.draw_truth(np.random.default_rng(4), "stop_uneven"))
    truth["h_hi_m"] = truth["h_lo_m"] = None
    t, u, y, noise = contact_truth.make(truth, np.random.default_rng(11))
    t2, u2, y2, noise2 = step_truth.make({**truth, "effect": "none"}, np.random.default_rng(11))
    np.testing.assert_array_equal(t, t2)
    np.testing.assert_array_equal(u, u2)
    step = truth["adc_step_V"]
    assert np.max(np.abs(y - y2)) <= step * (1 + 1e-9)
    assert np.mean(y != y2) < 1e-3
    assert np.max(np.abs((y - noise) - (y2 - noise2))) < 1e-9


# --------------------------------------------------------------------------------------
# 2. The inelastic limit
# --------------------------------------------------------------------------------------


def test_stiff_damped_contact_approaches_inelastic_stop():
    """κ = 1e5, ζ_c = 3 at step_truth's stop_saturation clearance (both sides) against its
    inelastic stop. The held level: on the samples the inelastic record holds at the stop,
    the compliant one is the stop voltage plus the spring's static compression
    (|U_settled| − U_stop)/(1 + κ) (a few 1e-6 of U_stop) to 1e-7 U_stop on most of
    them; the rest are the rebounds after impacts. The whole record (the clipped segments
    and their transients) agrees to e(ζ_c) U_stop, e the contact's restitution (0.024 at
    ζ_c = 3: the inelastic stop keeps no velocity, the contact returns e of it whatever
    its stiffness); found ≈ 0.1 e. With ζ_c = 1 (e = 0.135) the deviation is larger."""
    kappa, zeta = 1e5, 3.0
    restitution = _restitution(zeta)
    for seed in (3, 8):
        truth = step_truth.draw_truth(np.random.default_rng(seed), "stop_saturation")
        d = truth["device"]
        device = _contact_device(d)
        h = truth["stop_over_u_max"] * truth["u_max_V"] * device.k_test / (device.k_dp * device.k_y)
        device.h_hi = device.h_lo = h
        rec = _quiet(
            step_truth.Record(
                levels=np.asarray(truth["levels_V"]),
                change_times=np.asarray(truth["change_times_s"]),
                rate=truth["rate"],
                n=int(round(step_truth.DURATION * truth["rate"])),
                moment=truth["moment_Nm"],
                start=truth["start"],
                start_level=truth["start_level_V"],
            )
        )
        _, u, inelastic = step_truth.simulate(
            _step_device(d, h_max=h), rec, rng=np.random.default_rng(0)
        )
        stop_V = h * device.k_dp * device.k_y
        device.K_c, device.C_c = contact_truth.contact_parameters(device, kappa, zeta)
        compliant = contact_truth.run(device, rec)["clean"]
        diff = compliant - inelastic
        held = np.abs(np.abs(inelastic) - stop_V) < 1e-9 * stop_V
        assert held.sum() > 100  # the record holds on a stop
        settled = device.k_test * device.test_gain * u + device.gain * rec.moment / device.k_loop
        compression = np.sign(inelastic) * (np.abs(settled) - stop_V) / (1 + kappa)
        level_error = np.abs(diff - compression)[held] / stop_V
        on_level = np.mean(level_error < 1e-7)
        worst = float(np.max(np.abs(diff))) / stop_V
        print(
            f"seed {seed}: held samples {held.sum()}, at the compressed stop level (1e-7) "
            f"{on_level:.1%}, median level error {np.median(level_error):.1e} U_stop, "
            f"compression ≤ {np.max(np.abs(compression[held])) / stop_V:.1e} U_stop; "
            f"max |compliant − inelastic| = {worst:.2e} U_stop (e(3) = {restitution:.3f})"
        )
        assert on_level > 0.5
        assert np.median(level_error) < 1e-7
        assert worst < restitution
        if seed == 3:
            device.K_c, device.C_c = contact_truth.contact_parameters(device, kappa, 1.0)
            softer = contact_truth.run(device, rec)["clean"]
            worst_1 = float(np.max(np.abs(softer - inelastic))) / stop_V
            print(
                f"  ζ_c = 1: max |compliant − inelastic| = {worst_1:.2e} U_stop "
                f"(e(1) = {_restitution(1.0):.3f})"
            )
            assert worst_1 > 2 * worst
            assert worst_1 < _restitution(1.0)


# --------------------------------------------------------------------------------------
# 3. One stop only
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("side", [1, -1])
def test_one_sided_leaves_the_other_side_free(side):
    """One stop (on `side`, at 1/1.4 of the free peak there). The sequence swings the
    pendulum to the other side (0 → −side U → 0), then presses it onto the stop (+side U)
    and throws it from there to the other side (−side U → 0). Before the first contact the
    record is the free one; after the last release it is the exact free solution from the
    release state (matrix exponentials), to 1e-9 V: the other side's excursions, beyond the
    stop's clearance mirrored (a symmetric stop would clip them), are not clipped."""
    truth = step_truth.draw_truth(np.random.default_rng(21), "none")
    base = _contact_device(truth["device"])
    u_big = 2.0 * side / base.test_gain  # drives θ towards `side`
    rec = step_truth.Record(
        levels=np.array([0.0, -u_big, 0.0, u_big, -u_big, 0.0]),
        change_times=np.array([1e-3, 3e-3, 5e-3, 8e-3, 10e-3]),
        rate=1e6,
        n=12000,
    )
    free = contact_truth.run(base, rec)
    peak_free = float(np.max(side * free["theta"])) * base.l
    clearance = peak_free / 1.4
    device = dataclasses.replace(base, **{"h_hi" if side > 0 else "h_lo": clearance})
    device.K_c, device.C_c = contact_truth.contact_parameters(device, 300.0, 0.3)
    result = contact_truth.run(device, rec)
    contacts = result["contacts"]
    assert contacts and all(c[2] == side for c in contacts)
    t_first, t_last = contacts[0][0], contacts[-1][1]
    assert 5e-3 < t_first and t_last < 10e-3  # only while driven towards the stop
    t, theta = result["t"], result["theta"]
    before, after = t < t_first, t > t_last
    gap_before = float(np.max(np.abs(result["clean"][before] - free["clean"][before])))
    piece = next(p for p in result["pieces"] if p[0] < t_last <= p[1])
    released = piece[3](t_last)[:2]
    exact = _exact_free(device, dataclasses.replace(rec), start=(t_last, released))
    gap_after = float(np.max(np.abs(result["clean"][after] - exact[after])))
    other_before = float(np.max(-side * theta[before])) * base.l / clearance
    other_after = float(np.max(-side * theta[after])) * base.l / clearance
    clipped = float(np.max(side * theta)) * base.l / peak_free
    print(
        f"side {side:+d}: {len(contacts)} contacts; max |contact − free| before the first "
        f"{gap_before:.1e} V, after the last release (exact free) {gap_after:.1e} V; other "
        f"side's peaks {other_before:.2f} and {other_after:.2f} × the clearance; the stop "
        f"side's peak clipped to {clipped:.3f} of the free one"
    )
    assert gap_before < 1e-9
    assert gap_after < 1e-9
    assert other_before > 1.1 and other_after > 1.1
    assert clipped < 0.95


# --------------------------------------------------------------------------------------
# 4. The contact law on the dense solution
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("kappa, zeta", [(100.0, 1.5), (3000.0, 0.05), (30.0, 0.5)])
def test_contact_force_is_never_negative(kappa, zeta):
    """On a dense grid of every integration piece, the law M_contact = ∓max(0, F) where
    δ > 0 (F = K_c δ + C_c δ'): where a contact pushes, F ≥ 0 and δ ≥ 0 (the contact
    never pulls); where no contact pushes, δ ≤ 0 or F ≤ 0 (the law gives no force there
    either: after a release by the damper the pendulum is free inside the surface, δ > 0,
    F < 0). Both at once: g = min(K_c δ, F) ≥ 0 on the pushing pieces, ≤ 0 on the others,
    to 1e-9 K_c h/l (the pieces end a hair, ≤ 1e-9 s, past their events). The damped
    contacts release with δ > 0 (the unilateral clause acts)."""
    # A record that starts pressed into the lower stop and hits both stops.
    truth = contact_truth.draw_truth(np.random.default_rng(1), "stop_compliant")
    assert truth["start"] == "on_stop_low"
    truth = {**truth, "kappa": kappa, "zeta_c": zeta}
    device = contact_truth.contact_device(truth)
    result = contact_truth.run(device, _quiet(contact_truth.contact_record(truth)))
    loop = result["loop"]
    scale = device.K_c * min(device.h_hi, device.h_lo) / device.l  # N·m
    push_min, gate_pushing, gate_free, released_inside = np.inf, np.inf, -np.inf, 0
    for t_a, t_b, mode, solution in result["pieces"]:
        states = solution(np.linspace(t_a, t_b, 400)).T
        for side in loop.sides:
            gates = np.array([loop.gate(y, side) for y in states])
            if mode == side:
                push = np.array([loop.push(y, side) for y in states])
                push_min = min(push_min, float(np.min(push)))
                gate_pushing = min(gate_pushing, float(np.min(gates)))
                moments = np.array([loop.contact_moment(y, side) for y in states])
                assert np.all(-side * moments >= 0)
            else:
                gate_free = max(gate_free, float(np.max(gates)))
    pieces = result["pieces"]
    for (_, t_b, mode, solution), following in zip(pieces[:-1], pieces[1:], strict=True):
        if mode != 0 and following[2] == 0:  # a release
            released_inside += loop.penetration(solution(t_b), mode)[0] > 0
    print(
        f"κ {kappa:g}, ζ_c {zeta:g}: {len(result['contacts'])} contacts, "
        f"{released_inside} released inside the surface; pushing: min F = "
        f"{push_min / scale:.1e}, min g = {gate_pushing / scale:.1e}; not pushing: "
        f"max g = {gate_free / scale:.1e} (units of K_c h/l)"
    )
    assert len(result["contacts"]) >= 5
    assert {c[2] for c in result["contacts"]} == {1, -1}
    assert push_min > -1e-9 * scale
    assert gate_pushing > -1e-9 * scale
    assert gate_free < 1e-9 * scale
    assert released_inside >= 1


def test_a_graze_inside_a_step_is_caught():
    """A free peak 1e-7 beyond the clearance: δ > 0 for ≈ 0.3 µs, inside one integration
    step. The run finds it at the turning point (a graze) and gives the record of a run
    with steps 50 × smaller, which sees the contact by its ordinary event."""
    base = contact_truth.ContactDevice()
    rec = step_truth.Record(
        levels=np.array([0.0, 2.0]), change_times=np.array([5e-4]), rate=1e6, n=2000
    )
    free = contact_truth.run(base, rec)
    device = dataclasses.replace(base, h_hi=float(np.max(free["theta"])) * base.l * (1 - 1e-7))
    device.K_c, device.C_c = contact_truth.contact_parameters(device, 1000.0, 0.2)
    result = contact_truth.run(device, rec)
    fine = contact_truth.run(device, rec, step_scale=0.02)
    effect = float(np.max(np.abs(result["clean"] - free["clean"])))
    gap = float(np.max(np.abs(result["clean"] - fine["clean"])))
    print(
        f"graze: the contact changes the record by {effect:.1e} V; default vs 50× smaller "
        f"steps {gap:.1e} V"
    )
    assert result["grazes"] == 1 and fine["grazes"] == 0
    assert len(result["contacts"]) == len(fine["contacts"]) == 1
    assert effect > 1e-7
    assert gap < 1e-9


# --------------------------------------------------------------------------------------
# 5.–6. Reproducible, converged
# --------------------------------------------------------------------------------------


def test_same_seed_same_record():
    for effect in contact_truth.CONTACT_CLASSES:
        truth = contact_truth.draw_truth(np.random.default_rng(7), effect)
        assert truth == contact_truth.draw_truth(np.random.default_rng(7), effect)
        assert json.loads(json.dumps(truth)) == truth  # JSON-able
        first = contact_truth.make(truth, np.random.default_rng(8))
        second = contact_truth.make(truth, np.random.default_rng(8))
        for a, b in zip(first, second, strict=True):
            np.testing.assert_array_equal(a, b)
        t, u, y, noise = first
        assert t[0] == 0.0 and t.size == int(round(step_truth.DURATION * truth["rate"]))
        assert np.std(noise) > 0.5 * truth["noise_V"]


@pytest.mark.parametrize("effect", contact_truth.CONTACT_CLASSES)
def test_halving_rtol_and_steps_changes_the_record_below_1e9_volt(effect):
    worst = 0.0
    for seed in (0, 2):
        truth = contact_truth.draw_truth(np.random.default_rng(seed), effect)
        device, rec = contact_truth.contact_device(truth), contact_truth.contact_record(truth)
        coarse = contact_truth.run(device, rec, rtol=1e-10)["clean"]
        fine = contact_truth.run(device, rec, rtol=5e-11, step_scale=0.5)["clean"]
        worst = max(worst, float(np.max(np.abs(coarse - fine))))
    print(f"{effect}: rtol 1e-10 → 5e-11 and the largest steps halved: max change {worst:.1e} V")
    assert worst < 1e-9


# --------------------------------------------------------------------------------------
# The draws and the start against a stop
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("effect", contact_truth.CONTACT_CLASSES)
def test_draws_reach_their_stops(effect):
    """The clearances follow the drawn factors, the near stop is reached and clips the
    free peak, one-sided devices have one stop, and the start against a stop rests
    pressed into it."""
    starts_against = 0
    for seed in range(8):
        truth = contact_truth.draw_truth(np.random.default_rng(100 + seed), effect)
        near = truth["near_side"]
        h = {1: truth["h_hi_m"], -1: truth["h_lo_m"]}
        free_peak = {1: truth["free_peak_hi_m"], -1: truth["free_peak_lo_m"]}
        assert contact_truth.KAPPA[0] <= truth["kappa"] <= contact_truth.KAPPA[1]
        assert contact_truth.ZETA_C[0] <= truth["zeta_c"] <= contact_truth.ZETA_C[1]
        assert free_peak[near] / h[near] == pytest.approx(truth["peak_over_clearance"], rel=1e-12)
        assert contact_truth.SIDE_NAMES[near] in truth["sides_reached"]
        assert truth["clip_ratio"] < 1
        if effect == "stop_one_sided":
            assert h[-near] is None and truth["sides_reached"] == [contact_truth.SIDE_NAMES[near]]
        elif effect == "stop_uneven":
            assert h[-near] / h[near] == pytest.approx(truth["far_over_near"], rel=1e-12)
        else:
            assert h[1] == h[-1]
        if truth["start_against_stop"]:
            starts_against += 1
            side = step_truth.ON_STOP_STARTS[truth["start"]]
            result = contact_truth.run(
                contact_truth.contact_device(truth), _quiet(contact_truth.contact_record(truth))
            )
            assert result["contacts"][0][0] == result["t"][0] and result["contacts"][0][2] == side
            assert side * result["theta"][0] * result["loop"].d.l > h[side]
    print(f"{effect}: {starts_against} of 8 records start against a stop")


def test_start_against_stop_is_a_static_equilibrium():
    """Held by its holding level, the pendulum stays pressed into the stop, the spring
    compressed to the static balance; the record's lower level then pushes it off."""
    device = contact_truth.ContactDevice(h_hi=1.9e-6, h_lo=2.5e-6)
    device.K_c, device.C_c = contact_truth.contact_parameters(device, 50.0, 0.4)
    reach = 1.9e-6 * device.k_dp * device.k_y / device.k_test  # the level that just reaches it
    hold = 1.3 * reach
    rec = step_truth.Record(
        levels=np.array([hold, 0.5 * reach]),
        change_times=np.array([1e-3]),
        rate=1e6,
        n=3000,
        start="on_stop_high",
        hold_level=hold,
    )
    result = contact_truth.run(device, rec)
    theta = result["theta"]
    before = result["t"] < 1e-3
    balance = (device.k_loop + device.K_c) * theta[0] - (
        device.k_dm * hold + device.K_c * device.h_hi / device.l
    )
    assert abs(balance) < 1e-12 * device.K_c * device.h_hi / device.l
    assert np.max(np.abs(theta[before] - theta[0])) < 1e-12 * theta[0]
    assert theta[0] * device.l > device.h_hi
    assert np.min(theta[~before]) * device.l < device.h_hi  # pushed off the stop
    with pytest.raises(ValueError, match="does not press"):
        contact_truth.run(device, dataclasses.replace(rec, hold_level=0.9 * reach))
