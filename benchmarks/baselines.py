"""The baselines a user would write without accel_jax: NumPy/SciPy, one trajectory at a time.

Everything here is plain float64 NumPy/SciPy (python-control where named), written from the
model equations of `accel_jax.ServoParams` — not from accel_jax's code — so that the
benchmark also cross-checks the numbers.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.integrate
import scipy.signal

# --------------------------------------------------------------------------------------
# The linear loop, state [θ, θ', M_dm, U_f], input U_test (T_dm > 0, T_f > 0)


def state_space(v: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(A, B, C, D) of the loop for the input U_test [V] (SI units), from the equations
    J θ'' + μ θ' + c θ = M_ext + M_dm, T_dm M_dm' = k_dm (U_test − g θ) − M_dm,
    T_f U_f' = g θ − U_f, g = k_dp k_y l."""
    g = v["pickoff_gain"] * v["amplifier_gain"] * v["pendulum_length"]
    inertia, tdm, tf = v["moment_of_inertia"], v["torquer_time_constant"], v["filter_time_constant"]
    a = np.array(
        [
            [0.0, 1.0, 0.0, 0.0],
            [-v["stiffness"] / inertia, -v["damping"] / inertia, 1 / inertia, 0.0],
            [-v["torquer_gain"] * g / tdm, 0.0, -1 / tdm, 0.0],
            [g / tf, 0.0, 0.0, -1 / tf],
        ]
    )
    b = np.array([[0.0], [0.0], [v["torquer_gain"] / tdm], [0.0]])
    c = np.array([[0.0, 0.0, 0.0, 1.0]])
    d = np.zeros((1, 1))
    return a, b, c, d


def settled_output(v: dict) -> float:
    """U_out of the settled device at U_test = 0 under the constant M_ext [V]."""
    g = v["pickoff_gain"] * v["amplifier_gain"] * v["pendulum_length"]
    stiffness = v["stiffness"] + v["torquer_gain"] * g
    return g * v["external_moment"] / stiffness


def identify_oscillatory(ts, y, gain, gamma, tail_fraction=0.2):
    """The paper's oscillatory method in vectorised NumPy: U_ss and σ from the tail,
    crossings of U_ss with hysteresis (band 6σ + 1e-6 step), linear interpolation between
    the bracketing samples, A1/A2 the largest samples, eqs. (7)-(10). Returns K̂_a or NaN."""
    n = y.shape[0]
    n_tail = max(4, int(round(tail_fraction * n)))
    tail = y[n - n_tail :]
    steady, sigma = tail.mean(), tail.std()
    step = steady - y[0]
    d = math.copysign(1.0, step) * (y - steady)
    band = 6 * sigma + 1e-6 * abs(step)
    label = np.where(d > band, 1, np.where(d < -band, -1, 0))
    label[0] = -1
    label[n - n_tail :] = 0
    labelled = np.flatnonzero(label)
    states = label[labelled]
    changes = np.flatnonzero(states[1:] != states[:-1])
    if changes.size < 3:
        return math.nan
    times = []
    for c in changes[:3]:
        a, k = labelled[c], labelled[c + 1]
        segment = d[a : k + 1]
        j = a + np.flatnonzero(np.signbit(segment[1:]) != np.signbit(segment[:-1]))[0]
        times.append(ts[j] - d[j] * (ts[j + 1] - ts[j]) / (d[j + 1] - d[j]))
    t1, t_mid, t2 = times
    overshoot = d[(ts > t1) & (ts < t_mid)].max()
    undershoot = (-d[(ts > t_mid) & (ts < t2)]).max()
    log_decrement = math.log(overshoot / undershoot)
    damping = log_decrement / math.hypot(log_decrement, math.pi)
    time_constant = math.sqrt(1 - damping**2) * (t2 - t1) / (2 * math.pi)
    return gamma * time_constant**2 * gain


def record_lfilter(v: dict, ts: np.ndarray, test_voltage: float) -> np.ndarray:
    """Exact ZOH (`cont2discrete`), then `lfilter` of the step: the fastest SciPy loop."""
    dt = ts[1] - ts[0]
    ad, bd, cd, dd, _ = scipy.signal.cont2discrete(state_space(v), dt, method="zoh")
    numerator, denominator = scipy.signal.ss2tf(ad, bd, cd, dd)
    step = np.full(ts.shape[0], test_voltage)
    return settled_output(v) + scipy.signal.lfilter(numerator[0], denominator, step)


def record_lsim(v: dict, ts: np.ndarray, test_voltage: float) -> np.ndarray:
    step = np.full(ts.shape[0], test_voltage)
    _, y, _ = scipy.signal.lsim(state_space(v), step, ts)
    return settled_output(v) + y


def record_control(v: dict, ts: np.ndarray, test_voltage: float) -> np.ndarray:
    import control

    system = control.ss(*state_space(v))
    step = np.full(ts.shape[0], test_voltage)
    response = control.forced_response(system, T=ts, U=step)
    return settled_output(v) + np.asarray(response.outputs).reshape(-1)


def monte_carlo(record, devices: list[dict], ts, test_voltage, gains, gammas, seed):
    """δ-free loop: K̂_a per trajectory from `record(v, ts, U)` plus N(0, ε²) noise."""
    rng = np.random.default_rng(seed)
    out = np.empty(len(devices))
    for i, v in enumerate(devices):
        y = record(v, ts, test_voltage) + v["noise_std"] * rng.standard_normal(ts.shape[0])
        out[i] = identify_oscillatory(ts, y, gains[i], gammas[i])
    return out


# --------------------------------------------------------------------------------------
# The loop with the mechanical stops, solve_ivp, in the same O(1) units as accel_jax


def nonlinear_record(v: dict, ts, test_voltage, rtol, atol, stop_stiffness_ratio=1e4):
    """U_out with the stops by `solve_ivp` (RK45), state scaled to θ_max, θ_max/T, K θ_max,
    volts (so rtol/atol mean what they mean for `accel_jax.simulate_nonlinear`); the stop is
    the same spring–dashpot contact, K_s = r K, D_s = 2√(K_s J)."""
    a, b, _, _ = state_space(v)
    g = v["pickoff_gain"] * v["amplifier_gain"] * v["pendulum_length"]
    stiffness = v["stiffness"] + v["torquer_gain"] * g
    period = math.sqrt(v["moment_of_inertia"] / stiffness)
    theta_max = v["stop_displacement"] / v["pendulum_length"]
    scale = np.array([theta_max, theta_max / period, stiffness * theta_max, 1.0])
    a_scaled = a * scale[None, :] / scale[:, None]
    drive = (
        b[:, 0] * test_voltage + np.array([0, v["external_moment"] / v["moment_of_inertia"], 0, 0])
    ) / scale
    rate = stop_stiffness_ratio / period
    damping = 2 * math.sqrt(stop_stiffness_ratio) / period

    def rhs(t, y):
        dy = a_scaled @ y + drive
        above, below = y[0] - 1, -1 - y[0]
        if above > 0 or below > 0:
            dy[1] -= rate * (max(above, 0.0) - max(below, 0.0)) + damping * y[1]
        return dy

    theta0 = v["external_moment"] / stiffness
    y0 = np.array([theta0, 0.0, -v["torquer_gain"] * g * theta0, g * theta0]) / scale
    solution = scipy.integrate.solve_ivp(
        rhs, (ts[0], ts[-1]), y0, method="RK45", t_eval=ts, rtol=rtol, atol=atol
    )
    return solution.y[3], solution.nfev


# --------------------------------------------------------------------------------------
# Exact vibration error (docs/models.md §3) in NumPy, the same quadrature as accel_jax


def vibration_error(coefficients: dict, environment: dict, a3: float, n_phase=512, n_hermite=6):
    """δ_V [g] for arrays of coefficient sets (leading axis) under one environment: the
    polynomial part by phases × Gauss–Hermite nodes, |a3| by the folded normal, the
    cross terms by second moments (a1 = a2 = 0)."""
    from scipy.special import erf

    k = {name: np.asarray(value)[:, None, None] for name, value in coefficients.items()}
    b, phi, sigma = (
        np.asarray(environment[n]) for n in ("sine_amplitude", "sine_phase", "random_std")
    )
    rho = np.asarray(environment["random_correlation"])
    theta = 2 * np.pi * np.arange(n_phase) / n_phase
    nodes, weights = np.polynomial.hermite_e.hermegauss(n_hermite)
    weights = weights / weights.sum()
    x = a3 + b[2] * np.sin(theta + phi[2])[:, None] + sigma[2] * nodes[None, :]
    poly = k["k2"] * x**2 + k["k3"] * x**3 + k["k4"] * x**4 + k["k5"] * x**5
    poly_mean = (poly * weights).sum(-1).mean(-1)
    mu = a3 + b[2] * np.sin(theta + phi[2])
    if sigma[2] > 0:
        s = sigma[2]
        mean_abs = np.mean(
            s * math.sqrt(2 / math.pi) * np.exp(-0.5 * (mu / s) ** 2)
            + mu * erf(mu / (s * math.sqrt(2)))
        )
    else:
        mean_abs = np.mean(np.abs(mu))
    cross1 = 0.5 * b[2] * b[0] * math.cos(phi[2] - phi[0]) + rho[2, 0] * sigma[2] * sigma[0]
    cross2 = 0.5 * b[2] * b[1] * math.cos(phi[2] - phi[1]) + rho[2, 1] * sigma[2] * sigma[1]
    c = {name: np.asarray(value) for name, value in coefficients.items()}
    static_poly = c["k2"] * a3**2 + c["k3"] * a3**3 + c["k4"] * a3**4 + c["k5"] * a3**5
    return (
        0.5 * c["asymmetry"] * (mean_abs - abs(a3))
        + poly_mean
        - static_poly
        + c["m31"] * cross1
        + c["m32"] * cross2
    )
