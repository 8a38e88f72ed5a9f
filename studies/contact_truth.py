"""An independent truth simulator of step records of a closed-loop pendulum accelerometer
whose mechanical stops are compliant spring-damper contacts (SciPy, not JAX).

Written from the loop equations of docs/models.md §1, as `step_truth.py` is, with none of
the library's code; it reuses `step_truth`'s world (the drawn device, the small-step test
sequence, the recorder conventions, `Record`, the output noise and ADC handling) and
replaces its inelastic stops by compliant contacts. It is a test bench for a diagnosis of
such records, and for another simulator of compliant stops (`contact_device` gives the
physical values to compare).

Loop (SI units; θ the pendulum's angle, M the external moment, constant or a ramp):

    J θ'' + μ θ' + c θ = M_dm + M(t) + M_contact,   M(t) = M_0 + Ṁ t
    T_dm M_dm' = k_dm (g_w U_test(t) − U_amp) − M_dm      (M_dm algebraic when T_dm = 0)
    U_amp = k_dp k_y l θ,  T_f U_f' = U_amp − U_f,  U_out = U_f   (U_out = U_amp when T_f = 0)

Contacts. The upper stop's surface is at l θ = +h_hi, the lower one's at l θ = −h_lo; either
may be absent (h = ∞: a one-sided device). Each is a unilateral Kelvin–Voigt contact: with
the penetration δ = θ − h_hi/l (upper stop) or δ = −h_lo/l − θ (lower stop, the mirror
image), and while δ > 0,

    M_contact = ∓ max(0, K_c δ + C_c δ')        (− on the upper stop, + on the lower)

and 0 otherwise: the contact pushes the pendulum back, never pulls it in. K_c = κ k_loop
with k_loop = c + k_dm k_dp k_y l the loop's static stiffness, and C_c = 2 ζ_c √(K_c J).
The push F = K_c δ + C_c δ' is what the max(0, ·) clips: the pendulum enters a contact when
δ crosses 0 upward (F = C_c δ' > 0 there), and leaves it when F falls through 0. With
damping, F reaches 0 while δ is still > 0 (the damper would pull on the way out, δ' < 0):
the pendulum leaves the contact with the surface still indented (an idealised surface that
recovers at once behind it), flies free, and is pushed again only if F = K_c δ + C_c δ'
turns positive again while δ > 0 (the surface catches up with it) or after δ has crossed 0
upward again. Both, entry and release, are one event: the zero crossing of
g = min(K_c δ, K_c δ + C_c δ'), upward into a contact, downward out of it (g > 0 exactly
where the contact pushes). Each mode (free, on the upper contact, on the lower contact) is
a smooth linear system, integrated by SciPy's `solve_ivp` (DOP853) from event to event and
from test-voltage change to change. After an event the integration restarts a hair past
it (≤ 1e-9 s, where g is strictly on the new mode's side, so that the next crossing is
seen however soon it comes: a short flight between two bounces). A contact that grazes the
surface inside one integration step (δ > 0 for less than a step, no sign change of g at
the step's ends) is caught at the pendulum's turning point inside it (a non-terminal event
on θ' = 0) and the integration restarted at its entry. The steps are bounded by
`FREE_STEP` (off the contacts) and `CONTACT_STEP` (on them); the error control does the
rest (rtol 1e-10; the absolute tolerances scale with it). DOP853 rather than an implicit
method: the contacts drawn here are only moderately stiff (ω_c = √(K_c/J) ≤ √3000 ≈ 55 ×
the loop's natural frequency), the bounded explicit steps resolve the impacts (which a
record shows), and each mode's linear system would gain little from Radau at rtol 1e-10
(a record held 6 ms on a κ = 1e5, ζ_c = 3 contact takes ≈ 3 s).

The inelastic limit. A unilateral Kelvin–Voigt contact returns a fraction e(ζ_c) of the
impact velocity whatever K_c (the release F = 0 comes at a time and state that scale with
1/ω_c): e ≈ 0.86 at ζ_c = 0.05, 0.45 at 0.3, e^−2 ≈ 0.135 at 1, 0.048 at 2, 0.024 at 3.
So a stiff contact approaches `step_truth`'s inelastic stop (velocity lost at contact)
only as ζ_c grows too: the held level converges as 1/κ (the spring's static compression),
the impacts' rebounds as e(ζ_c) (tests/test_contact_truth.py).

Start states (`step_truth.Record.start`): "rest" (at rest under the first level long
before t0; a rest beyond a stop is the equilibrium pressed into it, the contact spring
compressed), a number (the first level switched on that long before t0 from rest under
`start_level`), or "on_stop_high" / "on_stop_low": the pendulum resting pressed into that
stop at t0, in the static equilibrium (k_loop + K_c) θ = k_dm g_w U_hold + M ± K_c h/l
under a holding voltage `hold_level` that presses harder than the level that just reaches
the stop (the torquer and the output filter settled there too); the record's own level
comes on at t0 and the spring pushes the pendulum off the stop or keeps it pressed, as the
dynamics say (see `START_AGAINST_STOP_P`).

The drawn records (`draw_truth`, `make`): the device, the small-step sequence and the
recorder conventions exactly as `step_truth.draw_truth` draws them (the same draws in the
same order; T_dm = T_f = 0, as its stop records), then a contact of one of
`CONTACT_CLASSES` whose clearance is set from the drawn sequence's own free response so
that the record reaches the stop (`PEAK_OVER_CLEARANCE`). The output as step_truth's:
output_sign × U_out + output_offset + white noise, quantised by the ADC.

Everything is float64 NumPy/SciPy.
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np
from scipy.integrate import solve_ivp
from scipy.optimize import brentq

sys.path.insert(0, str(Path(__file__).resolve().parent))
import step_truth  # noqa: E402

CONTACT_CLASSES = ("stop_compliant", "stop_one_sided", "stop_uneven")
"""The record classes: "stop_compliant", two compliant stops at the same clearance;
"stop_one_sided", one compliant stop (side drawn, see `USABLE_SIDE`), none on the other
side; "stop_uneven", two compliant stops at different clearances (`FAR_OVER_NEAR`)."""

KAPPA = (10.0, 3000.0)
"""κ = K_c / k_loop, the contact's stiffness over the loop's static stiffness, log-uniform.
At κ = 10 the contact is soft (the pendulum sinks well into it: a level that would settle
1.5 × the clearance out is held at 1 + 0.5/11 ≈ 1.05 of it); at 3000 it rings at
√3000 ≈ 55 × the loop's natural frequency (≈ 30 kHz, a 33 µs period)."""

ZETA_C = (0.05, 2.0)
"""ζ_c, the contact's damping ratio (C_c = 2 ζ_c √(K_c J)), log-uniform: from a ringing,
nearly elastic contact (the pendulum bounces off) to an overdamped one."""

PEAK_OVER_CLEARANCE = (1.1, 1.6)
"""The free (no-stop) response's peak deflection on the near stop's side over that stop's
clearance, uniform: the record reaches its stop and the contact clips the peak. The free
response is the drawn record's own (its sequence from its drawn start, `draw_truth`),
sampled at the record's times."""

FAR_OVER_NEAR = (1.3, 3.0)
"""h_far / h_near of a "stop_uneven" device, uniform: the far stop's clearance over the
near one's (the far one may or may not be reached: `sides_reached` says)."""

USABLE_SIDE = 0.5
"""A side can carry the near (or only) stop when the free response's peak deflection on
that side is ≥ this × the settled deflection of the full level U_max (k_test U_max /
(k_dp k_y) in metres): the sequence drives the pendulum towards that side. The drawn side
(`near_side`) is replaced by the other one when it is not usable (at least one side is:
the sequence reaches ±U_max at least once)."""

START_AGAINST_STOP_P = 0.25
"""The probability that a record starts with the pendulum resting pressed into a stop
(`start_against_stop`): the upper or lower one at even odds for two stops, the only one
for "stop_one_sided". An earlier test voltage U_hold = `HOLD_OVER_REACH` × the level whose
settled free deflection (with the record's moment) just reaches that stop's surface held
it there, the contact spring compressed to the static equilibrium; at t0 it was switched
off and the record's own sequence took over (`start` "on_stop_high" / "on_stop_low",
`start_level_V` = U_hold). The clearances are set from the free response of the record's
drawn start (`drawn_start`), not from this one."""

HOLD_OVER_REACH = (1.2, 1.5)
"""U_hold over the level that just reaches the stop, uniform (as step_truth.ON_STOP_HOLD)."""

FREE_STEP = 0.2
"""The largest integration step off the contacts, in units of the loop's time constant
√(J/k_loop) (≈ 290 µs): the error control (rtol) sets the steps below it; it keeps the
loop's turning points (θ' = 0, half a damped period ≈ 1 ms apart) one per step, so that a
graze inside a step is seen."""

CONTACT_STEP = 0.5
"""The largest integration step on a contact, in units of 1/ω_c = √(J/K_c) (a twelfth of
the contact's period): small enough that the push F cannot dip below 0 and back inside a
step unseen (F moves on the contact's time scale, or slower: the overdamped contact's fast
mode decays monotonically), and inside DOP853's stability region for the overdamped
contact's fast mode, −ω_c (ζ_c + √(ζ_c² − 1)) (h |λ| ≤ 2.9 up to ζ_c = 3)."""

SIDE_NAMES = {1: "high", -1: "low"}
"""The names of the sides in the truth dict: +1 the upper stop (l θ = +h_hi), −1 the lower."""


# --------------------------------------------------------------------------------------
# The device and the loop
# --------------------------------------------------------------------------------------


@dataclasses.dataclass
class ContactDevice:
    """Physical values (SI) of a loop with compliant stops. `h_hi`, `h_lo` [m]: the
    clearances to the upper and lower stops' surfaces (∞: no stop on that side); `K_c`
    [N·m/rad] and `C_c` [N·m·s/rad]: the contacts' stiffness and damping (both stops);
    `test_gain` g_w the test winding's signed gain. The rest as `step_truth.Device`."""

    m: float = step_truth.Device.m
    l: float = step_truth.Device.l
    J: float = step_truth.Device.J
    mu: float = step_truth.Device.mu
    c: float = step_truth.Device.c
    k_dp: float = step_truth.Device.k_dp
    k_y: float = step_truth.Device.k_y
    k_dm: float = step_truth.Device.k_dm
    T_dm: float = 0.0
    T_f: float = 0.0
    test_gain: float = 1.0
    h_hi: float = float("inf")
    h_lo: float = float("inf")
    K_c: float = 0.0
    C_c: float = 0.0

    @property
    def gain(self) -> float:
        """k_dp k_y l [V/rad]: the pickoff's output per angle."""
        return self.k_dp * self.k_y * self.l

    @property
    def k_loop(self) -> float:
        """c + k_dm k_dp k_y l [N·m/rad]: the loop's static stiffness."""
        return self.c + self.k_dm * self.gain

    @property
    def k_test(self) -> float:
        """The settled output per test volt, k_dm k_dp k_y l / k_loop (times g_w)."""
        return self.k_dm * self.gain / self.k_loop


def contact_parameters(device: ContactDevice, kappa: float, zeta_c: float):
    """(K_c [N·m/rad], C_c [N·m·s/rad]) of a contact κ times the loop's static stiffness
    with damping ratio ζ_c: K_c = κ k_loop, C_c = 2 ζ_c √(K_c J)."""
    stiffness = kappa * device.k_loop
    return stiffness, 2.0 * zeta_c * np.sqrt(stiffness * device.J)


class _Loop:
    """The state y = (θ, θ', M_dm, U_f) (the last two used only when T_dm, T_f > 0) and
    the three modes: 0 free, +1 pushed by the upper contact, −1 by the lower one."""

    def __init__(self, d: ContactDevice, rec: step_truth.Record, step_scale=1.0):
        self.d, self.rec = d, rec
        self.theta_stop = {1: d.h_hi / d.l, -1: d.h_lo / d.l}
        self.sides = [s for s in (1, -1) if np.isfinite(self.theta_stop[s])]
        if self.sides and not d.K_c > 0:
            raise ValueError("a device with a stop needs a contact stiffness K_c > 0")
        if d.C_c < 0:
            raise ValueError("the contact damping C_c must be ≥ 0")
        if d.h_hi <= 0 or d.h_lo <= 0:
            raise ValueError("the clearances h_hi, h_lo must be > 0")
        loop_time = np.sqrt(d.J / d.k_loop)
        self.free_step = FREE_STEP * loop_time * step_scale
        contact_time = np.sqrt(d.J / d.K_c) if d.K_c > 0 else loop_time
        self.contact_step = min(self.free_step, CONTACT_STEP * contact_time * step_scale)
        # The absolute tolerances (× rtol): 1e-3 of a typical stop angle (h ≈ 1.9e-6 m over
        # l = 4.28e-3 m: 4.4e-4 rad), of that angle's rate at the loop's time scale, of
        # the torquer's moment at 1 V and of 1 V.
        scale_theta = 1e-3 * 4.4e-4
        self.atol_scale = np.array([scale_theta, scale_theta / loop_time, 1e-3 * d.k_dm, 1e-3])

    # --- the contact ------------------------------------------------------------------
    def penetration(self, y, side):
        """(δ [rad], δ' [rad/s]) into the contact of the given side."""
        if side > 0:
            return y[0] - self.theta_stop[1], y[1]
        return -self.theta_stop[-1] - y[0], -y[1]

    def push(self, y, side):
        """F = K_c δ + C_c δ' [N·m] of the given side (the contact pushes where F > 0 and
        δ > 0)."""
        delta, rate = self.penetration(y, side)
        return self.d.K_c * delta + self.d.C_c * rate

    def gate(self, y, side):
        """g = min(K_c δ, F) [N·m]: > 0 exactly where the contact of that side pushes."""
        delta, rate = self.penetration(y, side)
        spring = self.d.K_c * delta
        return min(spring, spring + self.d.C_c * rate)

    def contact_moment(self, y, side):
        """M_contact [N·m] of the given side's law at the state y: −side max(0, F) where
        δ > 0, else 0."""
        delta, _ = self.penetration(y, side)
        if delta <= 0:
            return 0.0
        return -side * max(0.0, self.push(y, side))

    def mode_of(self, y):
        """The mode the law puts the state in (0 where no contact pushes)."""
        for side in self.sides:
            if self.gate(y, side) > 0:
                return side
        return 0

    # --- the loop ---------------------------------------------------------------------
    def moment(self, t):
        return self.rec.moment + self.rec.moment_rate * t

    def torquer(self, y, u):
        d = self.d
        if d.T_dm > 0:
            return y[2]
        return d.k_dm * (d.test_gain * u - d.gain * y[0])

    def rhs(self, t, y, u, mode):
        d = self.d
        dy = np.zeros(4)
        dy[0] = y[1]
        net = self.torquer(y, u) + self.moment(t) - d.mu * y[1] - d.c * y[0]
        if mode != 0:
            net -= mode * self.push(y, mode)
        dy[1] = net / d.J
        if d.T_dm > 0:
            dy[2] = (d.k_dm * (d.test_gain * u - d.gain * y[0]) - y[2]) / d.T_dm
        if d.T_f > 0:
            dy[3] = (d.gain * y[0] - y[3]) / d.T_f
        return dy

    def output(self, y):
        return y[3] if self.d.T_f > 0 else self.d.gain * y[0]

    def rest(self, u, t, side=None):
        """The state at rest under the test voltage u and the moment at t: the free
        equilibrium k_loop θ = k_dm g_w u + M, or, where that lies beyond a stop's surface,
        the equilibrium pressed into it, (k_loop + K_c) θ = k_dm g_w u + M ± K_c h/l.
        `side` (±1) asks for the pressed equilibrium on that stop (ValueError if u does not
        press the pendulum into it)."""
        d = self.d
        drive = d.k_dm * d.test_gain * u + self.moment(t)
        theta = drive / d.k_loop
        pressed = 0
        for s in self.sides:
            if s * theta > self.theta_stop[s]:
                pressed = s
        if side is not None and pressed != side:
            raise ValueError(
                f"the holding level {u} V does not press the pendulum into the "
                f"{SIDE_NAMES[side]} stop"
            )
        if pressed:
            theta = (drive + d.K_c * pressed * self.theta_stop[pressed]) / (d.k_loop + d.K_c)
        y = np.zeros(4)
        y[0] = theta
        y[2] = d.k_dm * (d.test_gain * u - d.gain * theta)
        y[3] = d.gain * theta
        return y

    def events(self, mode):
        """(functions, kinds) of the events of a mode: the gates' crossings (terminal: into
        a contact upward from the free mode, out of it downward), and in the free mode the
        turning points θ' = 0 (non-terminal: the check for a graze inside a step)."""
        functions, kinds = [], []
        if mode == 0:
            for side in self.sides:

                def enter(t, y, side=side):
                    return self.gate(y, side)

                enter.terminal, enter.direction = True, 1
                functions.append(enter)
                kinds.append(("enter", side))
            if self.sides:

                def turn(t, y):
                    return y[1]

                turn.terminal, turn.direction = False, 0
                functions.append(turn)
                kinds.append(("turn", 0))
        else:

            def leave(t, y, side=mode):
                return self.gate(y, side)

            leave.terminal, leave.direction = True, -1
            functions.append(leave)
            kinds.append(("leave", mode))
        return functions, kinds


def _past_crossing(loop: _Loop, solution, t_event, side, into):
    """(t, state, crossed) just past an event of the gate g of `side` at t_event: the
    first of t_event, t_event + 1e-18 s × 2^k (k < 30, on the dense `solution` of the piece
    that found it) where g is strictly on the new mode's side (> 0 into a contact, < 0
    out of it), so that the next piece starts with g of the right sign and finds the next
    crossing. crossed False: no such time within 1e-9 s (a tangency, not a crossing: the
    mode is kept)."""
    sign = 1.0 if into else -1.0
    t = t_event
    for k in range(31):
        y = solution(t)
        if sign * loop.gate(y, side) > 0:
            return t, y, True
        t = t_event + 1e-18 * 2.0**k
    return t_event, solution(t_event), False


def _integrate(loop: _Loop, y, mode, t_start, t_end, u, pending, results, rtol, log):
    """Integrate from t_start to t_end under the constant test voltage u, from contact
    event to event; fill `results` (θ and the output) at the pending sample times. `log`
    collects the contact intervals and the solution pieces. Returns (state, mode) at
    t_end."""
    times, index = pending
    theta_out, out = results
    t = t_start
    atol = rtol * loop.atol_scale
    stalls = 0
    while t < t_end:
        functions, kinds = loop.events(mode)
        sol = solve_ivp(
            lambda tt, yy, u=u, mode=mode: loop.rhs(tt, yy, u, mode),
            (t, t_end),
            y,
            method="DOP853",
            rtol=rtol,
            atol=atol,
            events=functions or None,
            dense_output=True,
            max_step=loop.free_step if mode == 0 else loop.contact_step,
        )
        if sol.status < 0:
            raise RuntimeError(f"solve_ivp failed at t = {t}: {sol.message}")
        t_stop, new_mode = sol.t[-1], mode
        y_stop = sol.y[:, -1].copy()
        if sol.status == 1:
            fired = next(
                kind for k, kind in enumerate(kinds) if kind[0] != "turn" and sol.t_events[k].size
            )
            into = fired[0] == "enter"
            t_stop, y_stop, crossed = _past_crossing(loop, sol.sol, t_stop, fired[1], into)
            if crossed:
                new_mode = fired[1] if into else 0
        if mode == 0 and loop.sides:
            # A contact that a step stepped over: a turning point inside a stop's contact.
            k_turn = kinds.index(("turn", 0))
            for t_turn in sol.t_events[k_turn]:
                if t_turn >= t_stop:
                    break
                state = sol.sol(t_turn)
                side = next((s for s in loop.sides if loop.gate(state, s) > 0), 0)
                if side == 0:
                    continue
                # The first upward crossing of the gate between the step's start and the turn.
                start = sol.t[max(np.searchsorted(sol.t, t_turn, side="left") - 1, 0)]
                grid = np.linspace(start, t_turn, 65)
                gates = np.array([loop.gate(sol.sol(tt), side) for tt in grid])
                up = np.flatnonzero((gates[:-1] <= 0) & (gates[1:] > 0))
                if up.size == 0:
                    raise RuntimeError(f"a contact at t = {t_turn} with no entry found")
                root = brentq(
                    lambda tt, s=side, f=sol.sol: loop.gate(f(tt), s),
                    grid[up[0]],
                    grid[up[0] + 1],
                    xtol=1e-18,
                )
                t_stop, y_stop, _ = _past_crossing(loop, sol.sol, root, side, True)
                new_mode = side
                log["grazes"] += 1
                break
        take = (times >= t) & (times <= t_stop)
        if np.any(take):
            states = sol.sol(times[take])
            theta_out[index[take]] = states[0]
            out[index[take]] = [loop.output(s) for s in states.T]
            times, index = times[~take], index[~take]
        log["pieces"].append((t, t_stop, mode, sol.sol))
        if new_mode != mode:
            if new_mode != 0:
                log["contacts"].append([t_stop, None, new_mode])
            elif log["contacts"] and log["contacts"][-1][1] is None:
                log["contacts"][-1][1] = t_stop
        stalls = stalls + 1 if t_stop <= t else 0
        if stalls > 3:
            raise RuntimeError(f"the integration stalls at t = {t}")
        t, y, mode = t_stop, y_stop, new_mode
    return y, mode


def run(device: ContactDevice, rec: step_truth.Record, *, rtol=1e-10, step_scale=1.0):
    """The clean record and what happened in it: a dict with "t" [s], "u_test" [V] (the
    level in force at each sample), "theta" [rad], "clean" [V] (U_out, before the output
    sign, offset, noise and ADC), "contacts" (a list of [t_in, t_out, side] [s]: the
    intervals over which a contact pushed, t_out None if still pushing at the end; side
    +1 upper, −1 lower; from the start of the integration, so a start transient's contacts
    come before t0), "pieces" (a list of (t_a, t_b, mode, dense solution) of the
    integration: the solution on [t_a, t_b] in that mode), "grazes" (the number of
    contacts found at a turning point inside a step) and "loop" (the `_Loop`, whose
    `contact_moment(y, side)` and `gate(y, side)` evaluate the contact law). `rtol`: the
    integration's relative tolerance (the absolute ones scale with it); `step_scale`
    multiplies the largest steps (`FREE_STEP`, `CONTACT_STEP`): a convergence check halves
    both."""
    if rec.bandpass is not None or rec.accel_levels is not None or any(rec.vibration):
        raise ValueError("contact_truth models no band-pass sensor or input acceleration")
    t = rec.t0 + np.arange(rec.n) / rec.rate
    levels = np.asarray(rec.levels, dtype=float)
    changes = np.asarray(rec.change_times, dtype=float)
    if changes.size != levels.size - 1:
        raise ValueError("change_times needs one time fewer than levels")
    u_column = levels[np.searchsorted(changes, t, side="right")]
    loop = _Loop(device, rec, step_scale)
    if rec.start == "rest":
        t_begin, y = t[0], loop.rest(levels[0], t[0])
    elif isinstance(rec.start, str) and rec.start in step_truth.ON_STOP_STARTS:
        side = step_truth.ON_STOP_STARTS[rec.start]
        if side not in loop.sides:
            raise ValueError(f"start {rec.start!r} needs a stop on that side")
        t_begin = t[0]
        u_first = float(levels[np.searchsorted(changes, t_begin, side="right")])
        u_hold = u_first if rec.hold_level is None else float(rec.hold_level)
        y = loop.rest(u_hold, t_begin, side=side)
    elif isinstance(rec.start, str):
        raise ValueError(f"unknown start {rec.start!r}")
    else:
        t_begin = t[0] - float(rec.start)
        y = loop.rest(rec.start_level, t_begin)
    mode = loop.mode_of(y)
    theta = np.full(rec.n, np.nan)
    clean = np.full(rec.n, np.nan)
    log = {"contacts": [], "pieces": [], "grazes": 0}
    if mode != 0:
        log["contacts"].append([t_begin, None, mode])
    edges = np.concatenate([[t_begin], changes[(changes > t_begin) & (changes < t[-1])], [t[-1]]])
    level_of = levels[np.searchsorted(changes, edges[:-1], side="right")]
    pending = (t, np.arange(rec.n))
    for a, b, u in zip(edges[:-1], edges[1:], level_of, strict=True):
        y, mode = _integrate(loop, y, mode, a, b, u, pending, (theta, clean), rtol, log)
        done = pending[0] <= b
        pending = (pending[0][~done], pending[1][~done])
    if np.any(np.isnan(clean)):
        raise RuntimeError("samples left unfilled")
    return {
        "t": t,
        "u_test": u_column,
        "theta": theta,
        "clean": clean,
        "contacts": log["contacts"],
        "pieces": log["pieces"],
        "grazes": log["grazes"],
        "loop": loop,
    }


def simulate(device: ContactDevice, rec: step_truth.Record, *, rng, rtol=1e-10, step_scale=1.0):
    """(t [s], u_test column [V], u_out column [V]) of one record, as `step_truth.simulate`
    returns it: output_sign × U_out + output_offset, plus white noise of σ `rec.noise`
    (rng.normal, drawn first), plus Gauss–Markov noise `rec.gm` (drawn next), quantised
    by `rec.adc_step` (0: none)."""
    result = run(device, rec, rtol=rtol, step_scale=step_scale)
    return result["t"], result["u_test"], step_truth.recorded(rec, result["clean"], rng)


# --------------------------------------------------------------------------------------
# The drawn records
# --------------------------------------------------------------------------------------


def _base_device(d: dict) -> ContactDevice:
    return ContactDevice(
        J=d["J"],
        mu=d["mu"],
        c=d["c"],
        k_dm=d["k_dm"],
        k_dp=d["k_dp"],
        k_y=d["k_y"],
        test_gain=d["test_gain"],
    )


def contact_device(truth: dict) -> ContactDevice:
    """The physical device of a drawn record (`draw_truth`): the loop's values, the
    clearances h_hi, h_lo [m] (∞ where the truth has no stop, None), K_c [N·m/rad] and
    C_c [N·m·s/rad]. `dataclasses.asdict` gives them as a dict."""
    device = _base_device(truth["device"])
    device.h_hi = float("inf") if truth["h_hi_m"] is None else float(truth["h_hi_m"])
    device.h_lo = float("inf") if truth["h_lo_m"] is None else float(truth["h_lo_m"])
    device.K_c, device.C_c = contact_parameters(device, truth["kappa"], truth["zeta_c"])
    return device


def contact_record(truth: dict) -> step_truth.Record:
    """The `step_truth.Record` of a drawn record (its sequence, conventions and start)."""
    hold = truth["start_level_V"] if truth.get("start_against_stop") else None
    return step_truth.record_from_truth(truth, hold_level=hold)


def _peaks(theta, length):
    """(peak deflection on the upper side, on the lower side) [m] of sampled angles."""
    return float(max(0.0, np.max(theta)) * length), float(max(0.0, -np.min(theta)) * length)


def draw_truth(rng: np.random.Generator, effect: str, *, rtol=1e-10) -> dict:
    """One record's world (JSON-able): the device, the small-step sequence and the
    conventions drawn as `step_truth.draw_truth` draws them (the same draws in the same
    order, so the same rng state gives the same world), then the contact.

    The contact's draws, in this order whatever the class: κ (`KAPPA`), ζ_c (`ZETA_C`),
    the peak-over-clearance factor (`PEAK_OVER_CLEARANCE`), the near side (±1, even
    odds), h_far/h_near (`FAR_OVER_NEAR`), the start-against-stop flag
    (`START_AGAINST_STOP_P`), its side (±1, even odds) and `HOLD_OVER_REACH`. Then the
    free response of the record (no stops, its drawn start) gives the peak deflections on
    both sides, and the clearances:

    - "stop_compliant": h_hi = h_lo = (the larger of the two peaks) / factor;
    - "stop_one_sided": a stop on the near side only, h = that side's peak / factor (the
      near side replaced by the other one if the sequence hardly drives the pendulum
      there, `USABLE_SIDE`);
    - "stop_uneven": h_near as the one-sided one's, h_far = ratio × h_near.

    Keys added to step_truth's: "kappa" (K_c/k_loop), "zeta_c", "K_c_Nm" [N·m/rad],
    "C_c_Nms" [N·m·s/rad], "k_loop_Nm" [N·m/rad], "peak_over_clearance", "near_side"
    (±1), "far_over_near" (None but for "stop_uneven"), "h_hi_m", "h_lo_m" [m] (None: no
    stop), "stop_hi_V", "stop_lo_V" [V] (k_dp k_y h: the output U_out, before the sign and
    offset, at the stop's surface; None: no stop), "free_peak_hi_m", "free_peak_lo_m"
    [m] (the free response's peaks that set them), "start_against_stop" (bool),
    "hold_over_reach", "drawn_start" and "drawn_start_level_V" (the conventions' start,
    that the clearances were set from; "start" and "start_level_V" are replaced by
    "on_stop_high"/"on_stop_low" and U_hold [V] when the record starts against a stop),
    and from the clean contact record itself (`rtol`): "sides_reached" (the sides, "high"
    / "low", whose contact pushed at some time in the record, from its first sample on),
    "contact_peak_hi_m", "contact_peak_lo_m" [m] (the sampled peaks with the contacts),
    "clip_ratio" (the contact peak over the free peak on the near side), "contacts_s"
    (the contact intervals [t_in, t_out, "high"/"low"] [s] from the first sample, clipped
    to the record) and "contact_fraction" (the fraction of the record spent in contact).
    """
    if effect not in CONTACT_CLASSES:
        raise ValueError(f"effect must be one of {CONTACT_CLASSES}, not {effect!r}")
    truth = step_truth.draw_truth(rng, "none")
    truth["effect"] = effect
    kappa = step_truth._log_uniform(rng, *KAPPA)
    zeta_c = step_truth._log_uniform(rng, *ZETA_C)
    factor = float(rng.uniform(*PEAK_OVER_CLEARANCE))
    near = int(rng.choice([-1, 1]))
    ratio = float(rng.uniform(*FAR_OVER_NEAR))
    against = bool(rng.uniform() < START_AGAINST_STOP_P)
    against_side = int(rng.choice([-1, 1]))
    hold_over_reach = float(rng.uniform(*HOLD_OVER_REACH))

    device = _base_device(truth["device"])
    record = contact_record({**truth, "start_against_stop": False})
    free = run(device, record, rtol=rtol)
    peak = dict(zip((1, -1), _peaks(free["theta"], device.l), strict=True))
    full = device.k_test * truth["u_max_V"] / (device.k_dp * device.k_y)  # m
    if peak[near] < USABLE_SIDE * full:
        near = -near
    if peak[near] < USABLE_SIDE * full:
        raise RuntimeError("the sequence drives the pendulum towards neither side")
    clearance = {1: None, -1: None}
    if effect == "stop_compliant":
        near = 1 if peak[1] >= peak[-1] else -1
        clearance[1] = clearance[-1] = peak[near] / factor
    elif effect == "stop_one_sided":
        clearance[near] = peak[near] / factor
    else:
        clearance[near] = peak[near] / factor
        clearance[-near] = ratio * clearance[near]
    stiffness, damping = contact_parameters(device, kappa, zeta_c)
    truth.update(
        {
            "kappa": kappa,
            "zeta_c": zeta_c,
            "K_c_Nm": float(stiffness),
            "C_c_Nms": float(damping),
            "k_loop_Nm": float(device.k_loop),
            "peak_over_clearance": factor,
            "near_side": near,
            "far_over_near": ratio if effect == "stop_uneven" else None,
            "h_hi_m": clearance[1],
            "h_lo_m": clearance[-1],
            "stop_hi_V": None if clearance[1] is None else clearance[1] * device.k_dp * device.k_y,
            "stop_lo_V": None
            if clearance[-1] is None
            else clearance[-1] * device.k_dp * device.k_y,
            "free_peak_hi_m": peak[1],
            "free_peak_lo_m": peak[-1],
            "start_against_stop": against,
            "hold_over_reach": hold_over_reach,
            "drawn_start": truth["start"],
            "drawn_start_level_V": truth["start_level_V"],
        }
    )
    if against:
        side = near if effect == "stop_one_sided" else against_side
        # The level whose settled free deflection (with the moment) reaches the surface.
        stop_V = clearance[side] * device.k_dp * device.k_y
        offset_V = device.gain * truth["moment_Nm"] / device.k_loop
        reach = (side * stop_V - offset_V) / (device.k_test * device.test_gain)
        truth["start"] = "on_stop_high" if side > 0 else "on_stop_low"
        truth["start_level_V"] = float(hold_over_reach * reach)
    result = run(contact_device(truth), contact_record(truth), rtol=rtol)
    t = result["t"]
    hi, lo = _peaks(result["theta"], device.l)
    truth["contact_peak_hi_m"], truth["contact_peak_lo_m"] = hi, lo
    truth["clip_ratio"] = (hi if near > 0 else lo) / peak[near]
    intervals = []
    for t_in, t_out, side in result["contacts"]:
        t_out = t[-1] if t_out is None else t_out
        if t_out >= t[0]:
            intervals.append([float(max(t_in, t[0]) - t[0]), float(t_out - t[0]), SIDE_NAMES[side]])
    truth["contacts_s"] = intervals
    truth["sides_reached"] = [
        name for name in ("high", "low") if any(c[2] == name for c in intervals)
    ]
    truth["contact_fraction"] = float(sum(c[1] - c[0] for c in intervals) / (t[-1] - t[0]))
    return truth


def make(truth: dict, rng: np.random.Generator, *, rtol=1e-10):
    """Simulate one drawn world (`draw_truth`'s): (t [s] from 0, u_test column [V], u_out
    column [V], noise component [V]), as `step_truth.make` returns them; the noise is the
    recorded output minus the clean one (output sign and offset included), its ADC
    rounding included."""
    record = contact_record(truth)
    result = run(contact_device(truth), record, rtol=rtol)
    t, clean = result["t"], result["clean"]
    y = step_truth.recorded(record, clean, rng)
    return t - t[0], result["u_test"], y, y - (record.output_sign * clean + record.output_offset)
