"""An independent truth simulator of closed-loop test-signal records (SciPy, not JAX).

Written from the equations of docs/models.md §1 with none of the library's code: its own state
equations, SciPy's `solve_ivp` (DOP853) integrating between events, and its own handling
of the mechanical stops as exact events. The blind validation uses it so that the
diagnosis is checked on records made with other conventions than its own:

- the test voltage changes at arbitrary times between samples (a DAC on its own clock),
  and the `u_test` column is that voltage *sampled* at the record's times;
- the test winding may be wired with either polarity, and its gain differs from the
  feedback winding's;
- the record starts wherever the recorder was started: at rest, or in the middle of the
  transient of an earlier change (a test sequence already running), or with the pendulum
  resting on a stop where an earlier, larger level had held it (`ON_STOP_STARTS`);
- the output carries an ADC offset and is quantised by an ADC of given step size;
- sample rates of 0.5–2 MHz and multi-level test sequences.

Loop (SI units; a the input acceleration, M the external moment):

    J θ'' + μ θ' + c θ = M_dm + M(t) + M_stop,   M(t) = M_0 + Ṁ t + m l a(t)
    T_dm M_dm' = k_dm (g_w U_test(t) − U_amp) − M_dm      (M_dm algebraic when T_dm = 0)
    U_amp = k_dp k_y l θ · (1 + p2 x + p3 x²),  x = θ/θ_ref   (pickoff nonlinearity)
    T_f U_f' = U_amp − U_f,   U_out = U_f                  (U_out = U_amp when T_f = 0)

Stops at |l θ| = h_max, inelastic: at contact the velocity is lost; the pendulum stays on
the stop while the net moment presses it there and leaves it (from rest) when the moment
reverses, each found as an event of the integration. The input acceleration a(t) =
g₀·a_in(t) + a_vib(t) is a piecewise-constant acceleration a_in [g] (a tilt or centrifuge
step; g₀ = 9.80665 m/s²) whose changes, like those of the test voltage, fall anywhere
between samples and break the integration exactly as the test voltage's do, plus the
sinusoidal a_vib. Options outside the accelerometer model (for the out-of-library cases):
the pickoff nonlinearity p2, p3; the sinusoidal input acceleration (a vibrating test
stand); and a band-pass (velocity-output) sensor, whose output is the rate of a
second-order system driven by the calibration signal.

Everything is float64 NumPy/SciPy. `simulate(device, record, rng=...)` returns
(t, u_test, u_out), and (t, u_test, u_out, a_in) for a record with an acceleration input.
`draw_truth`/`make` draw and simulate the blind harness's single records,
`draw_device_set`/`make_set` one device's set of records (small steps, steps onto the
stops, acceleration steps) for the multi-record diagnosis; `draw_truth_on_stop` a record
that starts on a stop (for `make`). For a test stand's view of the input: `measure_input`
(the digitised input channel: delay, anti-alias filter, noise, ADC, relay spikes, offset,
drift), and calibration sequences: `prbs_levels` (random telegraph), `sweep_column` and
`sweep_levels` (a chirp: an input with no plateaus).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.integrate import solve_ivp
from scipy.signal import lfilter

STANDARD_GRAVITY = 9.80665
"""g₀ [m/s²]: the unit of `Record.accel_levels`."""


@dataclasses.dataclass
class Device:
    """Physical values (SI). `test_gain` g_w is the test winding's signed gain relative to
    the feedback winding (−1: wired the other way)."""

    m: float = 2.9e-4
    l: float = 4.28e-3
    J: float = 7.09e-9
    mu: float = 2.54e-5
    c: float = 3.02e-4
    h_max: float = float("inf")
    k_dp: float = 2.5e5
    k_y: float = 8.5
    k_dm: float = 9.23e-6
    T_dm: float = 0.0
    T_f: float = 0.0
    test_gain: float = 1.0
    pickoff_p2: float = 0.0
    pickoff_p3: float = 0.0
    pickoff_reference_rad: float = 1e-3


@dataclasses.dataclass
class Record:
    """What the recorder sees and the world it records.

    `levels` (J+1,) the test voltages [V]; `change_times` (J,) [s] when they change;
    `rate` [Hz]; `n` samples from `t0` [s]; `moment` M_0 [N·m] and `moment_rate` Ṁ
    [N·m/s]; `vibration` (amplitude [m/s²], frequency [Hz], phase [rad]) of the input
    acceleration; `output_offset` [V]; `output_sign` ±1 (an inverting recorder input);
    `adc_step` [V] (0: none); `noise` white σ [V]; `gm` (σ [V], τ [s]) Gauss–Markov output
    noise; `start` "rest" (at rest under the first level, long before t0) or a number:
    the time [s] before t0 at which the first level was switched on from `start_level`,
    or "on_stop_high" / "on_stop_low": at rest on the +h_max / −h_max stop at t0 (see
    `ON_STOP_STARTS`), where it was held by the test voltage `hold_level` [V] (None: the
    level in force at t0); that level was switched off, and the record's level switched
    on, exactly at t0.
    `bandpass` (ω0 [rad/s], ζ, gain [V·s/V]) replaces the accelerometer by a velocity-
    output sensor driven by the calibration voltage (it ignores the acceleration input).
    `accel_levels` (K+1,) the piecewise-constant input acceleration [g] (None: none) and
    `accel_change_times` (K,) [s] when it changes (any times, like `change_times`); the
    level in force at t is accel_levels[#changes ≤ t], as for the test voltage.
    """

    levels: np.ndarray
    change_times: np.ndarray
    rate: float
    n: int
    t0: float = 0.0
    moment: float = 0.0
    moment_rate: float = 0.0
    vibration: tuple = (0.0, 0.0, 0.0)
    output_offset: float = 0.0
    output_sign: float = 1.0
    adc_step: float = 0.0
    noise: float = 0.0
    gm: tuple = (0.0, 1.0)
    start: object = "rest"
    start_level: float = 0.0
    bandpass: tuple | None = None
    accel_levels: np.ndarray | None = None
    accel_change_times: np.ndarray | None = None
    hold_level: float | None = None


ON_STOP_STARTS = {"on_stop_high": 1, "on_stop_low": -1}
"""`Record.start` values of a record that starts with the pendulum resting on a stop (the
sign of θ there). The story: an earlier, larger test voltage (`Record.hold_level`) drove
the pendulum onto that stop and held it there at rest (θ = ±h_max/l, θ' = 0), long enough
for the torquer lag and the output filter to settle: M_dm = k_dm (g_w U_hold − U_stop),
U_f = U_stop, with U_stop = ±k_dp k_y h_max (times the pickoff nonlinearity, if any) the
pickoff output at the stop. At t0 the record's own sequence takes over: from t0 the level
in force is the record's, and the pendulum stays on the stop while the net moment
J θ'' = M_dm + M(t) − c θ still presses it outward, and leaves it (the release event) when
that moment reverses: at once when T_dm = 0 (the torquer has no state) and the level in
force at t0 would settle inside the stops; after the torquer lag has turned M_dm round
when T_dm > 0. With `hold_level` None the holding voltage is the level in force at t0
itself (exact for T_dm = 0, where the earlier voltage leaves no trace; for T_dm > 0 the
torquer starts settled under that level). A given `hold_level` must press the pendulum
onto the named stop (else `simulate` raises ValueError). The output at t0 is the stop's:
output_sign · U_stop + output_offset."""


def _accel_steps(rec: Record):
    """(levels [g], change times [s]) of the input acceleration; ([0], []) for none."""
    if rec.accel_levels is None:
        return np.zeros(1), np.zeros(0)
    levels = np.atleast_1d(np.asarray(rec.accel_levels, dtype=float))
    times = np.atleast_1d(np.asarray(rec.accel_change_times, dtype=float))
    if times.size != levels.size - 1:
        raise ValueError("accel_change_times needs one time fewer than accel_levels")
    return levels, times


class _Loop:
    def __init__(self, d: Device, rec: Record):
        self.d, self.rec = d, rec
        self.gain = d.k_dp * d.k_y * d.l  # V/rad
        self.theta_stop = d.h_max / d.l
        self.accel_levels, self.accel_changes = _accel_steps(rec)

    def accel_at(self, t):
        """The piecewise-constant input acceleration [g] in force at t."""
        return float(self.accel_levels[np.searchsorted(self.accel_changes, t, side="right")])

    def amp(self, theta):
        d = self.d
        x = theta / d.pickoff_reference_rad
        return self.gain * theta * (1 + d.pickoff_p2 * x + d.pickoff_p3 * x * x)

    def moment(self, t, a):
        """M(t) [N·m] under the piecewise-constant acceleration a [g] (held constant over
        an integration piece) and the vibration."""
        rec, d = self.rec, self.d
        a_amp, a_freq, a_phase = rec.vibration
        accel = a_amp * np.sin(2 * np.pi * a_freq * t + a_phase) if a_amp else 0.0
        accel = accel + STANDARD_GRAVITY * a
        return rec.moment + rec.moment_rate * t + d.m * d.l * accel

    def torquer(self, y, u):
        """M_dm: the state, or algebraic when T_dm = 0."""
        d = self.d
        if d.T_dm > 0:
            return y[2]
        return d.k_dm * (d.test_gain * u - self.amp(y[0]))

    def net_moment(self, t, y, u, a):
        d = self.d
        return self.torquer(y, u) + self.moment(t, a) - d.mu * y[1] - d.c * y[0]

    def rhs(self, t, y, u, a, held):
        d = self.d
        dy = np.zeros_like(y)
        if held:
            dy[0] = dy[1] = 0.0
        else:
            dy[0] = y[1]
            dy[1] = self.net_moment(t, y, u, a) / d.J
        if d.T_dm > 0:
            dy[2] = (d.k_dm * (d.test_gain * u - self.amp(y[0])) - y[2]) / d.T_dm
        if d.T_f > 0:
            dy[3] = (self.amp(y[0]) - y[3]) / d.T_f
        return dy

    def output(self, y):
        return y[3] if self.d.T_f > 0 else self.amp(y[0])

    def rest(self, u, t):
        """The state at rest under the test voltage u and the moment (with the acceleration
        in force) at t (Newton on θ)."""
        d = self.d
        moment = self.moment(t, self.accel_at(t))
        theta = (d.k_dm * d.test_gain * u + moment) / (d.c + d.k_dm * self.gain)
        for _ in range(50):
            f = d.c * theta - d.k_dm * (d.test_gain * u - self.amp(theta)) - moment
            h = 1e-9 * max(abs(theta), 1e-9)
            slope = (
                d.c * (theta + h)
                + d.k_dm * self.amp(theta + h)
                - d.c * theta
                - d.k_dm * self.amp(theta)
            ) / h
            step = f / slope
            theta -= step
            if abs(step) < 1e-16 * max(abs(theta), 1e-12):
                break
        if np.isfinite(self.theta_stop):
            theta = float(np.clip(theta, -self.theta_stop, self.theta_stop))
        y = np.zeros(4)
        y[0] = theta
        y[2] = d.k_dm * (d.test_gain * u - self.amp(theta))
        y[3] = self.amp(theta)
        return y

    def on_stop(self, sign, u):
        """The state at rest on the stop of the given sign (θ = ±θ_stop, θ' = 0), with the
        torquer moment and the output filter settled there under the test voltage u:
        M_dm = k_dm (g_w u − U_amp(±θ_stop)), U_f = U_amp(±θ_stop)."""
        d = self.d
        theta = sign * self.theta_stop
        y = np.zeros(4)
        y[0] = theta
        y[2] = d.k_dm * (d.test_gain * u - self.amp(theta))
        y[3] = self.amp(theta)
        return y


def _integrate(loop: _Loop, y, held, t_start, t_end, u, a, t_eval, out, rtol):
    """Integrate from t_start to t_end under the constant test voltage u and acceleration
    a [g], handling stop contacts and releases as events; fill `out` at the times `t_eval`
    (indices into out). Returns the state and the held flag (0 free, ±1 on the
    upper/lower stop) at t_end."""
    d = loop.d
    stop = loop.theta_stop
    times, index = t_eval
    t = t_start
    period = np.sqrt(d.J / (d.c + d.k_dm * loop.gain))
    while t < t_end:
        if held != 0 and held * loop.net_moment(t, y, u, a) <= 0:
            held = 0  # the new test voltage pulls it off the stop at once
        events = []
        if held == 0 and np.isfinite(stop):

            def hit_high(tt, yy):
                return yy[0] - stop

            def hit_low(tt, yy):
                return yy[0] + stop

            hit_high.terminal = hit_low.terminal = True
            hit_high.direction, hit_low.direction = 1, -1
            events = [hit_high, hit_low]
        elif held != 0:

            def release(tt, yy, sign=held):
                return sign * loop.net_moment(tt, yy, u, a)

            release.terminal = True
            release.direction = -1
            events = [release]
        inside = (times >= t) & (times <= t_end)
        sol = solve_ivp(
            lambda tt, yy, on_stop=held != 0: loop.rhs(tt, yy, u, a, on_stop),
            (t, t_end),
            y,
            method="DOP853",
            rtol=rtol,
            atol=1e-14,
            events=events or None,
            dense_output=True,
            max_step=0.05 * period,
        )
        t_stop = sol.t[-1]
        take = inside & (times <= t_stop)
        if np.any(take):
            states = sol.sol(times[take])
            out[index[take]] = [loop.output(s) for s in states.T]
            times, index = times[~take], index[~take]
        y = sol.y[:, -1].copy()
        if sol.status == 1:  # an event
            if held == 0:
                sign = 1 if y[0] > 0 else -1
                y[0] = sign * stop
                y[1] = 0.0
                # Pressed onto the stop, or only touching it in an overshoot?
                held = sign if sign * loop.net_moment(t_stop, y, u, a) > 0 else 0
                if held == 0:
                    # From rest on the stop, moving inward: nudge to avoid re-triggering.
                    y[0] -= sign * 1e-15 * stop
            else:
                held = 0
        t = t_stop
    return y, held


def recorded(rec: Record, clean, rng: np.random.Generator):
    """What the recorder writes of the clean output U_out [V]: output_sign × U_out +
    output_offset, plus white noise of σ `rec.noise` (drawn first), plus Gauss–Markov noise
    `rec.gm` (drawn next, stationary from the first sample), quantised by `rec.adc_step`
    (0: none)."""
    y_out = rec.output_sign * clean + rec.output_offset
    if rec.noise > 0:
        y_out = y_out + rng.normal(size=rec.n) * rec.noise
    sigma, tau = rec.gm
    if sigma > 0:
        phi = np.exp(-1 / (rec.rate * tau))
        w = rng.normal(size=rec.n) * sigma * np.sqrt(1 - phi**2)
        w[0] = rng.normal() * sigma
        y_out = y_out + lfilter([1.0], [1.0, -phi], w)
    if rec.adc_step > 0:
        y_out = rec.adc_step * np.round(y_out / rec.adc_step)
    return y_out


def simulate(device: Device, rec: Record, *, rng: np.random.Generator, rtol=1e-10):
    """(t [s], u_test column [V], u_out column [V]) of one record (see `Record`), and with
    an acceleration input (`rec.accel_levels` not None) (t, u_test, u_out, a_in column
    [g]): the inputs sampled at the record's times (the level in force at t_k)."""
    t = rec.t0 + np.arange(rec.n) / rec.rate
    levels = np.asarray(rec.levels, dtype=float)
    changes = np.asarray(rec.change_times, dtype=float)
    u_column = levels[np.searchsorted(changes, t, side="right")]
    accel_levels, accel_changes = _accel_steps(rec)
    a_column = accel_levels[np.searchsorted(accel_changes, t, side="right")]
    if rec.bandpass is not None:
        clean = _bandpass(rec, t, levels, changes)
    else:
        loop = _Loop(device, rec)
        clean = np.empty(rec.n)
        if rec.start == "rest":
            t_begin, y = t[0], loop.rest(levels[0], t[0])
        elif isinstance(rec.start, str) and rec.start in ON_STOP_STARTS:
            if not np.isfinite(loop.theta_stop):
                raise ValueError(f"start {rec.start!r} needs a device with stops (finite h_max)")
            sign = ON_STOP_STARTS[rec.start]
            t_begin = t[0]
            u_first = float(levels[np.searchsorted(changes, t_begin, side="right")])
            u_hold = u_first if rec.hold_level is None else float(rec.hold_level)
            y = loop.on_stop(sign, u_hold)
            if rec.hold_level is not None:
                pressed = sign * loop.net_moment(t_begin, y, u_hold, loop.accel_at(t_begin))
                if not pressed > 0:
                    raise ValueError(
                        f"hold_level {u_hold} V does not press the pendulum onto the stop "
                        f"of start {rec.start!r}"
                    )
        else:
            t_begin = t[0] - float(rec.start)
            y = loop.rest(rec.start_level, t_begin)
        held = 0
        if (
            np.isfinite(loop.theta_stop)
            and abs(abs(y[0]) - loop.theta_stop) < 1e-12 * loop.theta_stop
        ):
            held = 1 if y[0] > 0 else -1
        # The pieces break at every change of either input.
        both = np.unique(np.concatenate([changes, accel_changes]))
        edges = np.concatenate([[t_begin], both[(both > t_begin) & (both < t[-1])], [t[-1]]])
        level_of = levels[np.searchsorted(changes, edges[:-1], side="right")]
        accel_of = accel_levels[np.searchsorted(accel_changes, edges[:-1], side="right")]
        pending = (t, np.arange(rec.n))
        for a, b, u, acc in zip(edges[:-1], edges[1:], level_of, accel_of, strict=True):
            y, held = _integrate(loop, y, held, a, b, u, acc, pending, clean, rtol)
            done = pending[0] <= b
            pending = (pending[0][~done], pending[1][~done])
    y_out = recorded(rec, clean, rng)
    if rec.accel_levels is None:
        return t, u_column, y_out
    return t, u_column, y_out, a_column


def _bandpass(rec: Record, t, levels, changes):
    """Velocity output of a second-order sensor (ω0, ζ, gain G) driven by the calibration
    voltage: y = G·d/dt x, x'' + 2ζω0 x' + ω0² x = ω0² u — exact sum of step responses,
    each (G ΔU ω0/ω_d) e^{−ζω0 s} sin(ω_d s) for ζ < 1. The output returns to zero after
    every step."""
    omega0, zeta, gain = rec.bandpass
    wd = omega0 * np.sqrt(max(1 - zeta**2, 1e-12))
    y = np.zeros(t.size)
    for tau, step in zip(changes, np.diff(levels), strict=True):
        s = t - tau
        on = s > 0
        y[on] += (
            gain
            * step
            * omega0
            / np.sqrt(1 - zeta**2)
            * np.exp(-zeta * omega0 * s[on])
            * np.sin(wd * s[on])
        )
    return y


# --------------------------------------------------------------------------------------
# The blind harness's world: conventions and effects drawn at random
# --------------------------------------------------------------------------------------

RATES = (0.5e6, 1e6, 2e6)
"""Sample rates [Hz], one drawn per record."""

DURATION = 12e-3
"""Record length [s]: a test sequence of `SEGMENTS` levels, each 1.2–2.2 ms (4–8 loop time
constants: most transients have not died out when the next level comes)."""

SEGMENTS = 7
LEVELS = (-1.0, -0.5, 0.0, 0.5, 1.0)
"""Test-voltage levels in units of the record's U_max (uniform 1.5–2.5 V)."""

NOISE = (2e-4, 2e-3)
"""White output noise σ [V], log-uniform."""

ADC_BITS = (14, 16, 18)
"""ADC resolution over ±10 V (q = 1.2 mV, 0.31 mV, 76 µV)."""

DEVICE_SD = {"J": 0.02, "mu": 0.02, "c": 0.02, "k_dm": 0.02, "k_dp": 0.01, "k_y": 0.01}
"""Relative σ of the device's values about the reference (the ±2 % device)."""

IN_LIBRARY = (
    "torquer_lag",
    "output_filter",
    "stop_saturation",
    "disturbance_drift",
    "colored_noise",
)
OUT_OF_LIBRARY = ("pickoff_nonlinearity", "bandpass_sensor", "periodic_disturbance")
CLASSES = ("none",) + IN_LIBRARY + OUT_OF_LIBRARY

ON_STOP_EFFECT = "start_on_stop"
"""The effect name of `draw_truth_on_stop`'s records (not in `CLASSES`): a device with
stops whose record starts with the pendulum resting on one of them. An in-library situation
for the stop effect (the loop and its stops are the library's model). With no torquer lag
the pendulum leaves the stop at t0 and the small steps never bring it back: no stop acts
within the record, and its start (displaced, at rest) is a state a transient of an
earlier input could leave, so a record of this class cannot show the stop (the blind
harness counts its `none` apart). `ON_STOP_HELD_EFFECT` is the class whose stop acts in
the record."""

ON_STOP_HELD_EFFECT = "held_on_stop"
"""The effect name of `draw_truth_on_stop(held=True)`'s records: as `ON_STOP_EFFECT`'s, but
the record's own first level is the holding voltage, so the pendulum rests on the stop
through the whole first segment and leaves it at the first change (a device left pressed
against its stop by the test sequence when the recorder started). The stop acts inside the
record: the honest verdict is the stop effect or `unexplained`, never `none`."""

ON_STOP_STOP = (1.8, 2.3)
"""stop_over_u_max of an on-stop record, uniform: the stop voltage k_dp k_y h_max over the
settled output of the full small level (U_max), beyond the reach of the later small steps'
transients (their overshoot at ζ ≈ 0.5, from the stop or between levels, with the moment's
offset of up to ≈ 0.2 V): over 100 drawn records (seeds 0–99) the output, once off the
starting stop, reached at most 0.86 of the stop voltage (1.59 U_max k_test)."""

ON_STOP_HOLD = (1.2, 1.5)
"""The holding level of an on-stop record over the level whose settled output just reaches
the stop, uniform (the earlier test voltage that drove the pendulum onto it)."""


def _log_uniform(rng, low, high):
    return float(np.exp(rng.uniform(np.log(low), np.log(high))))


def _draw_device(rng) -> dict:
    """The device's values about the reference (`DEVICE_SD`) and its test winding's gain,
    of random sign."""
    ref = Device()
    return {
        "J": ref.J * np.exp(rng.normal() * DEVICE_SD["J"]),
        "mu": ref.mu * np.exp(rng.normal() * DEVICE_SD["mu"]),
        "c": ref.c * np.exp(rng.normal() * DEVICE_SD["c"]),
        "k_dm": ref.k_dm * np.exp(rng.normal() * DEVICE_SD["k_dm"]),
        "k_dp": ref.k_dp * np.exp(rng.normal() * DEVICE_SD["k_dp"]),
        "k_y": ref.k_y * np.exp(rng.normal() * DEVICE_SD["k_y"]),
        "test_gain": float(rng.choice([-1.0, 1.0]) * np.exp(rng.normal() * 0.02)),
    }


def _draw_small_steps(rng):
    """(U_max [V], levels [V], change times [s]) of a small-step test sequence: `SEGMENTS`
    levels from `LEVELS` × U_max over `DURATION`, changes at exact (off-grid) times."""
    u_max = rng.uniform(1.5, 2.5)
    levels = [float(rng.choice(LEVELS))]
    while len(levels) < SEGMENTS:
        level = float(rng.choice(LEVELS))
        if level != levels[-1]:
            levels.append(level)
    if max(abs(x) for x in levels) < 1:  # reach the full level at least once
        levels[int(rng.integers(1, SEGMENTS))] = float(rng.choice([-1.0, 1.0]))
        for i in range(1, SEGMENTS):
            if levels[i] == levels[i - 1]:
                levels[i] = 0.5 if levels[i - 1] != 0.5 else -0.5
    lengths = rng.uniform(1.2, 2.2, SEGMENTS)
    bounds = np.cumsum(lengths / lengths.sum() * DURATION)[:-1]
    return u_max, [x * u_max for x in levels], bounds.tolist()


def draw_truth(rng: np.random.Generator, effect: str) -> dict:
    """One record's world: device, conventions (rate, test sequence and its DAC timing,
    polarities, offset, ADC, start state) and the effect with its magnitude."""
    device = _draw_device(rng)
    u_max, levels, bounds = _draw_small_steps(rng)
    truth = {
        "effect": effect,
        "device": device,
        "levels_V": levels,
        "change_times_s": bounds,  # exact times: the DAC runs on its own clock
        **_draw_conventions(rng, u_max),  # the same draws, in the same order
        "u_max_V": u_max,
    }
    if effect in ("torquer_lag", "output_filter"):
        truth["lag_s"] = _log_uniform(rng, 5e-6, 5e-5)
    elif effect == "stop_saturation":
        truth["stop_over_u_max"] = float(rng.uniform(0.8, 1.1))
    elif effect == "disturbance_drift":
        truth["drift_V"] = _log_uniform(rng, 2e-3, 2e-2) * float(rng.choice([-1.0, 1.0]))
    elif effect == "colored_noise":
        truth["gm_time_s"] = _log_uniform(rng, 2e-5, 2e-4)
        truth["gm_over_white"] = float(rng.uniform(0.5, 2.0))
    elif effect == "pickoff_nonlinearity":
        truth["p2"] = _log_uniform(rng, 0.02, 0.1) * float(rng.choice([-1.0, 1.0]))
        truth["p3"] = _log_uniform(rng, 0.02, 0.1) * float(rng.choice([-1.0, 1.0]))
    elif effect == "bandpass_sensor":
        truth["bandpass_Hz"] = _log_uniform(rng, 100.0, 1000.0)
        truth["bandpass_zeta"] = float(rng.uniform(0.3, 0.8))
        truth["bandpass_gain_s"] = _log_uniform(rng, 2e-4, 2e-3)
    elif effect == "periodic_disturbance":
        truth["vibration_Hz"] = _log_uniform(rng, 200.0, 3000.0)
        truth["vibration_over_noise"] = _log_uniform(rng, 5.0, 50.0)
        truth["vibration_phase"] = float(rng.uniform(0, 2 * np.pi))
    return truth


def record_from_truth(truth: dict, **changes) -> Record:
    """The `Record` of a drawn world (`draw_truth`'s dict, or another truth simulator's
    with the same keys): its sequence, conventions and start, `duration_s` long
    (`DURATION` where the dict has none); `changes` set further fields (`hold_level`)."""
    rate = truth["rate"]
    return Record(
        levels=np.asarray(truth["levels_V"], dtype=float),
        change_times=np.asarray(truth["change_times_s"], dtype=float),
        rate=rate,
        n=int(round(truth.get("duration_s", DURATION) * rate)),
        moment=truth["moment_Nm"],
        output_offset=truth["output_offset_V"],
        output_sign=truth["output_sign"],
        adc_step=truth["adc_step_V"],
        noise=truth["noise_V"],
        start=truth["start"],
        start_level=truth["start_level_V"],
        **changes,
    )


def make(truth: dict, rng: np.random.Generator):
    """Simulate one drawn world (`draw_truth`'s, or `draw_truth_on_stop`'s): (t, u_test
    column, u_out column, noise component) [s, V]."""
    d = truth["device"]
    device = Device(J=d["J"], mu=d["mu"], c=d["c"], k_dm=d["k_dm"], k_dp=d["k_dp"], k_y=d["k_y"])
    device.test_gain = d["test_gain"]
    gain = device.k_dp * device.k_y * device.l
    loop_k = device.c + device.k_dm * gain
    u_max = truth["u_max_V"]
    k_test = device.k_dm * gain / loop_k
    effect = truth["effect"]
    rate = truth["rate"]
    n = int(round(DURATION * rate))
    record = record_from_truth(truth)
    if effect == "torquer_lag":
        device.T_dm = truth["lag_s"]
    elif effect == "output_filter":
        device.T_f = truth["lag_s"]
    elif effect == "stop_saturation":
        device.h_max = truth["stop_over_u_max"] * u_max * k_test / (device.k_dp * device.k_y)
    elif effect == ON_STOP_EFFECT:
        device.h_max = truth["stop_over_u_max"] * u_max * k_test / (device.k_dp * device.k_y)
        record.hold_level = truth["start_level_V"]
    elif effect == ON_STOP_HELD_EFFECT:  # held by the record's own first level
        device.h_max = truth["stop_over_u_max"] * u_max * k_test / (device.k_dp * device.k_y)
    elif effect == "disturbance_drift":
        # Ṁ such that the settled output moves by drift_V over the record.
        record.moment_rate = truth["drift_V"] * loop_k / gain / DURATION
    elif effect == "colored_noise":
        record.gm = (truth["gm_over_white"] * truth["noise_V"], truth["gm_time_s"])
    elif effect == "pickoff_nonlinearity":
        device.pickoff_p2, device.pickoff_p3 = truth["p2"], truth["p3"]
        device.pickoff_reference_rad = u_max * k_test / gain
    elif effect == "bandpass_sensor":
        record.bandpass = (
            2 * np.pi * truth["bandpass_Hz"],
            truth["bandpass_zeta"],
            truth["bandpass_gain_s"],
        )
    elif effect == "periodic_disturbance":
        # An input-axis vibration whose output amplitude is vibration_over_noise × σ.
        omega = 2 * np.pi * truth["vibration_Hz"]
        period = np.sqrt(device.J / loop_k)
        zeta = device.mu / 2 / np.sqrt(device.J * loop_k)
        response = 1 / abs(1 - (omega * period) ** 2 + 2j * zeta * omega * period)
        scale_factor = device.m * device.l**2 * device.k_dp * device.k_y / loop_k  # V/(m/s²)
        amplitude = truth["vibration_over_noise"] * truth["noise_V"] / (scale_factor * response)
        record.vibration = (amplitude, truth["vibration_Hz"], truth["vibration_phase"])
    t, u, y = simulate(device, record, rng=rng)
    clean_record = dataclasses.replace(record, noise=0.0, gm=(0.0, 1.0), adc_step=0.0)
    _, _, clean = simulate(device, clean_record, rng=np.random.default_rng(0))
    return t - t[0], u, y, y - clean


def draw_truth_on_stop(rng: np.random.Generator, held: bool = False) -> dict:
    """One record of a device that rests on a mechanical stop when the record starts
    (effect `ON_STOP_EFFECT`), then driven off it by a small-step test sequence.

    The world is drawn as `draw_truth`'s (device, small-step sequence, conventions: the
    same draws in the same order), then: the stop (+h_max: "on_stop_high", −h_max:
    "on_stop_low", even odds), `stop_over_u_max` uniform in `ON_STOP_STOP` (the stop voltage
    k_dp k_y h_max = stop_over_u_max × U_max × k_test, as `stop_saturation`'s, but beyond
    every small level's settled output and its transients) and `hold_over_stop` uniform in
    `ON_STOP_HOLD`. The story (`ON_STOP_STARTS`): an earlier test voltage, `start_level_V`
    = hold_over_stop × the voltage whose settled output (with the record's moment) just
    reaches that stop, drove the pendulum onto the stop and held it there at rest; it was
    switched off at t0, when the record's first level came on. That level settles inside
    the stops, so the pendulum leaves the stop from t0 (the devices here have no torquer
    lag: at once), from rest, and the record's first samples sit at the stop voltage
    (output_sign × ±k_dp k_y h_max + output_offset) while it starts to move. The conventions'
    drawn `start` and `start_level_V` are replaced by the on-stop start and this level.

    `held`: the record's first level is that holding voltage (effect `ON_STOP_HELD_EFFECT`):
    the pendulum stays on the stop until the first change, then the small steps drive it."""
    device = _draw_device(rng)
    u_max, levels, bounds = _draw_small_steps(rng)
    truth = {
        "effect": ON_STOP_EFFECT,
        "device": device,
        "levels_V": levels,
        "change_times_s": bounds,
        **_draw_conventions(rng, u_max),
        "u_max_V": u_max,
    }
    side = float(rng.choice([-1.0, 1.0]))
    truth["stop_over_u_max"] = float(rng.uniform(*ON_STOP_STOP))
    truth["hold_over_stop"] = float(rng.uniform(*ON_STOP_HOLD))
    truth["start"] = "on_stop_high" if side > 0 else "on_stop_low"
    # The settled output under U is k_test g_w U + gain M/(c + k_dm gain); the holding
    # level is hold_over_stop times the U at which it equals the stop's ±k_dp k_y h_max.
    gain = device["k_dp"] * device["k_y"] * Device().l
    loop_k = device["c"] + device["k_dm"] * gain
    k_test = device["k_dm"] * gain / loop_k
    stop_V = truth["stop_over_u_max"] * u_max * k_test
    reach = (side * stop_V - gain * truth["moment_Nm"] / loop_k) / (k_test * device["test_gain"])
    truth["start_level_V"] = float(truth["hold_over_stop"] * reach)
    if held:
        truth["effect"] = ON_STOP_HELD_EFFECT
        truth["levels_V"] = [truth["start_level_V"]] + list(truth["levels_V"][1:])
    return truth


# --------------------------------------------------------------------------------------
# Device sets for the multi-record diagnosis: one device, several records
# --------------------------------------------------------------------------------------

SET_EFFECTS = ("none", "torquer_lag", "output_filter")
"""The effects of a device set: none (both lags at the reference's 10 µs) or one lag
replaced by a drawn value."""

REFERENCE_LAG = 1e-5
"""T_dm = T_f [s] of the reference device: every set's baseline."""

REFERENCE_STOP = 1.9e-6
"""h_max [m] of the reference device (docs/models.md §1); a set's device draws it × e^{N(0, 0.03)}."""

STOP_LEVEL = (5.0, 6.0)
"""U [V] of the stops record, uniform: its settled output ≈ U lies beyond the stop voltage
k_dp k_y h_max ≈ 4.0 V, so the pendulum is driven onto its stops."""

STOP_SEGMENT = (1.2e-3, 2.2e-3)
"""Segment lengths [s] of the stops record's levels [0, +U, −U, +U, −U, 0], uniform."""

ACCEL_LEVEL = (0.5, 1.0)
"""a [g] of the acceleration record's levels [0, +a, −a, 0], uniform."""

ACCEL_SEGMENT = (1.5e-3, 2.5e-3)
"""Segment lengths [s] of the acceleration record, uniform."""


def _draw_conventions(rng, level_scale) -> dict:
    """A record's own recorder conventions and start state (as `draw_truth`'s); the start
    transient's earlier test voltage is a level of `LEVELS` × `level_scale` [V]."""
    return {
        "rate": float(rng.choice(RATES)),
        "noise_V": _log_uniform(rng, *NOISE),
        "adc_step_V": 20.0 / 2 ** int(rng.choice(ADC_BITS)),
        "output_offset_V": float(rng.uniform(-0.05, 0.05)),
        "output_sign": float(rng.choice([-1.0, 1.0])),
        "moment_Nm": float(rng.uniform(-2e-6, 2e-6)),
        "start": "rest" if rng.uniform() < 0.5 else float(rng.uniform(1e-4, 1e-3)),
        "start_level_V": float(rng.choice(LEVELS)) * level_scale,
    }


def _segment_times(rng, count, bounds):
    """(change times [s], record length [s]) of `count` segments of uniform lengths."""
    ends = np.cumsum(rng.uniform(*bounds, count))
    return ends[:-1].tolist(), float(ends[-1])


def draw_device_set(rng: np.random.Generator, effect: str, *, accel: bool) -> dict:
    """One device and its set of records (JSON-able).

    The device is drawn as in `draw_truth` (J, μ, c, k_dm, k_dp, k_y about the reference,
    the test winding's signed gain), with stops at h_max = 1.9e-6 m × e^{N(0, 0.03)} and
    the reference's lags T_dm = T_f = 10 µs; `effect` ("none", "torquer_lag",
    "output_filter") replaces one of them by a lag drawn log-uniform in 5–50 µs. Records,
    each with its own rate, offset, polarity, ADC, white noise, moment and start state:

    - "small": a small-step test sequence as `draw_truth`'s (within the stops);
    - "stops": the test-voltage levels [0, +U, −U, +U, −U, 0], U uniform 5–6 V, segments
      1.2–2.2 ms: the pendulum is driven onto its stops;
    - with `accel`, "accel": the test voltage held at 0 V, the input acceleration stepped
      through [0, +a, −a, 0] g (a uniform 0.5–1 g) at arbitrary times, segments 1.5–2.5 ms.
    """
    if effect not in SET_EFFECTS:
        raise ValueError(f"effect must be one of {SET_EFFECTS}, not {effect!r}")
    device = _draw_device(rng)
    device["h_max"] = REFERENCE_STOP * float(np.exp(rng.normal() * 0.03))
    device["T_dm"] = device["T_f"] = REFERENCE_LAG
    lag = None
    if effect != "none":
        lag = _log_uniform(rng, 5e-6, 5e-5)
        device["T_dm" if effect == "torquer_lag" else "T_f"] = lag
    device = {key: float(value) for key, value in device.items()}
    records = []

    u_max, levels, bounds = _draw_small_steps(rng)
    small = {"name": "small", "levels_V": levels, "change_times_s": bounds, "u_max_V": u_max}
    small.update(_draw_conventions(rng, u_max))
    small["n"] = int(round(DURATION * small["rate"]))
    records.append(small)

    u_stop = float(rng.uniform(*STOP_LEVEL))
    times, length = _segment_times(rng, 6, STOP_SEGMENT)
    stops = {
        "name": "stops",
        "levels_V": [0.0, u_stop, -u_stop, u_stop, -u_stop, 0.0],
        "change_times_s": times,
        "u_max_V": u_stop,
    }
    stops.update(_draw_conventions(rng, u_stop))
    stops["n"] = int(round(length * stops["rate"]))
    records.append(stops)

    if accel:
        a = float(rng.uniform(*ACCEL_LEVEL))
        times, length = _segment_times(rng, 4, ACCEL_SEGMENT)
        record = {
            "name": "accel",
            "levels_V": [0.0],
            "change_times_s": [],
            "accel_levels_g": [0.0, a, -a, 0.0],
            "accel_change_times_s": times,
        }
        record.update(_draw_conventions(rng, float(rng.uniform(1.5, 2.5))))
        record["n"] = int(round(length * record["rate"]))
        records.append(record)
    return {"effect": effect, "lag_s": lag, "device": device, "records": records}


def make_set(truth_set: dict, rng: np.random.Generator) -> list[dict]:
    """Simulate a drawn device set: one dict per record, {"name", "t" [s] (from 0),
    "u_test" [V], "u_out" [V], "a_in" [g] (None without an acceleration input)}."""
    d = truth_set["device"]
    device = Device(
        J=d["J"],
        mu=d["mu"],
        c=d["c"],
        k_dm=d["k_dm"],
        k_dp=d["k_dp"],
        k_y=d["k_y"],
        h_max=d["h_max"],
        T_dm=d["T_dm"],
        T_f=d["T_f"],
        test_gain=d["test_gain"],
    )
    out = []
    for r in truth_set["records"]:
        accel_levels = r.get("accel_levels_g")
        record = Record(
            levels=np.asarray(r["levels_V"], dtype=float),
            change_times=np.asarray(r["change_times_s"], dtype=float),
            rate=r["rate"],
            n=r["n"],
            moment=r["moment_Nm"],
            output_offset=r["output_offset_V"],
            output_sign=r["output_sign"],
            adc_step=r["adc_step_V"],
            noise=r["noise_V"],
            start=r["start"],
            start_level=r["start_level_V"],
            accel_levels=None if accel_levels is None else np.asarray(accel_levels, float),
            accel_change_times=(
                None if accel_levels is None else np.asarray(r["accel_change_times_s"], dtype=float)
            ),
        )
        columns = simulate(device, record, rng=rng)
        t, u, y = columns[:3]
        a_in = columns[3] if len(columns) == 4 else None
        out.append({"name": r["name"], "t": t - t[0], "u_test": u, "u_out": y, "a_in": a_in})
    return out


# --------------------------------------------------------------------------------------
# The test stand's input channel, and calibration test sequences
# --------------------------------------------------------------------------------------

INPUT_DELAY_WHOLE = (0, 1, 2)
"""Whole-sample delays of the input channel behind the output channel, one drawn (even
odds); a fractional part uniform in 0–1 sample is added with probability
`INPUT_DELAY_FRACTION_P`."""

INPUT_DELAY_FRACTION_P = 0.5
INPUT_ANTIALIAS = (0.2, 1.0)
"""Time constant of the input channel's first-order anti-alias filter [sample periods],
uniform."""

INPUT_NOISE = (3e-4, 1.5e-3)
"""White noise σ of the input channel [V], log-uniform."""

INPUT_LSB = (0.0, 6e-4)
"""ADC step of the input channel [V], uniform; none (0) with probability `INPUT_LSB_NONE_P`."""

INPUT_LSB_NONE_P = 0.2
INPUT_SPIKE_P = 0.7
"""Probability of a relay spike at each change of the input."""

INPUT_SPIKE_SAMPLES = (1, 2)
INPUT_SPIKE = (5e-3, 5e-2)
"""Spike amplitude [V], uniform, of random sign."""

INPUT_DRIFT = 5e-4
"""Linear drift of the input channel over the record [V]: uniform ±this, present with
probability `INPUT_DRIFT_P` (else 0)."""

INPUT_DRIFT_P = 0.5
INPUT_OFFSET = 2e-3
"""Offset of the input channel [V], uniform ±this."""


def measure_input(
    column,
    rate,
    rng: np.random.Generator,
    *,
    noise_V=None,
    lsb_V=None,
    delay_samples=None,
    spikes=None,
    drift_V=None,
    antialias=None,
    offset_V=None,
    change_phase=None,
):
    """(measured column, info) of what a test stand's digitiser records of the input
    channel (the test voltage, or the acceleration) beside the output channel.

    The physical input is the piecewise-constant signal whose sampled column (the level in
    force at each sample, as `simulate` returns it) is `column`, (n,). Its changes are
    taken where the column changes, at sample k_j, and placed at the exact time
    s_j = k_j − φ_j [sample periods from the first sample], φ_j ∈ [0, 1) a fraction of a
    sample (the DAC runs on its own clock, so the column cannot say when between samples
    k_j − 1 and k_j it changed; φ_j = 0: exactly at sample k_j). Before the record the
    input is taken at the first sample's level, and the filter settled there. The channel:

    1. delayed by D = `delay_samples` sample periods behind the output channel (whole part
       from `INPUT_DELAY_WHOLE`, plus a fractional part uniform 0–1 with probability
       `INPUT_DELAY_FRACTION_P`): sample k sees the input at time e_k = k − D;
    2. filtered by a first-order anti-alias low-pass of time constant τ = `antialias`
       [sample periods] (`INPUT_ANTIALIAS`; 0: none), exactly for the piecewise-constant
       input: x(e) = c_0 + Σ_{s_j ≤ e} Δ_j (1 − exp(−(e − s_j)/τ)), Δ_j the j-th change;
    3. plus relay spikes (`spikes`): at each change, with probability `INPUT_SPIKE_P`, a
       rectangular spike of 1–2 samples and amplitude uniform in `INPUT_SPIKE` of random
       sign, on the first samples at or after the delayed change, k ≥ s_j + D (a value
       added to the digitised samples, not filtered);
    4. plus an offset (`offset_V`, uniform ±`INPUT_OFFSET`), a linear drift (`drift_V`:
       0 at the first sample, drift_V at the last; uniform ±`INPUT_DRIFT` with
       probability `INPUT_DRIFT_P`, else 0) and white noise of σ `noise_V` (`INPUT_NOISE`,
       log-uniform);
    5. quantised on the grid lsb_V × integer (`INPUT_LSB`; 0: none), offset included
       (the grid is the ADC's, fixed at zero).

    Each argument None is drawn (ranges in volts: for an acceleration channel give them in
    its units). `spikes`: None (drawn), or a list of {"change": j, "samples": 1 or 2,
    "amplitude_V": a} (or (j, samples, a) tuples; [] or False: none). `change_phase`: φ,
    one for all changes or one per change (None: uniform per change). Every draw is made
    in a fixed order whatever is given (delay, filter, phases, noise σ, LSB, spikes,
    drift, offset, the noise samples), so a given value leaves the others' draws as they
    would be. `info` (JSON-able) holds the values used: delay_samples, delay_s,
    antialias_tau_samples, antialias_tau_s, change_index (k_j), change_phase (φ_j),
    noise_V, lsb_V, spikes, drift_V, offset_V, rate.
    """
    column = np.asarray(column, dtype=float)
    n = column.size
    change_index = np.flatnonzero(column[1:] != column[:-1]) + 1
    count = change_index.size

    whole = int(rng.choice(INPUT_DELAY_WHOLE))
    fraction = float(rng.uniform()) if rng.uniform() < INPUT_DELAY_FRACTION_P else 0.0
    drawn_delay = whole + fraction
    drawn_tau = float(rng.uniform(*INPUT_ANTIALIAS))
    drawn_phase = rng.uniform(size=count)
    drawn_noise = _log_uniform(rng, *INPUT_NOISE)
    drawn_lsb = 0.0 if rng.uniform() < INPUT_LSB_NONE_P else float(rng.uniform(*INPUT_LSB))
    spike_on = rng.uniform(size=count) < INPUT_SPIKE_P
    spike_samples = rng.integers(INPUT_SPIKE_SAMPLES[0], INPUT_SPIKE_SAMPLES[1] + 1, count)
    spike_amplitude = rng.uniform(*INPUT_SPIKE, count) * rng.choice([-1.0, 1.0], count)
    drift_on = rng.uniform() < INPUT_DRIFT_P
    drawn_drift = float(rng.uniform(-INPUT_DRIFT, INPUT_DRIFT)) if drift_on else 0.0
    drawn_offset = float(rng.uniform(-INPUT_OFFSET, INPUT_OFFSET))
    white = rng.normal(size=n)

    delay = drawn_delay if delay_samples is None else float(delay_samples)
    tau = drawn_tau if antialias is None else float(antialias)
    if change_phase is None:
        phase = drawn_phase
    else:
        phase = np.broadcast_to(np.asarray(change_phase, dtype=float), (count,)).copy()
    sigma = drawn_noise if noise_V is None else float(noise_V)
    lsb = drawn_lsb if lsb_V is None else float(lsb_V)
    drift = drawn_drift if drift_V is None else float(drift_V)
    offset = drawn_offset if offset_V is None else float(offset_V)
    if spikes is None:
        spike_list = [
            {"change": int(j), "samples": int(spike_samples[j]), "amplitude_V": float(a)}
            for j, a in enumerate(spike_amplitude)
            if spike_on[j]
        ]
    else:
        keys = ("change", "samples", "amplitude_V")
        items = [
            x if isinstance(x, dict) else dict(zip(keys, x, strict=True)) for x in spikes or []
        ]
        spike_list = [
            {
                "change": int(x["change"]),
                "samples": int(x["samples"]),
                "amplitude_V": float(x["amplitude_V"]),
            }
            for x in items
        ]
    if delay < 0 or tau < 0 or sigma < 0 or lsb < 0:
        raise ValueError("delay_samples, antialias, noise_V and lsb_V must be ≥ 0")
    if np.any((phase < 0) | (phase >= 1)):
        raise ValueError("change_phase must lie in [0, 1)")

    # The physical input, delayed and filtered, at e_k = k − D [sample periods].
    levels = np.concatenate([column[:1], column[change_index]])
    steps = np.diff(levels)
    s = change_index - phase
    e = np.arange(n) - delay
    x = levels[np.searchsorted(s, e, side="right")]
    if tau > 0:
        for s_j, step in zip(s, steps, strict=True):
            # exp(−50) ≈ 2e−22: beyond 50 τ the remainder is below the level's rounding.
            lo, hi = np.searchsorted(e, [s_j, s_j + 50 * tau], side="left")
            x[lo:hi] -= step * np.exp(-(e[lo:hi] - s_j) / tau)
    for spike in spike_list:
        j = spike["change"]
        if not 0 <= j < count:
            raise ValueError(f"spike at change {j}: the column has {count} changes")
        first = int(np.ceil(s[j] + delay - 1e-9))
        x[max(first, 0) : max(first + spike["samples"], 0)] += spike["amplitude_V"]
    ramp = np.arange(n) / max(n - 1, 1)
    x = x + offset + drift * ramp + sigma * white
    if lsb > 0:
        x = lsb * np.round(x / lsb)
    info = {
        "rate": float(rate),
        "delay_samples": float(delay),
        "delay_s": float(delay / rate),
        "antialias_tau_samples": float(tau),
        "antialias_tau_s": float(tau / rate),
        "change_index": [int(k) for k in change_index],
        "change_phase": [float(f) for f in phase],
        "noise_V": float(sigma),
        "lsb_V": float(lsb),
        "spikes": spike_list,
        "drift_V": float(drift),
        "offset_V": float(offset),
    }
    return x, info


def prbs_levels(
    rng: np.random.Generator,
    *,
    n_changes: int,
    duration_s: float,
    low_V: float,
    high_V: float,
    min_bit_s: float,
    max_run: int = 4,
):
    """(levels [V], change times [s]) of a random-telegraph (PRBS-like) calibration
    sequence over `duration_s` from t = 0, for `Record.levels` / `Record.change_times`.

    Two levels, `low_V` and `high_V`, alternating from a random first one; exactly
    `n_changes` changes (≥ 200 in use). Each plateau lasts m bit times T_b, m = 1, 2, ...
    drawn as a PRBS's run lengths (P(m) = 2^−m) capped at `max_run` (the cap taking the
    tail); T_b = duration_s / (Σm + 1), the sequence starting at φ T_b (φ uniform 0–1: the
    first plateau, from before the record, lasts ≥ its m T_b in the record, and the last
    one runs to the end). T_b is a real number on no sample grid, so the changes fall at
    exact off-grid times (the DAC's own clock). Raises ValueError when T_b < `min_bit_s`
    (the duration cannot hold the changes): every plateau between changes is ≥ min_bit_s.
    """
    if n_changes < 1 or max_run < 1:
        raise ValueError("n_changes and max_run must be ≥ 1")
    first_high = rng.uniform() < 0.5
    runs = np.minimum(rng.geometric(0.5, size=n_changes + 1), max_run)
    phase = float(rng.uniform())
    bit = duration_s / (runs.sum() + 1)
    if bit < min_bit_s:
        raise ValueError(
            f"bit time {bit:.3g} s < min_bit_s {min_bit_s:.3g} s: {n_changes} changes "
            f"(of {int(runs.sum())} bits) do not fit in {duration_s:.3g} s"
        )
    times = (phase + np.cumsum(runs)[:-1]) * bit
    pair = (high_V, low_V) if first_high else (low_V, high_V)
    levels = [float(pair[i % 2]) for i in range(n_changes + 1)]
    return levels, [float(x) for x in times]


def _chirp(tau, f0, f1, length, amplitude):
    """A linear sweep f0 → f1 [Hz] over `length` [s] at the times τ [s] from its start."""
    return amplitude * np.sin(2 * np.pi * (f0 * tau + 0.5 * (f1 - f0) / length * tau**2))


def sweep_column(t, f0, f1, amplitude):
    """A swept-sine (linear chirp) test-voltage column [V] at the record's times t [s]:
    amplitude · sin 2π(f0 τ + (f1 − f0) τ²/(2T)), τ = t − t[0], T = t[−1] − t[0]; the
    frequency runs from f0 [Hz] at the first sample to f1 [Hz] at the last. An input with
    no plateaus (for a diagnosis that must refuse it)."""
    t = np.asarray(t, dtype=float)
    tau = t - t[0]
    return _chirp(tau, f0, f1, max(float(tau[-1]), 1e-300), amplitude)


def sweep_levels(f0, f1, amplitude, duration_s, dac_rate, *, dac_phase=0.0):
    """(levels [V], change times [s]) of the same sweep as `sweep_column` over
    `duration_s` from t = 0, as a DAC updating at `dac_rate` [Hz] would put it out (a
    zero-order hold of the chirp at its update times (k + dac_phase)/dac_rate, k ≥ 1,
    dac_phase in [0, 1); level 0 from before t = 0), so that `simulate` can drive the
    loop with it. Each update is a change (many pieces: keep dac_rate × duration to a few
    thousand)."""
    ticks = np.arange(1, int(np.floor(duration_s * dac_rate - dac_phase)) + 1) + dac_phase
    times = ticks / dac_rate
    times = times[times < duration_s]
    levels = np.concatenate([[0.0], _chirp(times, f0, f1, duration_s, amplitude)])
    return [float(x) for x in levels], [float(x) for x in times]
