"""Independent truth simulator of a single-channel INS error model (Schuler loop, velocity aiding).

What it simulates (SI units throughout, float64):

    dΔV/dt = −g δ + Δa            ΔV velocity error [m/s], g = 9.80665 m/s²
    dδ/dt  = ΔV/R + Δω            δ tilt (vertical) error [rad], R the Earth's radius [m]
    dΔa    = −Δa/τ_a dt + σ_a √(2/τ_a) dW_a        accelerometer error [m/s²], Gauss–Markov
    Δω     = gyro drift [rad/s], either Gauss–Markov (σ_ω, τ_ω) like Δa, or exponential-cosine
             with R(τ) = σ² e^{−α|τ|} cos βτ, realised as the output of the shaping filter
             σ√(2α)(p + b)/(p² + 2αp + b²), b² = α² + β², driven by unit white noise, in
             controllable canonical form: ξ₁' = ξ₂, ξ₂' = −b²ξ₁ − 2αξ₂ + σ√(2α) w,
             Δω = b ξ₁ + ξ₂.
    z_k    = s ΔV(t_k) + v_k,  v_k ~ N(0, σ_v²), t_k = k dt, k = 0 … T−1.

Method: the 4-state (Gauss–Markov gyro) or 5-state (exponential-cosine gyro) linear SDE
dx = A x dt + G dW is discretised exactly over one sample interval by Van Loan's method
(`scipy.linalg.expm` of [[−A, GGᵀ], [0, Aᵀ]] dt gives Φ = e^{A dt} and the process-noise
covariance Q_d = ∫₀^dt e^{As} GGᵀ e^{Aᵀs} ds); x_{k+1} = Φ x_k + L e_k with L Lᵀ = Q_d
(a symmetric square root, computed on the diagonally rescaled Q_d) and e_k ~ N(0, I) from a
NumPy Generator. Stationary sensor states are drawn from the Lyapunov solution
(`scipy.linalg.solve_continuous_lyapunov`).

Conventions randomised per log (when `conventions=None`), drawn from the log's Generator:
the observation sign s (+1: INS minus reference, −1: reference minus INS), the radius
R ∈ {6 371 000, 6 378 137} m, and the start: "prior" (ΔV ~ N(0, 0.1²), δ ~ N(0, (1e-4)²))
or "offset" (ΔV = 0.3 m/s, δ = 2e-4 rad); the sensors start stationary in both.

This module shares no code with `accel_jax`: NumPy and SciPy only, written from the
physics above.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import expm, solve_continuous_lyapunov

GRAVITY = 9.80665  # m/s²
RADII = (6_371_000.0, 6_378_137.0)  # m: mean radius; WGS-84 equatorial radius


def gyro_block(gyro: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(A, G, C) of the gyro drift's shaping filter: dξ = Aξ dt + G dW, Δω = C ξ [rad/s].

    `gyro`: dict(kind="gauss_markov", sigma=σ [rad/s], correlation_time=τ [s]) or
    dict(kind="exp_cosine", sigma=σ [rad/s], alpha=α [1/s], beta=β [rad/s]).
    """
    kind = gyro["kind"]
    sigma = float(gyro["sigma"])
    if kind == "gauss_markov":
        tau = float(gyro["correlation_time"])
        return (np.array([[-1.0 / tau]]), np.array([[sigma * np.sqrt(2.0 / tau)]]),
                np.array([1.0]))
    if kind == "exp_cosine":
        alpha, beta = float(gyro["alpha"]), float(gyro["beta"])
        b2 = alpha**2 + beta**2
        a = np.array([[0.0, 1.0], [-b2, -2.0 * alpha]])
        g = np.array([[0.0], [sigma * np.sqrt(2.0 * alpha)]])
        return a, g, np.array([np.sqrt(b2), 1.0])
    raise ValueError(f"unknown gyro kind {kind!r}")


def ins_system(accel: tuple[float, float], gyro: dict, radius: float,
               gravity: float = GRAVITY) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(A, G, C_ω) of the full state x = [ΔV, δ, Δa, ξ…]; Δω = C_ω x.

    `accel` = (σ_a [m/s²], τ_a [s]); white-noise inputs W = [W_a, W_ω] of unit intensity.
    """
    sigma_a, tau_a = accel
    ag, gg, cg = gyro_block(gyro)
    m = ag.shape[0]
    n = 3 + m
    a = np.zeros((n, n))
    c_omega = np.zeros(n)
    c_omega[3:] = cg
    a[0, 1] = -gravity
    a[0, 2] = 1.0
    a[1, 0] = 1.0 / radius
    a[1, :] += c_omega  # dδ/dt gets Δω = C ξ
    a[2, 2] = -1.0 / tau_a
    a[3:, 3:] = ag
    g = np.zeros((n, 2))
    g[2, 0] = sigma_a * np.sqrt(2.0 / tau_a)
    g[3:, 1:] = gg
    return a, g, c_omega


def discretise(a: np.ndarray, g: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact (Φ, Q_d) of dx = A x dt + G dW over dt, by Van Loan's matrix exponential."""
    n = a.shape[0]
    m = np.zeros((2 * n, 2 * n))
    m[:n, :n] = -a
    m[:n, n:] = g @ g.T
    m[n:, n:] = a.T
    e = expm(m * dt)
    phi = e[n:, n:].T
    q = phi @ e[:n, n:]
    return phi, 0.5 * (q + q.T)


def noise_root(q: np.ndarray) -> np.ndarray:
    """L with L Lᵀ = Q (Q symmetric positive semi-definite, badly scaled): eigen-root of
    the diagonally rescaled Q, negative round-off eigenvalues clipped to zero."""
    d = np.sqrt(np.clip(np.diag(q), 1e-300, None))
    w, v = np.linalg.eigh(q / np.outer(d, d))
    return d[:, None] * v * np.sqrt(np.clip(w, 0.0, None))


def stationary_covariance(a: np.ndarray, g: np.ndarray) -> np.ndarray:
    """P∞ solving A P + P Aᵀ + G Gᵀ = 0 (A stable)."""
    p = solve_continuous_lyapunov(a, -g @ g.T)
    return 0.5 * (p + p.T)


def propagate(rng: np.random.Generator, phi: np.ndarray, q: np.ndarray, x0: np.ndarray,
              n_steps: int) -> np.ndarray:
    """States x_0 … x_{n−1} of x_{k+1} = Φ x_k + L e_k; x0 of shape (n,) or (paths, n).
    Returns shape (n_steps, n) or (n_steps, paths, n)."""
    x0 = np.asarray(x0, dtype=np.float64)
    lt = noise_root(q).T
    out = np.empty((n_steps, *x0.shape))
    x = x0.copy()
    phi_t = phi.T
    for k in range(n_steps):
        out[k] = x
        x = x @ phi_t + rng.standard_normal(x0.shape) @ lt
    return out


def draw_conventions(rng: np.random.Generator) -> dict:
    """Sign s ∈ {+1, −1}, radius R ∈ RADII [m], start ∈ {"prior", "offset"}."""
    return dict(sign=float(rng.choice([1.0, -1.0])), radius=float(rng.choice(RADII)),
                start=str(rng.choice(["prior", "offset"])))


def simulate_log(rng: np.random.Generator, hours: float, *, dt: float = 1.0,
                 accel: tuple[float, float] = (1e-3, 600.0),
                 gyro: dict | None = None, velocity_noise: float = 0.1,
                 conventions: dict | None = None) -> dict:
    """One velocity-aided INS log.

    **Arguments:** `rng` a NumPy Generator; `hours` the log's length (T = hours·3600/dt
    samples); `dt` the sample interval [s]; `accel` = (σ_a [m/s²], τ_a [s]); `gyro` as in
    `gyro_block` (default: exponential-cosine σ = 5e-8 rad/s, α = 1/3600 1/s,
    β = 2.5/3600 rad/s); `velocity_noise` σ_v [m/s]; `conventions` dict(sign, radius,
    start) or None to draw them from `rng`.

    **Returns:** dict with `z` (T,) [m/s], `states` (T, 4) = [ΔV m/s, δ rad, Δa m/s²,
    Δω rad/s] at t_k = k dt, `conventions`, `time` (T,) [s].
    """
    if gyro is None:
        gyro = dict(kind="exp_cosine", sigma=5e-8, alpha=1 / 3600, beta=2.5 / 3600)
    conv = draw_conventions(rng) if conventions is None else dict(conventions)
    n_steps = int(round(hours * 3600.0 / dt))
    a, g, c_omega = ins_system(accel, gyro, conv["radius"])
    n = a.shape[0]
    # The sensors' stationary covariance (the kinematic states are not stationary).
    p_sens = stationary_covariance(a[2:, 2:], g[2:])
    x0 = np.zeros(n)
    x0[2:] = noise_root(p_sens) @ rng.standard_normal(n - 2)
    if conv["start"] == "prior":
        x0[0], x0[1] = 0.1 * rng.standard_normal(), 1e-4 * rng.standard_normal()
    elif conv["start"] == "offset":
        x0[0], x0[1] = 0.3, 2e-4
    else:
        raise ValueError(f"unknown start {conv['start']!r}")
    phi, q = discretise(a, g, dt)
    x = propagate(rng, phi, q, x0, n_steps)
    states = np.column_stack([x[:, 0], x[:, 1], x[:, 2], x @ c_omega])
    z = conv["sign"] * states[:, 0] + velocity_noise * rng.standard_normal(n_steps)
    return dict(z=z, states=states, conventions=conv, time=np.arange(n_steps) * dt)
