"""An independent truth simulator of closed-loop step records with effects outside the plain
loop, for testing a diagnosis that looks for unmodelled effects (SciPy, not JAX).

Written from the loop equations of docs/models.md §1, as `step_truth.py` is, with none of
the library's code; it reuses `step_truth`'s world (the drawn device, the small-step test
sequence, the recorder conventions, `Record`, the output noise and ADC handling) and adds
one effect per record, each from its physics. Two of them are terms a diagnosis's library
may hold (`IN_LIBRARY`), two are deliberately not (`OUT_OF_LIBRARY`).

Loop (SI units; θ the pendulum's angle, M(t) = M_0 + Ṁ t the external moment, G = k_dp k_y l
the pickoff-and-amplifier gain [V/rad], C = c + k_dm G the loop's static stiffness):

    J θ'' + μ θ' + c θ = φ(M_dm) + M(t) − M_fric
    T_dm M_dm' = k_dm (g_w U_test(t) − U_amp) − M_dm      (M_dm algebraic when T_dm = 0)
    U_amp = G · r_p,   T_f U_f' = U_amp − U_f,   U_out = U_f   (U_out = U_amp when T_f = 0)

with r_p the angle the pickoff reports (r_p = θ in the plain loop), φ(M) = M and
M_fric = 0 in the plain loop, whose records are then step_truth's. The drawn worlds have
T_dm = T_f = 0 (as step_truth's `draw_truth`); both lags are supported.

Effects (one per record; `CLASSES`):

- "torquer_asymmetry": the torquer's scale factor differs for the two directions of its
  current, φ(M_dm) = M_dm (1 + a sign M_dm), sign 0 = 0 (φ is continuous, with a kink at
  0). Each piece is integrated with the sign σ = ±1 held fixed, φ = M_dm (1 + a σ), and
  ended by the event M_dm = 0 crossing away from σ (direction −σ), where σ flips.
  Draw: |a| log-uniform in `ASYMMETRY`, random sign (a > 0: the positive direction
  stronger); physical: the two torquer gains k_dm (1 ± a).
- "coulomb_friction": dry friction at the pivot. Moving: M_fric = F sign θ', integrated
  with the direction v = ±1 held fixed and ended by the event θ' = 0 (direction −v).
  There, with N = φ(M_dm) + M(t) − μθ' − cθ the net other moment (θ' = 0): |N| < F →
  stuck: θ' = 0 and θ frozen (θ'' = 0) while the rest of the state evolves, ended by the
  events N = +F (upward) or N = −F (downward), where it moves off with v = sign N; |N| ≥ F
  → it reverses at once, v = sign N. At each test-voltage change a stuck pendulum whose
  N now exceeds F moves off at once. Rest start: stuck at the angle where N = −f F,
  θ = θ* + f F/C (θ* the frictionless rest), f = `stick_fraction` uniform in (−1, 1): a
  rest anywhere in the friction's dead band. Draw: F/(C θ_full) log-uniform in
  `FRICTION_RATIO`, θ_full = k_dm |g_w| U_max / C the settled angle under the full level.
- "pickoff_hysteresis": the pickoff reads p, the play (backlash) operator of half-width b
  on θ (on θ + θ₂ were a second mode present): p is a state; frozen (p' = 0) while
  |θ − p| < b, tracking (p' = θ', p = θ − s b) while θ moves in the direction s with
  θ − p = s b. Events: frozen → tracking s when θ − p − s b crosses 0 in the direction s
  (p reset to θ − s b exactly); tracking s → frozen when θ' (the reading's rate) crosses
  0 in the direction −s. U_amp = G p. Rest start: at rest after an approach from the side
  s = `approach_sign` (±1, even odds), tracking s:
  C p = k_dm g_w U + M − c s b, θ = p + s b. (The loop's high gain makes the static effect
  small: a settled level depends on the direction of approach by only 2 G c b / C, the
  mechanical spring c pulling θ across the dead band; the transients carry most of it.)
  Draw: b/θ_full log-uniform in `PLAY_RATIO`.
- "second_mode": a second mechanical mode seen by the pickoff, r_p = θ + θ₂,
      θ₂'' + 2 ζ₂ ω₂ θ₂' + ω₂² θ₂ = −κ θ''
  (θ'' the pendulum's angular acceleration from its own equation; the mode does not act
  back on θ except through the loop). Rest: θ₂ = θ₂' = 0. Draw: f₂/f_n log-uniform in
  `MODE_RATIO` (f_n = √(C/J)/2π the loop's natural frequency), ζ₂ uniform in `MODE_ZETA`,
  κ log-uniform in `MODE_COUPLING`. No events (the system is linear and smooth). Its
  size on the record goes as κ (f_n/f₂)²: with these ranges most draws fall below the
  noise (`visible` false in 32 of 40 draws, seeds 1000–1039; none of the 14 with
  f₂/f_n > 6.5), kept as drawn.

Integration: SciPy's `solve_ivp` (DOP853), rtol 1e-10 (atol 1e-4 × rtol on every state:
1e-14; `run`'s `rtol`), steps ≤ 0.05 / max(ω_n, ω₂) (`STEP_SCALE`, × `run`'s
`step_scale`; at rtol 1e-10 these bounds, not the error control, set most steps),
broken at every test-voltage change (the DAC's own, off-grid times) and at
every event above (all terminal: each mode of the hybrid system is a smooth ODE, so its
discontinuities are stepped on exactly, never across). Zero crossings are located on the
dense output (brentq, 4 ulp). Each switching threshold is offset a hair (`HAIR`, 1e-12 of
the quantity's scale) to the far side, a Schmitt trigger: a state resting exactly on a
threshold (M_dm ≡ 0 at rest under 0 V with no moment; θ' = 0 at rest) or just put on it
by a switch does not re-trigger it. After each piece the mode is checked against the
state (σ M_dm ≥ 0, v θ' ≥ 0, |θ − p| ≤ b, each to a hair): a missed crossing raises
RuntimeError rather than passing silently. The state vector is (θ, θ', M_dm, U_f, p, θ₂,
θ₂'), unused entries held at 0. With every magnitude 0 no event is set and the steps are
step_truth's: the record is step_truth's to rounding (tests/test_discovery_truth.py).

Start states (`step_truth.Record.start`): "rest" (at rest under the first level, long
before t0; the rest of each effect as above) or a number (the first level switched on that
long before t0 from rest under `start_level`). No stops (h_max = ∞), no acceleration input,
vibration or band-pass sensor: the drawn worlds have none.

The drawn records (`draw`, `make`): the world exactly as `step_truth.draw_truth(rng,
"none")` draws it (the same draws in the same order: device, sequence, conventions), then
the effect's magnitudes, then its rest details (`stick_fraction`, `approach_sign`). The
output as step_truth's: output_sign × U_out + output_offset + white noise, quantised by
the ADC (`step_truth.recorded`, the same noise draws as `step_truth.make` for the same
rng). The truth dict records each magnitude in physical terms and as a dimensionless
ratio, and the effect's size on the record: `effect_rms_V`, the RMS over the record of
the noise-free record minus the same record simulated without the effect, its ratio to the
white noise σ (`effect_over_noise`) and `visible` (≥ `VISIBLE_OVER_NOISE`; draws below it
are kept and marked, not redrawn).

Public: `CLASSES` (`IN_LIBRARY`, `OUT_OF_LIBRARY`); `draw(rng, effect)` the JSON-able
world, `make(truth, rng)` its record (t, u_test, u_out); `clean_record` (noise-free, with
or without the effect) and `effect_size`; `world(truth)` → (`step_truth.Device`,
`step_truth.Record`, `Effects`) and `run` / `simulate` for hand-built worlds.

Everything is float64 NumPy/SciPy.
"""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
from scipy.integrate import solve_ivp

sys.path.insert(0, str(Path(__file__).resolve().parent))
import step_truth  # noqa: E402

IN_LIBRARY = ("torquer_asymmetry", "coulomb_friction")
"""Effects a diagnosis's term library is meant to hold."""

OUT_OF_LIBRARY = ("pickoff_hysteresis", "second_mode")
"""Effects the term library deliberately lacks."""
CLASSES = ("none",) + IN_LIBRARY + OUT_OF_LIBRARY

ASYMMETRY = (0.01, 0.05)
"""|a|, the torquer's relative scale-factor difference between its two directions,
log-uniform (random sign)."""

FRICTION_RATIO = (0.002, 0.02)
"""F / (C θ_full), the dry friction moment over the loop's moment at the full level's
deflection, log-uniform."""

PLAY_RATIO = (0.005, 0.03)
"""b / θ_full, the pickoff's play half-width over the full level's deflection,
log-uniform."""

MODE_RATIO = (3.0, 5.0)
"""f₂ / f_n, the second mode's natural frequency over the loop's, log-uniform."""

MODE_ZETA = (0.02, 0.1)
"""ζ₂, the second mode's damping ratio, uniform."""

MODE_COUPLING = (0.02, 0.1)
"""κ, the second mode's coupling to the pendulum's angular acceleration, log-uniform."""

VISIBLE_OVER_NOISE = 3.0
"""`visible`: the effect's RMS on the record is at least this × the white noise σ."""

MEASURED = ("effect_rms_V", "effect_over_noise", "visible")
"""The truth dict's keys that `draw` measures by simulating (the rest is the world)."""

STEP_SCALE = 0.05
"""The largest step, in units of 1/max(ω_n, ω₂) (step_truth's 0.05 √(J/C))."""

HAIR = 1e-12
"""Each switching threshold lies this far (relative to the quantity's scale: the torquer's
moment k_dm max|U| + |M_0|, the rate and angle that moment gives through the loop) beyond
its nominal value on the far side, a Schmitt trigger: a state that rests exactly on a
threshold (M_dm ≡ 0 at rest under 0 V, θ' ≡ 0 at rest) or has just been put on it by a
switch cannot re-trigger it; the switch comes that hair late (an error ≲ 1e-12 of the
record)."""

_MODE_CHECK = 1e-9
"""The hair by which a state may lie on the wrong side of its mode after a piece (relative
to the scale of the quantity): beyond it a crossing was missed (RuntimeError)."""

TH, OM, MDM, UF, P, Q, QD = range(7)


@dataclasses.dataclass
class Effects:
    """The effects' physical magnitudes (all 0: the plain loop). `asymmetry` a [1];
    `friction` F [N·m] and `stick_fraction` f of the rest state (see the module docstring);
    `play` b [rad] and `approach_sign` s of the rest state; `mode_omega` ω₂ [rad/s],
    `mode_zeta` ζ₂, `mode_coupling` κ."""

    asymmetry: float = 0.0
    friction: float = 0.0
    stick_fraction: float = 0.0
    play: float = 0.0
    approach_sign: float = 1.0
    mode_omega: float = 0.0
    mode_zeta: float = 0.0
    mode_coupling: float = 0.0


@dataclasses.dataclass
class _Mode:
    """The discrete state of the hybrid system: `sgn` σ of the torquer's moment (±1),
    `stuck` (friction), `vdir` v the direction of motion (friction), `play` 0 frozen or ±1
    tracking."""

    sgn: float = 1.0
    stuck: bool = False
    vdir: float = 1.0
    play: int = 0


def _sign(x):
    return 1.0 if x > 0 else (-1.0 if x < 0 else 0.0)


class _Plant:
    def __init__(self, d: step_truth.Device, rec: step_truth.Record, e: Effects, step_scale=1.0):
        if np.isfinite(d.h_max) or d.pickoff_p2 or d.pickoff_p3:
            raise ValueError("discovery_truth: no stops or pickoff nonlinearity")
        if rec.bandpass is not None or rec.accel_levels is not None or rec.vibration[0]:
            raise ValueError("discovery_truth: no band-pass sensor, acceleration or vibration")
        if e.friction < 0 or e.play < 0 or abs(e.stick_fraction) >= 1:
            raise ValueError("friction and play must be ≥ 0, |stick_fraction| < 1")
        self.d, self.rec, self.e = d, rec, e
        self.gain = d.k_dp * d.k_y * d.l
        self.stiffness = d.c + d.k_dm * self.gain
        omega = max(np.sqrt(self.stiffness / d.J), e.mode_omega)
        self.max_step = step_scale * STEP_SCALE / omega
        self.mode_on = e.mode_omega > 0
        levels = np.abs(np.asarray(rec.levels, dtype=float))
        self.moment_scale = d.k_dm * max(float(levels.max()), 1e-3) + abs(rec.moment)
        self.hair_moment = HAIR * self.moment_scale
        self.hair_rate = HAIR * self.moment_scale / np.sqrt(d.J * self.stiffness)
        self.hair_angle = HAIR * self.moment_scale / self.stiffness

    # The loop's quantities (y a state, or states (7, k) for `output`).
    def pick(self, y):
        """The angle the pickoff reports: p (play), else θ + θ₂."""
        return y[P] if self.e.play > 0 else y[TH] + y[Q]

    def reading(self, y):
        return y[TH] + y[Q]

    def amp(self, y):
        return self.gain * self.pick(y)

    def output(self, y):
        return y[UF] if self.d.T_f > 0 else self.amp(y)

    def torquer(self, y, u):
        d = self.d
        if d.T_dm > 0:
            return y[MDM]
        return d.k_dm * (d.test_gain * u - self.amp(y))

    def moment(self, t):
        return self.rec.moment + self.rec.moment_rate * t

    def net(self, t, y, u, mode):
        """N = φ(M_dm) + M(t) − μ θ' − c θ: every moment but the friction's."""
        d = self.d
        m = self.torquer(y, u)
        if self.e.asymmetry:
            m = m * (1 + self.e.asymmetry * mode.sgn)
        return m + self.moment(t) - d.mu * y[OM] - d.c * y[TH]

    def rhs(self, t, y, u, mode):
        d, e = self.d, self.e
        dy = np.zeros_like(y)
        if mode.stuck:
            acc = 0.0
        else:
            dy[TH] = y[OM]
            acc = (self.net(t, y, u, mode) - e.friction * mode.vdir) / d.J
            dy[OM] = acc
        if d.T_dm > 0:
            dy[MDM] = (d.k_dm * (d.test_gain * u - self.amp(y)) - y[MDM]) / d.T_dm
        if d.T_f > 0:
            dy[UF] = (self.amp(y) - y[UF]) / d.T_f
        if self.mode_on:
            w, z = e.mode_omega, e.mode_zeta
            dy[Q] = y[QD]
            dy[QD] = -e.mode_coupling * acc - 2 * z * w * y[QD] - w * w * y[Q]
        if mode.play != 0:
            dy[P] = dy[TH] + dy[Q]
        return dy

    # Rest, modes, events.
    def rest(self, u, t):
        """(state, mode) at rest under the test voltage u at t (see the module docstring:
        friction stuck at θ* + f F/C, the play approached from the side s, θ₂ = 0)."""
        d, e = self.d, self.e
        s = float(e.approach_sign) if e.play > 0 else 0.0
        b = e.play
        hold = e.stick_fraction * e.friction
        moment = self.moment(t)
        for sigma in (1.0, -1.0):
            k = d.k_dm * (1 + e.asymmetry * sigma)
            theta = (k * (d.test_gain * u + self.gain * s * b) + moment + hold) / (
                d.c + k * self.gain
            )
            p = theta - s * b
            m = d.k_dm * (d.test_gain * u - self.gain * p)
            if not e.asymmetry or sigma * m >= 0:
                break
        y = np.zeros(7)
        y[TH] = theta
        y[P] = p
        y[MDM] = m
        y[UF] = self.gain * p
        mode = _Mode(
            sgn=_sign(m) or 1.0,
            stuck=e.friction > 0,
            vdir=1.0,
            play=int(s) if b > 0 else 0,
        )
        return y, mode

    def settle(self, t, y, u, mode):
        """The mode at the start of a piece (a new test voltage): σ from M_dm's sign (its
        slope's at 0), a stuck pendulum released if |N| > F."""
        mode = dataclasses.replace(mode)
        e = self.e
        if e.asymmetry:
            m = self.torquer(y, u)
            if m == 0:
                h = 1e-3 * self.max_step
                m = self.torquer(y + h * self.rhs(t, y, u, mode), u)
            mode.sgn = _sign(m) or 1.0
        if e.friction > 0 and mode.stuck:
            n = self.net(t, y, u, mode)
            if abs(n) > e.friction:
                mode.stuck, mode.vdir = False, _sign(n)
        return mode

    def events(self, u, mode):
        """[(event function, key)] of the mode's possible ends."""
        e = self.e
        out = []

        def add(fun, direction, key):
            fun.terminal, fun.direction = True, direction
            out.append((fun, key))

        if e.asymmetry:
            hm = mode.sgn * self.hair_moment
            add(lambda t, y: self.torquer(y, u) + hm, -mode.sgn, ("torquer", 0))
        if e.friction > 0:
            f = e.friction + self.hair_moment
            if mode.stuck:
                add(lambda t, y: self.net(t, y, u, mode) - f, 1, ("release", 1))
                add(lambda t, y: self.net(t, y, u, mode) + f, -1, ("release", -1))
            else:
                hv = mode.vdir * self.hair_rate
                add(lambda t, y: y[OM] + hv, -mode.vdir, ("halt", 0))
        if e.play > 0:
            b = e.play + self.hair_angle
            if mode.play == 0:
                add(lambda t, y: self.reading(y) - y[P] - b, 1, ("grip", 1))
                add(lambda t, y: self.reading(y) - y[P] + b, -1, ("grip", -1))
            else:
                hv = mode.play * self.hair_rate
                add(lambda t, y: y[OM] + y[QD] + hv, -mode.play, ("slip", 0))
        return out

    def switch(self, t, y, u, mode, key):
        """(state, mode) after the event `key` at t."""
        y, mode = y.copy(), dataclasses.replace(mode)
        name, side = key
        if name == "torquer":
            mode.sgn = -mode.sgn
        elif name == "halt":
            y[OM] = 0.0
            n = self.net(t, y, u, mode)
            if abs(n) < self.e.friction:
                mode.stuck = True
            else:
                mode.vdir = _sign(n)
        elif name == "release":
            y[OM] = 0.0
            mode.stuck, mode.vdir = False, float(side)
        elif name == "grip":
            mode.play = side
            y[P] = self.reading(y) - side * self.e.play
        elif name == "slip":
            mode.play = 0
        return y, mode

    def check(self, t, y, u, mode):
        """Raise RuntimeError where the state lies beyond a hair on the wrong side of its
        mode (a crossing the event detection missed)."""
        e = self.e
        if e.asymmetry and mode.sgn * self.torquer(y, u) < -_MODE_CHECK * self.moment_scale:
            raise RuntimeError(f"t = {t:.9g}: the torquer's sign changed unseen")
        if e.friction > 0 and not mode.stuck:
            if mode.vdir * y[OM] < -_MODE_CHECK / HAIR * self.hair_rate:
                raise RuntimeError(f"t = {t:.9g}: the pendulum reversed unseen")
        slack = max(_MODE_CHECK * e.play, 10 * self.hair_angle)
        if e.play > 0 and abs(self.reading(y) - y[P]) > e.play + slack:
            raise RuntimeError(f"t = {t:.9g}: the play's edge was passed unseen")


def _integrate(plant: _Plant, y, mode, t_start, t_end, u, pending, out, rtol, log):
    """Integrate from t_start to t_end under the constant test voltage u, from event to
    event; fill `out` at the pending times (indices into out). Returns (state, mode,
    pending left)."""
    times, index = pending
    t = t_start
    mode = plant.settle(t, y, u, mode)
    stalled = 0
    while t < t_end:
        events = plant.events(u, mode)
        frozen = dataclasses.replace(mode)
        sol = solve_ivp(
            lambda tt, yy, m=frozen: plant.rhs(tt, yy, u, m),
            (t, t_end),
            y,
            method="DOP853",
            rtol=rtol,
            atol=1e-4 * rtol,
            events=[f for f, _ in events] or None,
            dense_output=True,
            max_step=plant.max_step,
        )
        if sol.status < 0:
            raise RuntimeError(sol.message)
        t_stop = float(sol.t[-1])
        take = times <= t_stop
        if np.any(take):
            if t_stop > t:
                out[index[take]] = plant.output(sol.sol(times[take]))
            else:
                out[index[take]] = plant.output(y)
            times, index = times[~take], index[~take]
        y = sol.y[:, -1].copy()
        if sol.status == 1:
            fired = next(i for i, te in enumerate(sol.t_events) if te.size)
            key = events[fired][1]
            y, mode = plant.switch(t_stop, y, u, mode, key)
            log.append((t_stop, key[0]))
            stalled = stalled + 1 if t_stop <= t else 0
            if stalled > 8:
                raise RuntimeError(f"t = {t:.9g}: events repeat without progress ({key})")
        plant.check(t_stop, y, u, mode)
        t = t_stop
    return y, mode, (times, index)


def run(
    device: step_truth.Device,
    rec: step_truth.Record,
    effects: Effects,
    *,
    rtol=1e-10,
    step_scale=1.0,
):
    """(t [s], u_test column [V], U_out [V] noise-free, before the recorder, events) of one
    record: `events` the list of (time [s], kind) of the hybrid system's switches.
    `step_scale` scales the largest step (`STEP_SCALE`; < 1 for a refinement check)."""
    plant = _Plant(device, rec, effects, step_scale)
    t = rec.t0 + np.arange(rec.n) / rec.rate
    levels = np.asarray(rec.levels, dtype=float)
    changes = np.asarray(rec.change_times, dtype=float)
    u_column = levels[np.searchsorted(changes, t, side="right")]
    if rec.start == "rest":
        t_begin = t[0]
        y, mode = plant.rest(levels[0], t_begin)
    elif isinstance(rec.start, str):
        raise ValueError(f"start {rec.start!r}: discovery_truth has no stops")
    else:
        t_begin = t[0] - float(rec.start)
        y, mode = plant.rest(rec.start_level, t_begin)
    clean = np.empty(rec.n)
    edges = np.concatenate([[t_begin], changes[(changes > t_begin) & (changes < t[-1])], [t[-1]]])
    level_of = levels[np.searchsorted(changes, edges[:-1], side="right")]
    pending = (t, np.arange(rec.n))
    log = []
    for a, b, u in zip(edges[:-1], edges[1:], level_of, strict=True):
        y, mode, pending = _integrate(plant, y, mode, a, b, u, pending, clean, rtol, log)
    return t, u_column, clean, log


def simulate(
    device: step_truth.Device,
    rec: step_truth.Record,
    effects: Effects,
    *,
    rng: np.random.Generator,
    rtol=1e-10,
):
    """(t [s], u_test column [V], u_out column [V]) as the recorder stores them
    (`step_truth.recorded`: sign, offset, white noise drawn from rng, ADC)."""
    t, u, clean, _ = run(device, rec, effects, rtol=rtol)
    return t, u, step_truth.recorded(rec, clean, rng)


# --------------------------------------------------------------------------------------
# The drawn worlds
# --------------------------------------------------------------------------------------


def _log_uniform(rng, low, high):
    return float(np.exp(rng.uniform(np.log(low), np.log(high))))


def device_of(truth: dict) -> step_truth.Device:
    """The truth's device (as step_truth.make builds it; T_dm, T_f from the dict, 0 if
    absent)."""
    d = truth["device"]
    device = step_truth.Device(
        J=d["J"],
        mu=d["mu"],
        c=d["c"],
        k_dm=d["k_dm"],
        k_dp=d["k_dp"],
        k_y=d["k_y"],
        T_dm=d.get("T_dm", 0.0),
        T_f=d.get("T_f", 0.0),
    )
    device.test_gain = d["test_gain"]
    return device


def record_of(truth: dict) -> step_truth.Record:
    """The truth's record (as step_truth.make builds it; `duration_s` from the dict,
    step_truth.DURATION if absent)."""
    return step_truth.record_from_truth(truth)


def effects_of(truth: dict) -> Effects:
    """The truth's effect as `Effects` (all 0 for "none")."""
    effect = truth["effect"]
    if effect == "none":
        return Effects()
    if effect == "torquer_asymmetry":
        return Effects(asymmetry=truth["asymmetry"])
    if effect == "coulomb_friction":
        return Effects(friction=truth["friction_Nm"], stick_fraction=truth["stick_fraction"])
    if effect == "pickoff_hysteresis":
        return Effects(play=truth["play_rad"], approach_sign=truth["approach_sign"])
    if effect == "second_mode":
        return Effects(
            mode_omega=2 * np.pi * truth["mode_Hz"],
            mode_zeta=truth["mode_zeta"],
            mode_coupling=truth["mode_coupling"],
        )
    raise ValueError(f"effect must be one of {CLASSES}, not {effect!r}")


def world(truth: dict):
    """(Device, Record, Effects) of a drawn truth."""
    return device_of(truth), record_of(truth), effects_of(truth)


def draw(rng: np.random.Generator, effect: str, *, duration_s=None, measure=True) -> dict:
    """One record's world (JSON-able): `step_truth.draw_truth(rng, "none")`'s (the same
    draws in the same order), then the effect's magnitudes and rest details (module
    docstring, and the ranges `ASYMMETRY` … `MODE_COUPLING`). Keys added to step_truth's:
    `effect`; `duration_s` (the record's length, step_truth.DURATION unless given; a
    shorter one cuts the sequence); `loop_stiffness_Nm` C, `natural_Hz` f_n,
    `theta_full_rad` θ_full, `full_output_V` G θ_full; per effect —

    - torquer_asymmetry: `asymmetry` a, `torquer_gain_positive_NmV` k_dm (1 + a),
      `torquer_gain_negative_NmV` k_dm (1 − a);
    - coulomb_friction: `friction_Nm` F, `friction_ratio` F/(C θ_full), `friction_output_V`
      G F/C (the largest output error of a stuck pendulum), `stick_fraction` f;
    - pickoff_hysteresis: `play_rad` b, `play_m` l b, `play_ratio` b/θ_full, `play_output_V`
      G b, `approach_sign` s;
    - second_mode: `mode_Hz` f₂, `mode_ratio` f₂/f_n, `mode_zeta` ζ₂, `mode_coupling` κ;

    and with `measure` (two noise-free simulations) `effect_rms_V`, `effect_over_noise`,
    `visible` (`effect_size`; for "none": 0, 0, None)."""
    if effect not in CLASSES:
        raise ValueError(f"effect must be one of {CLASSES}, not {effect!r}")
    truth = step_truth.draw_truth(rng, "none")
    truth["effect"] = effect
    truth["duration_s"] = float(step_truth.DURATION if duration_s is None else duration_s)
    d = truth["device"]
    device = device_of(truth)
    gain = device.k_dp * device.k_y * device.l
    stiffness = d["c"] + d["k_dm"] * gain
    theta_full = d["k_dm"] * abs(d["test_gain"]) * truth["u_max_V"] / stiffness
    natural = np.sqrt(stiffness / d["J"]) / (2 * np.pi)
    truth.update(
        loop_stiffness_Nm=float(stiffness),
        natural_Hz=float(natural),
        theta_full_rad=float(theta_full),
        full_output_V=float(gain * theta_full),
    )
    if effect == "torquer_asymmetry":
        a = _log_uniform(rng, *ASYMMETRY) * float(rng.choice([-1.0, 1.0]))
        truth.update(
            asymmetry=a,
            torquer_gain_positive_NmV=float(d["k_dm"] * (1 + a)),
            torquer_gain_negative_NmV=float(d["k_dm"] * (1 - a)),
        )
    elif effect == "coulomb_friction":
        ratio = _log_uniform(rng, *FRICTION_RATIO)
        friction = ratio * stiffness * theta_full
        truth.update(
            friction_Nm=float(friction),
            friction_ratio=ratio,
            friction_output_V=float(gain * friction / stiffness),
            stick_fraction=float(rng.uniform(-1.0, 1.0)),
        )
    elif effect == "pickoff_hysteresis":
        ratio = _log_uniform(rng, *PLAY_RATIO)
        play = ratio * theta_full
        truth.update(
            play_rad=float(play),
            play_m=float(play * device.l),
            play_ratio=ratio,
            play_output_V=float(gain * play),
            approach_sign=float(rng.choice([-1.0, 1.0])),
        )
    elif effect == "second_mode":
        ratio = _log_uniform(rng, *MODE_RATIO)
        truth.update(
            mode_Hz=float(ratio * natural),
            mode_ratio=ratio,
            mode_zeta=float(rng.uniform(*MODE_ZETA)),
            mode_coupling=_log_uniform(rng, *MODE_COUPLING),
        )
    if measure:
        truth.update(effect_size(truth))
    return truth


_CACHE: dict = {}
_CACHE_SIZE = 8


def _world_key(truth: dict, rtol) -> str:
    return json.dumps(
        [{k: v for k, v in truth.items() if k not in MEASURED}, rtol], sort_keys=True
    )


def clean_record(truth: dict, *, effect=True, rtol=1e-10):
    """(t [s] from 0, u_test [V], u_out [V]) of the truth's record without noise or ADC
    (output sign and offset applied); `effect` False: the same record without its effect.
    The last few are cached (`make` reuses `draw`'s)."""
    device, rec, effects = world(truth)
    if not effect:
        effects = Effects()
    key = _world_key(truth, rtol) + str(bool(effect))
    if key not in _CACHE:
        t, u, clean, _ = run(device, rec, effects, rtol=rtol)
        y = rec.output_sign * clean + rec.output_offset
        if len(_CACHE) >= _CACHE_SIZE:
            _CACHE.pop(next(iter(_CACHE)))
        _CACHE[key] = (t - t[0], u, y, clean)
    t, u, y, _ = _CACHE[key]
    return t.copy(), u.copy(), y.copy()


def effect_size(truth: dict, *, rtol=1e-10) -> dict:
    """{"effect_rms_V", "effect_over_noise", "visible"}: the RMS over the record of the
    noise-free record minus the same record without the effect, over the white noise σ,
    and whether that is ≥ `VISIBLE_OVER_NOISE` (None for "none")."""
    if truth["effect"] == "none":
        return {"effect_rms_V": 0.0, "effect_over_noise": 0.0, "visible": None}
    _, _, with_effect = clean_record(truth, rtol=rtol)
    _, _, without = clean_record(truth, effect=False, rtol=rtol)
    rms = float(np.sqrt(np.mean((with_effect - without) ** 2)))
    ratio = rms / truth["noise_V"] if truth["noise_V"] > 0 else float("inf")
    return {
        "effect_rms_V": rms,
        "effect_over_noise": float(ratio),
        "visible": bool(ratio >= VISIBLE_OVER_NOISE),
    }


def make(truth: dict, rng: np.random.Generator, *, rtol=1e-10):
    """(t [s] from 0, u_test column [V], u_out column [V]) of a drawn world, the noisy,
    quantised record as a test stand stores it (the noise drawn from rng as
    `step_truth.make` draws it). "none" at step_truth's duration is `step_truth.make`'s
    record itself."""
    if truth["effect"] == "none" and truth.get("duration_s", step_truth.DURATION) == (
        step_truth.DURATION
    ):
        t, u, y, _ = step_truth.make(truth, rng)
        return t, u, y
    device, rec, effects = world(truth)
    key = _world_key(truth, rtol) + "True"
    if key in _CACHE:
        t, u, _, clean = _CACHE[key]
    else:
        t, u, clean, _ = run(device, rec, effects, rtol=rtol)
        t = t - t[0]
    return t.copy(), u.copy(), step_truth.recorded(rec, clean, rng)
