"""An independent truth simulator of closed-loop test-signal records (SciPy, not JAX).

Written from the equations of SPEC.md §1 with none of the library's code: its own state
equations, SciPy's `solve_ivp` (DOP853) integrating between events, and its own handling
of the mechanical stops as exact events. The blind validation uses it so that the
diagnosis is checked on records made with other conventions than its own:

- the test voltage changes at arbitrary times between samples (a DAC on its own clock),
  and the `u_test` column is that voltage *sampled* at the record's times;
- the test winding may be wired with either polarity, and its gain differs from the
  feedback winding's;
- the record starts wherever the recorder was started: at rest, or in the middle of the
  transient of an earlier change (a test sequence already running);
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
stops, acceleration steps) for the multi-record diagnosis.
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
    the time [s] before t0 at which the first level was switched on from `start_level`.
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
    y_out = rec.output_sign * clean + rec.output_offset
    if rec.noise > 0:
        y_out = y_out + rng.normal(size=rec.n) * rec.noise
    sigma, tau = rec.gm
    if sigma > 0:
        phi = np.exp(-1 / (rec.rate * tau))
        w = rng.normal(size=rec.n) * sigma * np.sqrt(1 - phi**2)
        w[0] = rng.normal() * sigma  # stationary from the first sample
        y_out = y_out + lfilter([1.0], [1.0, -phi], w)
    if rec.adc_step > 0:
        y_out = rec.adc_step * np.round(y_out / rec.adc_step)
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


def make(truth: dict, rng: np.random.Generator):
    """Simulate one drawn world: (t, u_test column, u_out column, noise component) [s, V]."""
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
    record = Record(
        levels=np.asarray(truth["levels_V"]),
        change_times=np.asarray(truth["change_times_s"]),
        rate=rate,
        n=n,
        moment=truth["moment_Nm"],
        output_offset=truth["output_offset_V"],
        output_sign=truth["output_sign"],
        adc_step=truth["adc_step_V"],
        noise=truth["noise_V"],
        start=truth["start"],
        start_level=truth["start_level_V"],
    )
    if effect == "torquer_lag":
        device.T_dm = truth["lag_s"]
    elif effect == "output_filter":
        device.T_f = truth["lag_s"]
    elif effect == "stop_saturation":
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


# --------------------------------------------------------------------------------------
# Device sets for the multi-record diagnosis: one device, several records
# --------------------------------------------------------------------------------------

SET_EFFECTS = ("none", "torquer_lag", "output_filter")
"""The effects of a device set: none (both lags at the reference's 10 µs) or one lag
replaced by a drawn value."""

REFERENCE_LAG = 1e-5
"""T_dm = T_f [s] of the reference device: every set's baseline."""

REFERENCE_STOP = 1.9e-6
"""h_max [m] of the reference device (SPEC.md §1); a set's device draws it × e^{N(0, 0.03)}."""

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
