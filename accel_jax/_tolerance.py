"""Tolerance limits on the static transfer-function coefficients (docs/models.md §3, eqs. 7-15):
the paper's fixed-ratio method, a gradient-based allocation with exact sensitivities, the
joint admissible region, the worst case over a flight profile, a Monte Carlo yield, and the
limits side by side with a unit's passport judged against them (`tolerance_table`).

Everything is in g (coefficients in g-units, 1 ppm = 1e-6; see `accel_jax._static`).
Precision: limits are ratios of O(1e-4 g) budgets to O(1..1e4) sensitivities, fine in
float32; the Monte Carlo yield evaluates ppm-level vibration errors: float64 advised.
"""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._params import _concrete
from ._static import COEFFICIENTS, PPM_UNITS, StaticTransferFunction, _as_float
from ._vibration import VibrationEnvironment, vibration_error

# --- the paper's fixed budget ratios (7)-(14) -------------------------------------------
ADDITIVE_SHARE = 0.44
"""δ0(1) = δ0(2) = δ0(3) ≤ 0.44 δ* (eq. 12): 0.83 δ*/sqrt(3 + 2·0.25)."""
CROSS_SHARE = 0.22
"""δ0(4) = δ0(5) ≤ 0.22 δ* (eq. 12), half the additive share."""
LINEAR_SHARE = 0.35
"""Each of the two terms of δ(1) (k3 and k5) ≤ 0.35 δ*/a (eq. 15): 0.49/√2."""
HIGHER_SHARE = 0.24
"""δ(2) a² and δ(3) a³ ≤ 0.24 δ* (eq. 14)."""

PAPER_SHARES = {
    "asymmetry": ADDITIVE_SHARE,
    "k2": ADDITIVE_SHARE,
    "k3": LINEAR_SHARE,
    "k4": HIGHER_SHARE,
    "k5": HIGHER_SHARE,
    "m31": CROSS_SHARE,
    "m32": CROSS_SHARE,
}
"""The share of δ* the paper's method gives each coefficient's binding term (used to put
the gradient-based limits on the same budget)."""

TOLERANCED = ("asymmetry", "k2", "k3", "k4", "k5", "m31", "m32")
"""The coefficients the paper puts limits on (Table 2; m = m31 = m32)."""


class ToleranceScenario(eqx.Module):
    """A flight for which coefficient limits are computed.

    **Fields:**

    - `admissible_error`: δ* [g], the admissible vibration error.
    - `mean_acceleration`: a3 [g], the flight-mean apparent acceleration along IA.
    - `environment`: the vibration (`VibrationEnvironment`).
    - `profile_time`, `profile_acceleration`: the flight profile a3(t) [s], [g] (for the
      worst case over the flight).
    """

    admissible_error: Float[Array, ""] = eqx.field(converter=_as_float)
    mean_acceleration: Float[Array, ""] = eqx.field(converter=_as_float)
    environment: VibrationEnvironment
    profile_time: Float[Array, " n"] = eqx.field(converter=_as_float)
    profile_acceleration: Float[Array, " n"] = eqx.field(converter=_as_float)

    def __check_init__(self):
        d = _concrete(self.admissible_error)
        if d is not None and not np.all(d > 0):
            raise ValueError(f"ToleranceScenario.admissible_error must be positive, got {d!r} g.")
        a = _concrete(self.mean_acceleration)
        if a is not None and not np.all(np.isfinite(a) & (a != 0)):
            raise ValueError(
                f"ToleranceScenario.mean_acceleration must be finite and non-zero (the "
                f"multiplicative limits divide by it), got {a!r} g."
            )
        t, p = _concrete(self.profile_time), _concrete(self.profile_acceleration)
        if t is not None and p is not None and t.shape != p.shape:
            raise ValueError(
                f"profile_time {t.shape} and profile_acceleration {p.shape} differ in shape."
            )


def _profile(points, n=601):
    t, a = np.asarray(points, dtype=float).T
    ts = np.linspace(t[0], t[-1], n)
    return ts, np.interp(ts, t, a)


def cyclone4() -> ToleranceScenario:
    """Example 1 (Cyclone-4 launcher): δ* = 5e-4 g, mean a3 = 2 g; sinusoid 0.5 g on IA,
    1.2 g on OA and PA (8-16 Hz, taken in phase); random σ = 1.4 g on every axis (Table 1's
    value, taken for all axes, fully correlated: the paper's m31 limit assumes σ3σ1);
    600 s profile between 1 and 5 g (an approximation of Fig. 3a, time mean ≈ 2 g)."""
    ts, prof = _profile(
        [
            (0, 1.2),
            (140, 3.2),
            (141, 1.0),
            (380, 2.4),
            (381, 1.0),
            (560, 5.0),
            (561, 1.0),
            (600, 1.0),
        ]
    )
    env = VibrationEnvironment(
        sine_amplitude=(1.2, 1.2, 0.5),
        sine_frequency=12.0,
        random_std=1.4,
        random_correlation=1.0,
        random_band=(20.0, 640.0),
    )
    return ToleranceScenario(5e-4, 2.0, env, ts, prof)


def tactical_missile(flight: str = "short") -> ToleranceScenario:
    """Example 2 (hypothetical tactical missile): δ* = 2e-4 g; self-oscillation 2 g on all
    axes (10-25 Hz, in phase); random σ = 9 g on every axis (5 g over 20-2000 Hz times the
    mount's η peak, the paper's value), fully correlated; mean a3 = 5.1 g ("short": 100 s,
    8 → 2.2 g) or 2.2 g ("long": 300 s, 1.2 + 5 e^{−t/60} g) — approximations of Fig. 3b."""
    if flight == "short":
        ts = np.linspace(0, 100, 601)
        prof, mean = 8.0 - 5.8 * ts / 100, 5.1
    elif flight == "long":
        ts = np.linspace(0, 300, 601)
        prof, mean = 1.2 + 5 * np.exp(-ts / 60), 2.2
    else:
        raise ValueError(f"flight must be 'short' or 'long', got {flight!r}.")
    env = VibrationEnvironment(
        sine_amplitude=2.0,
        sine_frequency=15.0,
        random_std=9.0,
        random_correlation=1.0,
        random_band=(20.0, 2000.0),
    )
    return ToleranceScenario(2e-4, mean, env, ts, prof)


# --- the paper's method (13), (15) ------------------------------------------------------

# (c4, c5): the σ⁴ coefficients of the k4 additive and k5 linear bounds, per reading.
_FOURTH_MOMENT = {"exact": (3.0, 15.0), "printed": (1.0, 5.0)}


def paper_limits(scenario: ToleranceScenario, *, reading: str = "exact") -> dict[str, Array]:
    """Admissible |coefficient| by the paper's fixed-ratio method, eqs. (13) and (15) [g-units;
    ×1e6 for ppm]. With b = sine amplitudes, σ = RMS random levels, a = mean a3, δ*:

        A1 ≤ 0.44δ*/(0.673 b3 + 0.125 σ3)          k2 ≤ 0.44δ*/(0.5 b3² + σ3²)
        k4 ≤ 0.44δ*/(0.375 b3⁴ + c4 σ3⁴)  (additive) m3i ≤ 0.22δ*/(0.5 b3 bi + σ3 σi)
        k3 ≤ 0.35δ*/(a (1.5 b3² + 3σ3²))           k5 ≤ 0.35δ*/(a (1.875 b3⁴ + c5 σ3⁴))
        k4 ≤ 0.24δ*/(3a² (b3² + 2σ3²))  (mult.)    k5 ≤ 0.24δ*/(5a³ (b3² + 2σ3²))

    `reading` chooses the fourth-moment coefficients of the random part: `"exact"` (default)
    c4 = 3, c5 = 15, the Gaussian moments E v⁴ = 3σ⁴ and E (a+v)⁵ − a⁵ ⊃ 15 a σ⁴ (docs/models.md §3);
    `"printed"` c4 = 1, c5 = 5, the coefficients as printed in the paper's (4)/(13) and
    (5)/(15). The two agree for sinusoidal vibration alone (σ = 0).

    **Returns:** a dict with every bound and "k4", "k5" the smaller of their two bounds.
    """
    if reading not in _FOURTH_MOMENT:
        raise ValueError(f"reading must be 'exact' or 'printed', got {reading!r}.")
    c4, c5 = _FOURTH_MOMENT[reading]
    d = scenario.admissible_error
    a = jnp.abs(scenario.mean_acceleration)
    b = scenario.environment.sine_amplitude
    s = scenario.environment.random_std
    b3, s3 = b[2], s[2]
    out = {
        "asymmetry": ADDITIVE_SHARE * d / (0.673 * b3 + 0.125 * s3),
        "k2": ADDITIVE_SHARE * d / (0.5 * b3**2 + s3**2),
        "k4_additive": ADDITIVE_SHARE * d / (0.375 * b3**4 + c4 * s3**4),
        "m31": CROSS_SHARE * d / (0.5 * b3 * b[0] + s3 * s[0]),
        "m32": CROSS_SHARE * d / (0.5 * b3 * b[1] + s3 * s[1]),
        "k3": LINEAR_SHARE * d / (a * (1.5 * b3**2 + 3 * s3**2)),
        "k5_linear": LINEAR_SHARE * d / (a * (1.875 * b3**4 + c5 * s3**4)),
        "k4_multiplicative": HIGHER_SHARE * d / (3 * a**2 * (b3**2 + 2 * s3**2)),
        "k5_cubic": HIGHER_SHARE * d / (5 * a**3 * (b3**2 + 2 * s3**2)),
    }
    out["k4"] = jnp.minimum(out["k4_additive"], out["k4_multiplicative"])
    out["k5"] = jnp.minimum(out["k5_linear"], out["k5_cubic"])
    return out


# --- gradient-based allocation ----------------------------------------------------------


def sensitivities(
    environment: VibrationEnvironment, a3: ArrayLike, *, n_phase: int = 512
) -> StaticTransferFunction:
    """∂δ_V/∂coefficient at the steady input a3 [g per unit coefficient], by `jax.grad` of
    the exact vibration error (vmapped over the elements of an array a3). δ_V is linear in
    the coefficients, so these are exact and independent of where they are taken
    (evaluated at zero coefficients).

    **Returns:** a `StaticTransferFunction` pytree whose fields are the sensitivities.
    """
    a3 = _as_float(a3)
    flat = _sensitivities_flat(environment, a3.reshape(-1), n_phase)
    return jax.tree_util.tree_map(lambda x: x.reshape(a3.shape), flat)


@eqx.filter_jit
def _sensitivities_flat(environment, a3, n_phase):
    zero = StaticTransferFunction(**{name: jnp.zeros((), a3.dtype) for name in COEFFICIENTS})

    def one(a):
        return jax.grad(lambda tf: vibration_error(tf, environment, a, n_phase=n_phase))(zero)

    return jax.vmap(one)(a3)


def error_contributions(
    tf: StaticTransferFunction,
    environment: VibrationEnvironment,
    a3: ArrayLike,
    *,
    n_phase: int = 512,
) -> dict[str, Array]:
    """Each coefficient's part of a unit's vibration error, s_k·k [g], at the steady input
    a3 [g] (shape of a3). δ_V is linear in the coefficients, so the parts add up to
    `vibration_error(tf, environment, a3)` exactly; the largest |part| is the coefficient
    that dominates the unit's error in this environment.

    **Returns:** {coefficient name: s_k·k} for every field of `StaticTransferFunction`
    (a0, δ, m1, m2 give 0: zero-mean vibration does not change linear terms).
    """
    sens = sensitivities(environment, a3, n_phase=n_phase)
    return {name: getattr(sens, name) * getattr(tf, name) for name in COEFFICIENTS}


def gradient_limits(
    scenario: ToleranceScenario,
    *,
    over_profile: bool = False,
    n_phase: int = 512,
) -> dict[str, dict[str, Array]]:
    """Admissible |coefficient| from the exact sensitivities s_k = ∂δ_V/∂k.

    Three allocations of the budget δ* (all in g-units):

    - `"paper_shares"`: |k| ≤ share_k δ*/|s_k| with the paper's share for that coefficient
      (`PAPER_SHARES`) — the paper's budget, exact sensitivities.
    - `"full_budget"`: |k| ≤ δ*/|s_k|, that coefficient alone using all of δ*.
    - `"equal_rms"`: |k| ≤ δ*/(sqrt(N) |s_k|) over the N = 7 toleranced coefficients —
      the largest box inside the RMS ellipsoid Σ (s_k k)² ≤ δ*² with equal shares.

    **Arguments:**

    - `scenario`: the flight.
    - `over_profile`: False uses the mean a3; True takes the worst (largest) |s_k| over
      the flight profile a3(t), i.e. the limit holding at every instant.

    **Returns:** {"sensitivity": {name: s_k}, allocation: {name: limit}}.
    """
    if over_profile:
        sens = sensitivities(scenario.environment, scenario.profile_acceleration, n_phase=n_phase)
        sens = jax.tree_util.tree_map(lambda x: jnp.max(jnp.abs(x), axis=-1), sens)
    else:
        sens = sensitivities(scenario.environment, scenario.mean_acceleration, n_phase=n_phase)
    d = scenario.admissible_error
    s = {name: jnp.abs(getattr(sens, name)) for name in TOLERANCED}
    n = len(TOLERANCED)
    return {
        "sensitivity": {name: getattr(sens, name) for name in TOLERANCED},
        "paper_shares": {k: PAPER_SHARES[k] * d / v for k, v in s.items()},
        "full_budget": {k: d / v for k, v in s.items()},
        "equal_rms": {k: d / (math.sqrt(n) * v) for k, v in s.items()},
    }


def tolerance_table(
    scenario: ToleranceScenario, device: StaticTransferFunction | None = None
) -> dict:
    """The limits on each toleranced coefficient side by side, in the paper's display units
    (×1e6: ppm, ppm/g, …), and a unit's passport judged against them (the `accel-jax
    tolerance` table).

    **Arguments:**

    - `scenario`: the flight; the limits hold at its mean a3.
    - `device`: a unit's transfer function (e.g. `StaticTransferFunction.aks05()`), or None.

    **Returns:** a dict: `rows`, {name: row} over `TOLERANCED`, each row with `unit` (its
    display unit), `paper_method` (`paper_limits`), `gradient_paper_shares` and
    `gradient_full_budget` (`gradient_limits`), `sensitivity_g_per_ppm`; with a device also
    `passport` (its |coefficient|), `within` (at most the gradient limit with the paper's
    share) and `vibration_error_part_g` (its signed part s_k·k of the unit's δ_V at a3,
    `error_contributions`). `total_vibration_error_g` (the parts' sum, δ_V at a3) and
    `within_budget` (|δ_V| ≤ δ*) are None without a device. Host floats: evaluate in
    float64 for ppm work.
    """
    paper = paper_limits(scenario)
    grad = gradient_limits(scenario)
    unit_ppm = device.as_ppm() if device is not None else {}
    parts = {}
    if device is not None:
        parts = error_contributions(device, scenario.environment, scenario.mean_acceleration)
    rows = {}
    for name in TOLERANCED:
        row = {
            "unit": PPM_UNITS[name],
            "paper_method": float(paper[name]) * 1e6,
            "gradient_paper_shares": float(grad["paper_shares"][name]) * 1e6,
            "gradient_full_budget": float(grad["full_budget"][name]) * 1e6,
            "sensitivity_g_per_ppm": float(grad["sensitivity"][name]) * 1e-6,
        }
        if unit_ppm:
            value = abs(unit_ppm.get(name, 0.0))
            row["passport"] = value
            row["within"] = bool(value <= row["gradient_paper_shares"])
            row["vibration_error_part_g"] = float(parts[name])
        rows[name] = row
    total = float(sum(parts.values())) if parts else None
    within = None if total is None else abs(total) <= float(scenario.admissible_error)
    return {"rows": rows, "total_vibration_error_g": total, "within_budget": within}


def sensitivity_profile(
    scenario: ToleranceScenario, *, n_phase: int = 512
) -> StaticTransferFunction:
    """s_k(t) = ∂δ_V/∂k along the flight profile (a pytree of arrays over time) [g/unit]."""
    return sensitivities(scenario.environment, scenario.profile_acceleration, n_phase=n_phase)


def within_rms_region(
    tf: StaticTransferFunction, sensitivity: StaticTransferFunction, admissible_error: ArrayLike
) -> Array:
    """Whether coefficients lie in the joint admissible region of the paper's RMS criterion
    (7), sqrt(Σ_k (s_k k)²) ≤ δ* (components of independent sign add in quadrature)."""
    d = _concrete(admissible_error)
    if d is not None and not np.all(d > 0):
        raise ValueError(f"within_rms_region: admissible_error δ* must be positive, got {d!r} g.")
    terms = jnp.stack([getattr(sensitivity, n) * getattr(tf, n) for n in TOLERANCED])
    return jnp.sqrt(jnp.sum(terms**2, axis=0)) <= admissible_error


# --- Monte Carlo yield -----------------------------------------------------------------

AKS05_RANGES_PPM = {
    "asymmetry": (15.0, 25.0),
    "k2": (0.5, 3.0),
    "k3": (1.0, 5.0),
    "k4": (0.0, 0.03),
    "k5": (0.0, 0.5),
    "m31": (2.0, 4.0),
    "m32": (2.0, 4.0),
}
"""Table 2's ranges of |coefficient| for the AKS-05 batch [ppm units]."""


def sample_batch(
    key: Array, n: int, ranges_ppm: dict[str, tuple[float, float]] = AKS05_RANGES_PPM, *, dtype=None
) -> StaticTransferFunction:
    """n units with |coefficient| uniform in `ranges_ppm` [ppm units] and independent random
    signs (the paper gives ranges of the moduli only); other coefficients 0. Returns a
    batched `StaticTransferFunction` (leading axis n)."""
    for name, (low, high) in ranges_ppm.items():
        if name not in COEFFICIENTS or not 0 <= low <= high:
            raise ValueError(
                f"sample_batch: range for {name!r} must be a known coefficient with "
                f"0 ≤ low ≤ high, got ({low!r}, {high!r}) ppm."
            )
    dtype = jnp.dtype(dtype or jnp.result_type(float))
    names = list(ranges_ppm)
    low, high = (jnp.asarray([ranges_ppm[k][i] for k in names], dtype) for i in (0, 1))
    values = _sample_moduli(key, low, high, n=n, dtype=dtype)
    fields = {name: jnp.zeros(n, dtype) for name in COEFFICIENTS}
    fields.update(zip(names, values, strict=True))
    return StaticTransferFunction(**fields)


@functools.partial(jax.jit, static_argnames=("n", "dtype"))
def _sample_moduli(key, low, high, *, n, dtype):
    # One compiled draw for all coefficients (rows) and units (columns), in g-units.
    k_mag, k_sign = jax.random.split(key)
    shape = (low.shape[0], n)
    mag = low[:, None] + (high - low)[:, None] * jax.random.uniform(k_mag, shape, dtype)
    sign = jnp.where(jax.random.bernoulli(k_sign, 0.5, shape), 1.0, -1.0).astype(dtype)
    return mag * sign * 1e-6


def unit_vibration_error(
    tf: StaticTransferFunction, scenario: ToleranceScenario, *, n_phase: int = 256
) -> tuple[Array, Array]:
    """(δ_V at the mean a3, worst |δ_V| over the profile) [g] of one unit: the function a
    yield sweep maps over a batch (`accel_jax.sweep(unit_vibration_error, batch, scenario,
    in_axes=(0, None))`)."""
    env = scenario.environment
    at_mean = vibration_error(tf, env, scenario.mean_acceleration, n_phase=n_phase)
    along = vibration_error(tf, env, scenario.profile_acceleration, n_phase=n_phase)
    return at_mean, jnp.max(jnp.abs(along))
