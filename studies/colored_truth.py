"""An independent truth simulator of step records with coloured noise, at the output and
inside the loop (NumPy/SciPy, not JAX).

Written from the loop equations of docs/models.md §1 (as `step_truth.py` is) without
reading the library's effect code (its diagnosis, noise, simulation or estimation
modules): it imports only `step_truth`, whose world (the drawn device, test sequence and
recorder conventions, `Device`, `Record` and the output's noise and ADC handling,
`step_truth.recorded`) it reuses. It is a test bench for the step-record diagnosis's
coloured-noise verdicts.

Loop (SI units; θ the pendulum's angle, M_0 a constant external moment, M_n the moment
noise), linear: no stops, no pickoff nonlinearity, no input acceleration:

    J θ'' + μ θ' + c θ = M_dm + M_0 + M_n(t)
    T_dm M_dm' = k_dm (g_w U_test(t) − U_amp) − M_dm      (M_dm algebraic when T_dm = 0)
    U_amp = k_dp k_y l θ
    T_f U_f' = U_amp − U_f,  U_out = U_f                  (U_out = U_amp when T_f = 0)
    dM_n = −M_n/τ_M dt + √(2 σ_M²/τ_M) dW                 (stationary Gauss–Markov moment)

The recorded sample k (step_truth's conventions):

    y_k = s · U_out(t_k) + offset + n_white,k + n_gm,k,  then quantised: q · round(y/q)

with s = `Record.output_sign`, offset = `Record.output_offset`, n_white white of σ
`Record.noise`, n_gm a stationary first-order Gauss–Markov output noise of (σ_gm, τ_gm),
q = `Record.adc_step` (0: none). The moment noise enters the loop and is filtered by it
(its output part is multiplied by s like the rest of U_out); the output noise is not.

The exact discretisation. The state x = (θ, θ', [M_dm], [U_f], M_n) (M_dm only when
T_dm > 0, U_f only when T_f > 0) obeys dx = (A x + b(u)) dt + G dW, b(u) the test voltage's
and M_0's forcing (constant while the test voltage is), G = √(2σ_M²/τ_M) e_{M_n}. The
propagation steps from event to event: the samples t_k = t0 + k/rate and, between them,
the test voltage's changes (the DAC runs on its own clock, so they fall between samples).
Over a step of length h under the level u:

    x ← x_eq + Φ(h) (x − x_eq) + w,   Φ(h) = expm(A h),  x_eq = −A⁻¹ b(u),
    w ~ N(0, Q(h)),  Q(h) = ∫₀ʰ e^{As} G Gᵀ e^{Aᵀs} ds

with Φ = expm(A h) and Q by Van Loan's method: expm([[−A, G Gᵀ], [0, Aᵀ]] h') =
[[·, F12], [0, F22]], Φ(h') = F22ᵀ, Q(h') = Φ(h') F12, on h' = h/2^m small enough that
‖A‖ h' ≤ 1/2 (the block's e^{−A h'} would otherwise swamp the rest: a long step, or a
τ_M far below the sample period), then doubled m times, Q(2h') = Q(h') + Φ(h') Q(h')
Φ(h')ᵀ (m = 0 for the drawn records' steps). The start's transient before t0 (no noise)
uses expm(A h) alone. w is drawn as L z, z standard normal, L = V diag(√max(λ, 0)) from
the eigen-decomposition Q = V diag(λ) Vᵀ (Q is positive definite in exact arithmetic but
very ill-conditioned: its angle part grows as h⁵; the clipping guards the rounding). The
computation runs in scaled units (θ in 1/(k_dp k_y l) rad, i.e. 1 V at the pickoff; θ' in
that over the loop time √(J/C); the moments in C times that angle; U_f in V; C = c + k_dm
k_dp k_y l the loop's stiffness), where A's entries are all of order 1/(time constant).
The noise-free state follows the same recursion with w = 0 (propagated alongside, for the
clean record and the noise component); so the recorded output is exact in distribution,
not an integration of the SDE.

The stationary start. At t0 the state is the deterministic part plus a draw from the
stationary distribution of the noise part, N(0, P), P the joint stationary covariance of
the loop's states and M_n: the solution of the continuous Lyapunov equation
A P + P Aᵀ + G Gᵀ = 0 (`scipy.linalg.solve_continuous_lyapunov`), drawn with the same
clipped eigen-factor. The deterministic part is step_truth's start: at rest under the
first level at t0 ("rest"), or (a number) at rest under `start_level` that long before t0
with the sequence's levels from then on (the noise, stationary, has run forever). So the
record has no start-up transient of its noise. The output's moment-noise variance is
H P Hᵀ (H the output row), linear in σ_M²: `draw_truth` chooses σ_M so that its standard
deviation is the drawn ratio × the record's white σ (`moment_sigma_for_output_std`).

The output Gauss–Markov noise is step_truth's (`step_truth.recorded` with `Record.gm`):
an AR(1) sampled exactly, n_gm,0 ~ N(0, σ²), n_gm,k = φ n_gm,k−1 + √(1 − φ²) σ ε_k,
φ = exp(−1/(rate τ)) — checked exact (the stationary start and the exact AR(1) of a
first-order Gauss–Markov process sampled at the record's interval).

Draw order of `simulate`'s rng: the moment noise first (only when σ_M > 0: the start's
dim(x) normals, then dim(x) normals per propagation step, in time order), then
step_truth.recorded's (the white noise, then the output Gauss–Markov noise). With σ_M = 0
the rng is used as step_truth.simulate uses it, so the same seed gives its record.

The drawn records (`draw_truth`, `make`): the device, the small-step test sequence and the
recorder conventions exactly as `step_truth.draw_truth(rng, "none")` draws them (the same
draws in the same order: the sample rate 0.5–2 MHz, the white σ, the ADC step, the output
offset and sign, the constant moment M_0, the start — at rest, or in the transient of an
earlier level —, the test winding's signed gain, the off-grid change times), T_dm = T_f = 0
(step_truth's "none" world has no lags), then the coloured noise of the class
(`CLASSES`): "none"; "output_gm", σ_gm / σ_white log-uniform in `RATIO`, τ_gm log-uniform
in [3 samples, DURATION/20]; "moment_gm", the output std of the moment noise over σ_white
log-uniform in `RATIO`, τ_M in the same range. The two draws are made for every class
(in that order), so the world and the rng's state after `draw_truth` do not depend on it.

Everything is float64 NumPy/SciPy.
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np
from scipy.linalg import expm, solve_continuous_lyapunov

sys.path.insert(0, str(Path(__file__).resolve().parent))
import step_truth  # noqa: E402

CLASSES = ("none", "output_gm", "moment_gm")
"""The record classes: no coloured noise, a Gauss–Markov output noise, a Gauss–Markov
moment noise inside the loop."""

RATIO = (1.0, 20.0)
"""The coloured noise's standard deviation at the output over the white σ, log-uniform: σ_gm
/ σ_white for "output_gm", the std of U_out's moment-noise part / σ_white for
"moment_gm"."""

TAU_SAMPLES_MIN = 3.0
"""The shortest correlation time τ, in sample periods of the record."""

TAU_MAX = step_truth.DURATION / 20
"""The longest correlation time τ [s] (600 µs: the record holds 20 of them)."""


# --------------------------------------------------------------------------------------
# The linear loop with the moment noise as a state
# --------------------------------------------------------------------------------------


def _check(device: step_truth.Device, rec: step_truth.Record | None = None):
    if np.isfinite(device.h_max):
        raise ValueError("colored_truth models no stops (h_max must be inf)")
    if device.pickoff_p2 or device.pickoff_p3:
        raise ValueError("colored_truth models no pickoff nonlinearity")
    if device.T_dm < 0 or device.T_f < 0:
        raise ValueError("T_dm and T_f must be ≥ 0")
    if rec is None:
        return
    if rec.bandpass is not None or rec.accel_levels is not None or any(rec.vibration):
        raise ValueError("colored_truth models no band-pass sensor or input acceleration")
    if rec.moment_rate:
        raise ValueError("colored_truth models a constant moment only (moment_rate 0)")
    if isinstance(rec.start, str) and rec.start != "rest":
        raise ValueError(f"start {rec.start!r}: colored_truth has no stops")


class _Model:
    """The augmented linear system in scaled units (see the module docstring): z = S⁻¹ x,
    x = (θ, θ', [M_dm], [U_f], M_n) the physical state."""

    def __init__(self, d: step_truth.Device, tau_m: float):
        if not tau_m > 0:
            raise ValueError("the moment noise's τ_M must be > 0")
        self.d = d
        self.tau_m = float(tau_m)
        gain = d.k_dp * d.k_y * d.l  # V/rad
        self.gain = gain
        self.k_loop = d.c + d.k_dm * gain  # N·m/rad
        self.loop_time = np.sqrt(d.J / self.k_loop)
        names = ["theta", "theta_rate"]
        if d.T_dm > 0:
            names.append("M_dm")
        if d.T_f > 0:
            names.append("U_f")
        names.append("M_n")
        self.names = names
        i = {name: k for k, name in enumerate(names)}
        self.index = i
        n = len(names)
        a = np.zeros((n, n))
        b_u = np.zeros(n)  # forcing per test volt
        b_m = np.zeros(n)  # forcing per N·m of M_0
        a[i["theta"], i["theta_rate"]] = 1.0
        w = i["theta_rate"]
        a[w, i["theta"]] = -d.c / d.J
        a[w, w] = -d.mu / d.J
        a[w, i["M_n"]] = 1.0 / d.J
        b_m[w] = 1.0 / d.J
        if d.T_dm > 0:
            m = i["M_dm"]
            a[w, m] = 1.0 / d.J
            a[m, i["theta"]] = -d.k_dm * gain / d.T_dm
            a[m, m] = -1.0 / d.T_dm
            b_u[m] = d.k_dm * d.test_gain / d.T_dm
        else:
            a[w, i["theta"]] -= d.k_dm * gain / d.J
            b_u[w] = d.k_dm * d.test_gain / d.J
        if d.T_f > 0:
            f = i["U_f"]
            a[f, i["theta"]] = gain / d.T_f
            a[f, f] = -1.0 / d.T_f
        a[i["M_n"], i["M_n"]] = -1.0 / self.tau_m
        h = np.zeros(n)
        if d.T_f > 0:
            h[i["U_f"]] = 1.0
        else:
            h[i["theta"]] = gain
        # Scales: 1 V at the pickoff, its rate over the loop time, C times it, 1 V.
        theta_s = 1.0 / gain
        moment_s = self.k_loop * theta_s
        scale = {
            "theta": theta_s,
            "theta_rate": theta_s / self.loop_time,
            "M_dm": moment_s,
            "U_f": 1.0,
            "M_n": moment_s,
        }
        self.scale = np.array([scale[name] for name in names])
        s = self.scale
        self.A_phys, self.H_phys = a, h
        self.A = a * (1.0 / s)[:, None] * s[None, :]
        self.b_u = b_u / s
        self.b_m = b_m / s
        self.H = h * s
        self.A_inv = np.linalg.inv(self.A)
        # The noise input per unit σ_M [N·m]: √(2/τ_M) on M_n, scaled.
        self.g_unit = np.zeros(n)
        self.g_unit[i["M_n"]] = np.sqrt(2.0 / self.tau_m) / s[i["M_n"]]
        gg = np.outer(self.g_unit, self.g_unit)
        self.P_unit = solve_continuous_lyapunov(self.A, -gg)
        self.P_unit = 0.5 * (self.P_unit + self.P_unit.T)
        self._gg = gg
        self._steps = {}
        self._transitions = {}
        self._rest = {}

    def equilibrium(self, u, moment):
        """The rest state (scaled) under the test voltage u and the moment M_0 (M_n = 0)."""
        key = (float(u), float(moment))
        if key not in self._rest:
            if len(self._rest) >= self.CACHE:
                self._rest.clear()
            self._rest[key] = -self.A_inv @ (self.b_u * u + self.b_m * moment)
        return self._rest[key]

    CACHE = 512
    """The most transitions (and process-noise factors) kept per model: the sample period's
    and the pieces of the sample intervals split by a change (cleared when full)."""

    def transition(self, h):
        """Φ(h) = expm(A h) (scaled)."""
        key = float(h)
        if key not in self._transitions:
            if len(self._transitions) >= self.CACHE:
                self._transitions.clear()
            self._transitions[key] = expm(self.A * h)
        return self._transitions[key]

    def step(self, h):
        """(Φ(h), L(h)): the transition and the factor of the process noise's covariance
        for unit σ_M (scaled; L Lᵀ = Q(h)); cached by h. Q by Van Loan's method on
        h' = h / 2^m, m the least with ‖A‖ h' ≤ 1/2 (so that the block exponential's
        e^{−A h'} stays of order 1), then doubled m times: Q(2h') = Q(h') + Φ(h') Q(h')
        Φ(h')ᵀ."""
        key = float(h)
        if key not in self._steps:
            if len(self._steps) >= self.CACHE:
                self._steps.clear()
            n = self.A.shape[0]
            norm = np.linalg.norm(self.A, 1) * h
            m = max(0, int(np.ceil(np.log2(norm / 0.5)))) if norm > 0.5 else 0
            small = h / 2**m
            block = np.zeros((2 * n, 2 * n))
            block[:n, :n] = -self.A
            block[:n, n:] = self._gg
            block[n:, n:] = self.A.T
            f = expm(block * small)
            phi = f[n:, n:].T
            q = phi @ f[:n, n:]
            for _ in range(m):
                q = q + phi @ q @ phi.T
                phi = phi @ phi
            q = 0.5 * (q + q.T)
            self._steps[key] = (self.transition(h), _factor(q), q)
        phi, factor, _ = self._steps[key]
        return phi, factor

    def process_cov(self, h):
        """Q(h) for unit σ_M (scaled)."""
        self.step(h)
        return self._steps[float(h)][2]

    def output_var_unit(self):
        """The stationary variance [V²] of U_out's moment-noise part for σ_M = 1 N·m."""
        return float(self.H @ self.P_unit @ self.H)


_MODELS: dict = {}
"""The last few `_Model`s, by the device's values and τ_M (a many-record study rebuilds
none: the Lyapunov solution and the sample period's Van Loan step are made once)."""


def _model(device: step_truth.Device, tau_m: float) -> _Model:
    key = (dataclasses.astuple(device), float(tau_m))
    if key not in _MODELS:
        if len(_MODELS) >= 8:
            _MODELS.pop(next(iter(_MODELS)))
        _MODELS[key] = _Model(device, tau_m)
    return _MODELS[key]


def _factor(cov):
    """L with L Lᵀ = cov (symmetrised), from eigh with negative eigenvalues clipped to 0:
    a factor of a positive semi-definite (or rounding-indefinite) covariance."""
    cov = 0.5 * (cov + cov.T)
    values, vectors = np.linalg.eigh(cov)
    return vectors * np.sqrt(np.clip(values, 0.0, None))[None, :]


def moment_noise_model(device: step_truth.Device, tau_m: float, sigma_m: float = 1.0) -> dict:
    """The moment noise's linear model in physical units: {"states" (the state names),
    "A" (the augmented system matrix), "G" (the noise input column, √(2σ_M²/τ_M) on M_n),
    "H" (the output row: U_out = H x), "P" (the joint stationary covariance of the loop's
    states and M_n, the Lyapunov solution for σ_M = `sigma_m` [N·m]), "output_var" (H P Hᵀ
    [V²])}."""
    _check(device)
    model = _Model(device, tau_m)
    s = model.scale
    p = model.P_unit * np.outer(s, s) * sigma_m**2
    g = model.g_unit * s * sigma_m
    return {
        "states": list(model.names),
        "A": model.A_phys.copy(),
        "G": g,
        "H": model.H_phys.copy(),
        "P": p,
        "output_var": model.output_var_unit() * sigma_m**2,
    }


def moment_sigma_for_output_std(device: step_truth.Device, tau_m: float, std_V: float) -> float:
    """σ_M [N·m] of the Gauss–Markov moment (τ_M [s]) whose part of U_out has the stationary
    standard deviation `std_V` [V] (from the Lyapunov solution, linear in σ_M²)."""
    _check(device)
    return float(std_V / np.sqrt(_Model(device, tau_m).output_var_unit()))


# --------------------------------------------------------------------------------------
# The record
# --------------------------------------------------------------------------------------


def run(
    device: step_truth.Device,
    rec: step_truth.Record,
    *,
    rng: np.random.Generator,
    output_gm=None,
    moment_gm=(0.0, 1.0),
) -> dict:
    """One record and its parts: a dict with "t" [s], "u_test" [V] (the level in force at
    each sample), "clean" [V] (U_out with no noise), "moment_part" [V] (U_out's
    moment-noise part: U_out = clean + moment_part), "u_out" [V] (the recorded column),
    "recorded_clean" [V] (output_sign × clean + output_offset: the same record with every
    noise off and no ADC) and "noise" (u_out − recorded_clean: the total noise component,
    ADC rounding included). `output_gm` (σ [V], τ [s]): the output Gauss–Markov noise
    (None: the record's own `gm`); `moment_gm` (σ_M [N·m], τ_M [s]): the moment noise."""
    _check(device, rec)
    sigma_m, tau_m = (float(v) for v in moment_gm)
    if sigma_m < 0:
        raise ValueError("σ_M must be ≥ 0")
    if output_gm is not None:
        if rec.gm[0] > 0:
            raise ValueError("give the output Gauss–Markov noise once: Record.gm or output_gm")
        sigma_gm, tau_gm = (float(v) for v in output_gm)
        if sigma_gm < 0 or (sigma_gm > 0 and not tau_gm > 0):
            raise ValueError("output_gm needs σ ≥ 0 and τ > 0")
        rec = dataclasses.replace(rec, gm=(sigma_gm, tau_gm))
    model = _model(device, tau_m)
    dim = len(model.names)
    t = rec.t0 + np.arange(rec.n) / rec.rate
    levels = np.asarray(rec.levels, dtype=float)
    changes = np.asarray(rec.change_times, dtype=float)
    if changes.size != levels.size - 1:
        raise ValueError("change_times needs one time fewer than levels")

    def level_at(time):
        return float(levels[np.searchsorted(changes, time, side="right")])

    u_column = levels[np.searchsorted(changes, t, side="right")]

    # The deterministic start (step_truth's), propagated to t0 with no noise.
    if rec.start == "rest":
        x = model.equilibrium(float(levels[0]), rec.moment)
    else:
        t_begin = t[0] - float(rec.start)
        x = model.equilibrium(float(rec.start_level), rec.moment)
        inner = changes[(changes > t_begin) & (changes < t[0])]
        edges = np.concatenate([[t_begin], inner, [t[0]]])
        for a, b in zip(edges[:-1], edges[1:], strict=True):
            if b > a:
                eq = model.equilibrium(level_at(a), rec.moment)
                x = eq + model.transition(b - a) @ (x - eq)

    # The propagation steps: sample to sample, split at the changes between them.
    dt = 1.0 / rec.rate
    inside = changes[(changes > t[0]) & (changes < t[-1])]
    split = {}
    for c in inside:
        k = int(np.searchsorted(t, c, side="right")) - 1
        if t[k] < c < t[k + 1]:
            split.setdefault(k, []).append(float(c))
    n_steps = rec.n - 1 + sum(len(v) for v in split.values())

    noisy = sigma_m > 0
    state = np.empty((dim, 2))  # column 0: with the moment noise; column 1: noise-free
    state[:, 1] = x
    state[:, 0] = x
    if noisy:
        start = _factor(model.P_unit) @ rng.standard_normal(dim) * sigma_m
        draws = rng.standard_normal((n_steps, dim)) * sigma_m
        state[:, 0] += start
    out = np.empty((rec.n, 2))
    out[0] = model.H @ state
    phi_dt = model.transition(dt)
    if noisy:
        increments = draws @ model.step(dt)[1].T  # the regular steps' (the split ones redone)
    offsets = {}  # x_eq − Φ(dt) x_eq per level: x ← Φ x + (x_eq − Φ x_eq)
    h_row = model.H
    j = 0
    for k in range(rec.n - 1):
        if k in split:
            edges = [t[k], *sorted(split[k]), t[k + 1]]
            for a, b in zip(edges[:-1], edges[1:], strict=True):
                eq = model.equilibrium(level_at(a), rec.moment)
                state = eq[:, None] + model.transition(b - a) @ (state - eq[:, None])
                if noisy:
                    state[:, 0] += model.step(b - a)[1] @ draws[j]
                j += 1
        else:
            u = u_column[k]
            if u not in offsets:
                eq = model.equilibrium(u, rec.moment)
                offsets[u] = (eq - phi_dt @ eq)[:, None]
            state = phi_dt @ state + offsets[u]
            if noisy:
                state[:, 0] += increments[j]
            j += 1
        out[k + 1] = h_row @ state
    clean = out[:, 1].copy()
    moment_part = out[:, 0] - out[:, 1]
    u_out = step_truth.recorded(rec, clean + moment_part, rng)
    recorded_clean = rec.output_sign * clean + rec.output_offset
    return {
        "t": t,
        "u_test": u_column,
        "clean": clean,
        "moment_part": moment_part,
        "u_out": u_out,
        "recorded_clean": recorded_clean,
        "noise": u_out - recorded_clean,
    }


def simulate(
    device: step_truth.Device,
    rec: step_truth.Record,
    *,
    rng: np.random.Generator,
    output_gm=None,
    moment_gm=(0.0, 1.0),
):
    """(t [s], u_test column [V], u_out column [V]) of one record, as step_truth.simulate
    returns them (see `run` and the module docstring). `output_gm` (σ_gm [V], τ_gm [s]),
    None: the record's own `gm` (step_truth's exact AR(1)); `moment_gm` (σ_M [N·m], τ_M
    [s]), σ_M = 0: none."""
    result = run(device, rec, rng=rng, output_gm=output_gm, moment_gm=moment_gm)
    return result["t"], result["u_test"], result["u_out"]


# --------------------------------------------------------------------------------------
# The drawn records
# --------------------------------------------------------------------------------------


def tau_bounds(rate: float) -> tuple[float, float]:
    """(shortest, longest) correlation time [s] drawn for a record of this sample rate:
    `TAU_SAMPLES_MIN` sample periods and `TAU_MAX`."""
    return TAU_SAMPLES_MIN / rate, TAU_MAX


def truth_device(truth: dict) -> step_truth.Device:
    """The `step_truth.Device` of a drawn record (lags from "T_dm_s", "T_f_s")."""
    d = truth["device"]
    return step_truth.Device(
        J=d["J"],
        mu=d["mu"],
        c=d["c"],
        k_dm=d["k_dm"],
        k_dp=d["k_dp"],
        k_y=d["k_y"],
        T_dm=truth["T_dm_s"],
        T_f=truth["T_f_s"],
        test_gain=d["test_gain"],
    )


def truth_record(truth: dict) -> step_truth.Record:
    """The `step_truth.Record` of a drawn record (its `gm` left at none)."""
    return step_truth.record_from_truth(truth)


def draw_truth(rng: np.random.Generator, effect: str) -> dict:
    """One record's world (JSON-able): step_truth.draw_truth(rng, "none")'s (the same draws
    in the same order), then the coloured noise's two draws, for every class in this order:
    the ratio (log-uniform in `RATIO`) and τ (log-uniform in `tau_bounds(rate)`).

    Keys added to step_truth's: "effect" (one of `CLASSES`), "T_dm_s", "T_f_s" (the lags,
    0: step_truth's "none" world has none), "ratio" (σ_gm/σ_white, or the moment noise's
    output std over σ_white; None for "none"), "tau_s" (τ_gm or τ_M [s]; None for "none"),
    "sigma" (σ_gm [V] for "output_gm", σ_M [N·m] for "moment_gm", 0.0 for "none"),
    "sigma_unit" ("V", "N·m" or None), "output_std_V" (the coloured noise's stationary std
    at the output, ratio × noise_V; 0.0 for "none"). `make` rebuilds the record from them
    (it uses "sigma" as stored)."""
    if effect not in CLASSES:
        raise ValueError(f"effect must be one of {CLASSES}, not {effect!r}")
    truth = step_truth.draw_truth(rng, "none")
    truth["effect"] = effect
    truth["T_dm_s"] = truth["T_f_s"] = 0.0
    ratio = step_truth._log_uniform(rng, *RATIO)
    tau = step_truth._log_uniform(rng, *tau_bounds(truth["rate"]))
    if effect == "none":
        truth.update(
            {"ratio": None, "tau_s": None, "sigma": 0.0, "sigma_unit": None, "output_std_V": 0.0}
        )
        return truth
    std = ratio * truth["noise_V"]
    if effect == "output_gm":
        sigma, unit = std, "V"
    else:
        sigma, unit = moment_sigma_for_output_std(truth_device(truth), tau, std), "N·m"
    truth.update(
        {
            "ratio": ratio,
            "tau_s": tau,
            "sigma": float(sigma),
            "sigma_unit": unit,
            "output_std_V": float(std),
        }
    )
    return truth


def make(truth: dict, rng: np.random.Generator):
    """Simulate one drawn world (`draw_truth`'s): (t [s] from 0, u_test column [V], u_out
    column [V], noise component [V]), as step_truth.make returns them. The noise component
    is u_out minus the same record with every noise (white, output Gauss–Markov, moment)
    off and no ADC (output sign and offset kept): the noise-free state is propagated
    alongside the noisy one, by the same transitions."""
    effect = truth["effect"]
    if effect not in CLASSES:
        raise ValueError(f"effect must be one of {CLASSES}, not {effect!r}")
    output_gm, moment_gm = (0.0, 1.0), (0.0, 1.0)
    if effect == "output_gm":
        output_gm = (truth["sigma"], truth["tau_s"])
    elif effect == "moment_gm":
        moment_gm = (truth["sigma"], truth["tau_s"])
    result = run(
        truth_device(truth), truth_record(truth), rng=rng, output_gm=output_gm, moment_gm=moment_gm
    )
    t = result["t"]
    return t - t[0], result["u_test"], result["u_out"], result["noise"]
