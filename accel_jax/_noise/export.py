"""An identified accelerometer noise model in the formats navigation engineers load: kalibr's
`imu.yaml`, gnss-ins-sim's IMU error dictionary, and the IEEE Std 952 / 1293 Allan-variance
coefficients with their customary units, plus the unit conversions people most often get
wrong by √Δt, by √2 or by 60.

Conventions (those of kalibr, IEEE Std 952 and `allan_coefficients`), for one axis sampled
every Δt = 1/f_s seconds, accelerations in m/s²:

- White noise density N [m/s²/√Hz = m/s/√s], the velocity random walk: the continuous-time
  white noise n(t) with E[n(t₁)n(t₂)] = N² δ(t₁ − t₂), i.e. a TWO-sided power spectral
  density N² (a one-sided PSD 2N², a one-sided amplitude spectral density √2·N, what a
  one-sided Welch estimate of the record gives). Its Allan deviation is σ(τ) = N/√τ, and the
  record's per-sample standard deviation (ideal low-pass at f_s/2) is σ_d = N/√Δt = N·√f_s,
  so N = σ_d·√Δt: the ADEV at τ = Δt of a white record is σ_d.
- Acceleration (bias) random walk K [m/s²/√s = m/s³/√Hz]: the bias b(t) = ∫ w, w white with
  two-sided PSD K²; σ(τ) = K·√(τ/3); per sample b_{k+1} = b_k + K·√Δt·ξ_k.
- Bias instability B [m/s²]: the IEEE flicker coefficient, the ADEV floor √(2 ln 2/π)·B ≈
  0.664 B. A state-space format needs a first-order Gauss–Markov bias instead: with a
  correlation time τ_c, the exports take its stationary σ_b = B (the usual practice; the GM's
  ADEV peak, ≈ 0.62 σ_b at τ ≈ 1.9 τ_c, is then within 7 % of the flicker floor). Discrete:
  b_{k+1} = ρ b_k + σ_b √(1 − ρ²) ξ_k, ρ = e^{−Δt/τ_c}.
- Quantization Q [m/s]: σ(τ) = √3·Q/τ.

Records in g convert with the standard gravity `STANDARD_GRAVITY` = 9.80665 m/s² (1 µg =
9.80665e-6 m/s²). Everything here is plain Python floats (NumPy arrays for the helpers'
array arguments and gnss-ins-sim's per-axis vectors), no JAX: an export is bookkeeping.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, fields, replace
from typing import Any, TypeGuard

import numpy as np

from .._static import STANDARD_GRAVITY

_UNITS = {"g": STANDARD_GRAVITY, "m/s^2": 1.0}
_UNIT_ALIASES = {"m/s²": "m/s^2", "m/s2": "m/s^2", "mps2": "m/s^2"}
_MICRO = 1e-6
_SQRT_HOUR = 60.0  # √(3600 s/h): 1 /√s = 60 /√h, so m/s²/√Hz = m/s/√s → ×60 m/s/√h
_HOUR_3_2 = 3600.0**1.5  # 1 /s^{3/2} = 216 000 /h^{3/2}


def _num(x):
    a = np.asarray(x, dtype=float)
    return float(a) if a.ndim == 0 else a


def _positive(name: str, value) -> np.ndarray:
    a = np.asarray(value, dtype=float)
    if not np.all(np.isfinite(a)) or not np.all(a > 0):
        raise ValueError(f"{name} must be finite and > 0, got {value!r}.")
    return a


def _unit(unit: str) -> str:
    if not isinstance(unit, str):
        raise ValueError(f"unit must be a string, 'g' or 'm/s^2', got {unit!r}.")
    unit = _UNIT_ALIASES.get(unit.strip(), unit.strip())
    if unit not in _UNITS:
        raise ValueError(f"Unknown unit {unit!r}: use 'g' or 'm/s^2'.")
    return unit


# --- conversions ------------------------------------------------------------------------


def unit_to_si(value, unit: str):
    """An acceleration-like quantity in `unit` ("g" or "m/s^2") as m/s² (×9.80665 from g;
    the same factor for a density, a random walk or a bias: only the acceleration unit
    changes)."""
    return _num(np.asarray(value, dtype=float) * _UNITS[_unit(unit)])


def si_to_micro_g(value):
    """m/s² (or m/s²/√Hz, …) as µg (µg/√Hz, …): × 1e6 / 9.80665."""
    return _num(np.asarray(value, dtype=float) / (STANDARD_GRAVITY * _MICRO))


def micro_g_to_si(value):
    """µg (or µg/√Hz, …) as m/s² (m/s²/√Hz, …): × 9.80665e-6."""
    return _num(np.asarray(value, dtype=float) * (STANDARD_GRAVITY * _MICRO))


def density_to_discrete(density, sample_rate):
    """The per-sample standard deviation σ_d of white noise of density N (square root of the
    two-sided PSD, [unit/√Hz]) sampled at f_s = 1/Δt behind an ideal low-pass at f_s/2:
    σ_d = N/√Δt = N·√f_s [unit] (kalibr's σ_wd)."""
    return _num(np.asarray(density, dtype=float) * np.sqrt(_positive("sample_rate", sample_rate)))


def discrete_to_density(sigma, sample_rate):
    """The density N = σ_d·√Δt = σ_d/√f_s [unit/√Hz] of white noise of per-sample standard
    deviation σ_d at f_s (the inverse of `density_to_discrete`; N is also the Allan deviation
    at τ = 1 s)."""
    return _num(np.asarray(sigma, dtype=float) / np.sqrt(_positive("sample_rate", sample_rate)))


def random_walk_to_discrete(random_walk, sample_rate):
    """The per-sample standard deviation of a random walk's increments: σ_bd = K·√Δt =
    K/√f_s [unit] for K [unit/√s = (unit/s)/√Hz] (kalibr's σ_bd)."""
    return _num(
        np.asarray(random_walk, dtype=float) / np.sqrt(_positive("sample_rate", sample_rate))
    )


def discrete_to_random_walk(sigma, sample_rate):
    """K = σ_bd/√Δt = σ_bd·√f_s [unit/√s] from the per-sample increment standard deviation
    σ_bd (the inverse of `random_walk_to_discrete`)."""
    return _num(np.asarray(sigma, dtype=float) * np.sqrt(_positive("sample_rate", sample_rate)))


def gauss_markov_to_discrete(sigma, correlation_time, sample_rate):
    """The exact discrete form of a first-order Gauss–Markov process of stationary standard
    deviation σ_b and correlation time τ_c sampled at f_s = 1/Δt:
    x_{k+1} = ρ x_k + σ_w ξ_k with ρ = e^{−Δt/τ_c} and σ_w = σ_b √(1 − ρ²).

    **Returns:** (ρ, σ_w [unit])."""
    x = 1.0 / (
        _positive("sample_rate", sample_rate) * _positive("correlation_time", correlation_time)
    )
    rho = np.exp(-x)
    return _num(rho), _num(np.asarray(sigma, dtype=float) * np.sqrt(-np.expm1(-2 * x)))


def discrete_to_gauss_markov(rho, driving_sigma, sample_rate):
    """The inverse of `gauss_markov_to_discrete`: τ_c = −Δt/ln ρ and σ_b = σ_w/√(1 − ρ²) for
    0 < ρ < 1. **Returns:** (σ_b [unit], τ_c [s])."""
    rho = np.asarray(rho, dtype=float)
    if not np.all((rho > 0) & (rho < 1)):
        raise ValueError(f"rho must be in (0, 1), got {rho!r}.")
    dt = 1.0 / _positive("sample_rate", sample_rate)
    sigma = np.asarray(driving_sigma, dtype=float) / np.sqrt(-np.expm1(2 * np.log(rho)))
    return _num(sigma), _num(-dt / np.log(rho))


def density_to_vrw(density):
    """Velocity random walk [m/s/√h] from a white noise density [m/s²/√Hz = m/s/√s]: ×60
    (√3600 s/h). The same factor takes g/√Hz to g·s/√h … any unit/√s to (unit·s)/√h."""
    return _num(np.asarray(density, dtype=float) * _SQRT_HOUR)


def vrw_to_density(vrw):
    """White noise density [m/s²/√Hz] from a velocity random walk [m/s/√h]: ÷60."""
    return _num(np.asarray(vrw, dtype=float) / _SQRT_HOUR)


def density_to_one_sided_asd(density):
    """The ONE-sided amplitude spectral density [unit/√Hz] of white noise of density N (the
    square root of the two-sided PSD, the convention of IEEE Std 952, kalibr and this
    module): √2·N. A one-sided Welch PSD of the record is flat at 2N²."""
    return _num(np.asarray(density, dtype=float) * math.sqrt(2.0))


def one_sided_asd_to_density(asd):
    """The density N (two-sided convention) from a one-sided amplitude spectral density:
    ÷√2. Use it when a datasheet or a one-sided Welch estimate gives the noise floor and the
    record's per-sample σ satisfies σ² = ASD²·f_s/2."""
    return _num(np.asarray(asd, dtype=float) / math.sqrt(2.0))


# --- the model --------------------------------------------------------------------------


_TERM_KEYS = {
    "N": "noise_density",
    "K": "random_walk",
    "B": "bias_instability",
    "Q": "quantization",
}


@dataclass(frozen=True, kw_only=True)
class AccelNoiseTerms:
    """One accelerometer axis's identified noise, continuous time, in the record's unit
    ("g" or "m/s^2"); the conventions are the module's (a two-sided density).

    **Fields:**

    - `noise_density` N [unit/√Hz = unit·√s]: white acceleration noise, velocity random walk.
    - `unit`: "g" or "m/s^2" (also "m/s²").
    - `random_walk` K [unit/√s = (unit/s)/√Hz] or None: acceleration (bias) random walk.
    - `bias_instability` B [unit] or None: the IEEE flicker coefficient (ADEV floor 0.664 B),
      or with `bias_correlation_time` a Gauss–Markov bias of stationary σ_b = B.
    - `bias_correlation_time` τ_c [s] or None (> 0; only with `bias_instability`).
    - `quantization` Q [unit·s] or None.
    - `sample_rate` f_s [Hz] or None (> 0): the record's rate, the default update rate.

    Values are finite and ≥ 0 (a ValueError otherwise), stored as floats.
    """

    noise_density: float
    unit: str
    random_walk: float | None = None
    bias_instability: float | None = None
    bias_correlation_time: float | None = None
    quantization: float | None = None
    sample_rate: float | None = None

    def __post_init__(self):
        object.__setattr__(self, "unit", _unit(self.unit))
        for f in fields(self):
            if f.name == "unit":
                continue
            value = getattr(self, f.name)
            if value is None and f.name != "noise_density":
                continue
            try:
                if value is None or isinstance(value, (bool, str, bytes)) or np.ndim(value) != 0:
                    raise TypeError
                number = float(value)
            except (TypeError, ValueError):
                raise ValueError(
                    f"AccelNoiseTerms.{f.name} must be a real number, got {value!r}."
                ) from None
            if not math.isfinite(number) or number < 0:
                raise ValueError(f"AccelNoiseTerms.{f.name} must be finite and ≥ 0, got {value!r}.")
            object.__setattr__(self, f.name, number)
        for name in ("bias_correlation_time", "sample_rate"):
            if getattr(self, name) == 0.0:
                raise ValueError(f"AccelNoiseTerms.{name} must be > 0 (or None), got 0.")
        if self.bias_correlation_time is not None and self.bias_instability is None:
            raise ValueError(
                "AccelNoiseTerms.bias_correlation_time needs bias_instability (the σ_b of the "
                "Gauss–Markov bias)."
            )

    @classmethod
    def from_mapping(
        cls,
        mapping: Mapping,
        unit: str,
        sample_rate: float | None = None,
        *,
        bias_correlation_time: float | None = None,
    ) -> AccelNoiseTerms:
        """From Allan-variance terms keyed "N", "K", "B", "Q" (e.g. a fit's table), in `unit`.

        A value is a number, None (an unsupported term), or a mapping with "value" (and
        optionally "supported": False meaning None), as a per-term fit summary gives. "N" is
        required; "R" (rate ramp) is accepted only as None or unsupported (no format here
        carries it); other keys are a ValueError.
        """
        if not isinstance(mapping, Mapping):
            raise ValueError(f"from_mapping needs a mapping of terms, got {type(mapping)}.")
        unknown = set(mapping) - set(_TERM_KEYS) - {"R"}
        if unknown:
            raise ValueError(
                f"Unknown Allan term(s) {sorted(map(str, unknown))}; valid keys are "
                f"{sorted(_TERM_KEYS)} (and 'R' when unsupported)."
            )

        def value(key):
            v = mapping.get(key)
            if isinstance(v, Mapping):
                if v.get("supported", True) is False:
                    return None
                if "value" not in v:
                    raise ValueError(f"Term {key!r} is a mapping without 'value': {v!r}.")
                v = v["value"]
            return v

        if value("R") is not None:
            raise ValueError(
                "A rate ramp R has no field in AccelNoiseTerms (no export format carries it); "
                "drop it or mark it unsupported."
            )
        if value("N") is None:
            raise ValueError("from_mapping needs the white noise term 'N'.")
        kwargs: dict[str, Any] = {name: value(key) for key, name in _TERM_KEYS.items()}
        return cls(
            **kwargs,
            unit=unit,
            sample_rate=sample_rate,
            bias_correlation_time=bias_correlation_time,
        )

    def in_si(self) -> AccelNoiseTerms:
        """The same terms in m/s² (×9.80665 from g; τ_c and f_s unchanged)."""
        factor = _UNITS[self.unit]
        scaled = {
            name: None if getattr(self, name) is None else getattr(self, name) * factor
            for name in _TERM_KEYS.values()
        }
        return replace(self, unit="m/s^2", **scaled)


def _terms(terms) -> AccelNoiseTerms:
    if not isinstance(terms, AccelNoiseTerms):
        raise ValueError(f"Expected AccelNoiseTerms, got {type(terms).__name__}.")
    return terms.in_si()


def _present(value: float | None) -> TypeGuard[float]:
    return value is not None and value > 0


def _dropped(fmt: str, dropped: dict[str, str], strict: bool):
    if dropped and strict:
        raise ValueError(
            f"{fmt} cannot carry "
            + "; ".join(f"{name} ({why})" for name, why in dropped.items())
            + ". Pass strict=False to export without them."
        )


# --- kalibr -------------------------------------------------------------------------------

# kalibr (github.com/ethz-asl/kalibr, commit 1f60227, 2024-03-08):
# aslam_offline_calibration/kalibr/python/kalibr_common/ConfigReader.py, class ImuParameters
# (lines 428-517): the keys "accelerometer_noise_density", "accelerometer_random_walk" and
# "update_rate"; both statistics must be > 0 (checkAccelerometerStatistics, lines 464-468) and
# the discrete noise is noise_density / sqrt(1/update_rate) (line 473); the random walk is used
# in continuous time (IccSensors.py line 769, Waccel = 1/K²). The YAML is read with
# yaml.safe_load into a dict (ParametersBase.readYaml, line 209): extra keys are ignored.
# Units and the discrete forms: https://github.com/ethz-asl/kalibr/wiki/IMU-Noise-Model


def to_kalibr(
    terms: AccelNoiseTerms, *, update_rate: float | None = None, strict: bool = False
) -> dict:
    """The accelerometer entries of kalibr's `imu.yaml` (continuous time, SI):

    - `accelerometer_noise_density` σ_a = N [m/s²/√Hz];
    - `accelerometer_random_walk` σ_ba = K [m/s³/√Hz];
    - `update_rate` [Hz]: `update_rate`, else `terms.sample_rate` (the IMU's message rate:
      kalibr turns the density into a per-sample σ with it);
    - extra keys kalibr's reader ignores, the discrete-time equivalents of the kalibr wiki:
      `accelerometer_noise_density_discrete` σ_ad = σ_a/√Δt [m/s²] and
      `accelerometer_random_walk_discrete` σ_bad = σ_ba·√Δt [m/s²], Δt = 1/update_rate.

    kalibr's model is white noise plus a random-walk bias only: B (with τ_c) and Q are left
    out (`strict=True`: a ValueError instead). kalibr refuses a zero density or random walk,
    so K must be given and both > 0 (a ValueError otherwise). The wiki advises inflating the
    values of a static identification for a moving calibration; nothing is inflated here.
    A full imu.yaml also needs `rostopic` and the gyroscope entries (`kalibr_yaml` writes
    `rostopic` if given).
    """
    si = _terms(terms)
    rate = update_rate if update_rate is not None else si.sample_rate
    if rate is None:
        raise ValueError("to_kalibr needs update_rate (or terms.sample_rate) [Hz].")
    rate = float(_positive("update_rate", rate))
    if not _present(si.noise_density) or not _present(si.random_walk):
        raise ValueError(
            "kalibr needs accelerometer_noise_density and accelerometer_random_walk > 0 "
            f"(its ConfigReader refuses ≤ 0), got N = {si.noise_density!r} m/s²/√Hz, K = "
            f"{si.random_walk!r} m/s³/√Hz."
        )
    dropped = {}
    if _present(si.bias_instability):
        dropped["B"] = "no bias-instability or Gauss–Markov term in kalibr's model"
    if _present(si.quantization):
        dropped["Q"] = "no quantization term in kalibr's model"
    _dropped("kalibr", dropped, strict)
    return {
        "accelerometer_noise_density": si.noise_density,
        "accelerometer_random_walk": si.random_walk,
        "update_rate": rate,
        "accelerometer_noise_density_discrete": density_to_discrete(si.noise_density, rate),
        "accelerometer_random_walk_discrete": random_walk_to_discrete(si.random_walk, rate),
    }


def _yaml_float(x: float) -> str:
    # The shortest round-tripping repr, with the '.' YAML 1.1 (PyYAML) needs to read an
    # exponent form as a float ("1e-05" is a string there, "1.0e-05" a float).
    r = repr(float(x))
    mantissa, e, exponent = r.partition("e")
    if e and "." not in mantissa:
        mantissa += ".0"
    return mantissa + e + exponent


def kalibr_yaml(
    terms: AccelNoiseTerms,
    *,
    update_rate: float | None = None,
    rostopic: str | None = None,
    strict: bool = False,
) -> str:
    """`to_kalibr` as YAML text: kalibr's three keys (and `rostopic` if given) as keys, the
    discrete-time values and any term kalibr cannot carry as comments. Written by hand (no
    YAML dependency); readable by `yaml.safe_load`, which kalibr uses."""
    entries = to_kalibr(terms, update_rate=update_rate, strict=strict)
    si = _terms(terms)
    dt = 1.0 / entries["update_rate"]
    lines = [
        "# Accelerometer noise (accel_jax), kalibr imu.yaml convention: continuous time, SI.",
        "# accelerometer_noise_density [m/s^2/sqrt(Hz)], accelerometer_random_walk "
        "[m/s^3/sqrt(Hz)], update_rate [Hz].",
        f"# Discrete at dt = {_yaml_float(dt)} s: sigma_ad = density/sqrt(dt) = "
        f"{_yaml_float(entries['accelerometer_noise_density_discrete'])} m/s^2, "
        f"sigma_bad = random_walk*sqrt(dt) = "
        f"{_yaml_float(entries['accelerometer_random_walk_discrete'])} m/s^2.",
    ]
    if _present(si.bias_instability):
        tau = si.bias_correlation_time
        lines.append(
            f"# Not in kalibr's model: bias instability B = {_yaml_float(si.bias_instability)}"
            " m/s^2" + ("" if tau is None else f", correlation time {_yaml_float(tau)} s") + "."
        )
    if _present(si.quantization):
        lines.append(
            f"# Not in kalibr's model: quantization Q = {_yaml_float(si.quantization)} m/s."
        )
    if rostopic is not None:
        if not isinstance(rostopic, str) or not rostopic or any(c in rostopic for c in '\n\r"\\'):
            raise ValueError(f"rostopic must be a one-line string, got {rostopic!r}.")
        lines.append(f'rostopic: "{rostopic}"')
    for key in ("accelerometer_noise_density", "accelerometer_random_walk", "update_rate"):
        lines.append(f"{key}: {_yaml_float(entries[key])}")
    return "\n".join(lines) + "\n"


# --- gnss-ins-sim -------------------------------------------------------------------------

# gnss-ins-sim (github.com/Aceinna/gnss-ins-sim, commit 966ff27, 2024-11-27):
# gnss_ins_sim/sim/imu_model.py, IMU.__init__ docstring (lines 82-85): 'accel_b' m/s2,
# 'accel_vrw' m/s/rt-hr, 'accel_b_stability' m/s2, 'accel_b_corr' sec; required keys (lines
# 134-136: with the gyro's, 'accel_b', 'accel_b_stability', 'accel_vrw'); conversion (lines
# 141-143): vrw = accel_vrw / 60.0 [m/s²/√Hz]; 'accel_b_corr' absent → inf (lines 155-158).
# gnss_ins_sim/pathgen/pathgen.py: acc_gen (line 496) draws white noise vrw/sqrt(dt) per
# sample; bias_drift (lines 565-593) is a first-order GM, a = 1 − dt/τ, b = σ√(1 − e^{−2dt/τ})
# (stationary σ ≈ accel_b_stability) for a finite τ, but for τ = inf WHITE noise of σ per
# sample (line 593), not the random walk the README announces. Values are per-axis 3-vectors.


def to_gnss_ins_sim(terms: AccelNoiseTerms, *, strict: bool = False) -> dict:
    """The accelerometer part of gnss-ins-sim's IMU error dictionary (`IMU(accuracy=...)`,
    merge it with the gyro's keys), each value a 3-vector (the same on every axis):

    - `accel_b`: constant bias [m/s²], zeros (not part of a noise model; set it yourself);
    - `accel_vrw`: velocity random walk 60·N [m/s/√h] (gnss-ins-sim divides by 60 and
      draws N/√Δt per sample, the module's convention);
    - `accel_b_stability`: the Gauss–Markov bias's stationary σ_b = B [m/s²];
    - `accel_b_corr`: its correlation time τ_c [s].

    gnss-ins-sim has no random-walk bias, no quantization and, for a bias without a finite
    correlation time, only white per-sample noise: K, Q and a B without τ_c are left out
    (`accel_b_stability` 0, `accel_b_corr` inf; `strict=True`: a ValueError instead).
    """
    si = _terms(terms)
    _dropped("gnss-ins-sim", gnss_ins_sim_left_out(terms), strict)
    stability, corr = 0.0, math.inf
    if _present(si.bias_instability) and si.bias_correlation_time is not None:
        stability, corr = si.bias_instability, si.bias_correlation_time
    ones = np.ones(3)
    return {
        "accel_b": np.zeros(3),
        "accel_vrw": density_to_vrw(si.noise_density) * ones,
        "accel_b_stability": stability * ones,
        "accel_b_corr": corr * ones,
    }


def gnss_ins_sim_left_out(terms: AccelNoiseTerms) -> dict[str, str]:
    """The terms `to_gnss_ins_sim` cannot carry, each with the reason: {IEEE symbol: why}."""
    si = _terms(terms)
    left_out = {}
    if _present(si.random_walk):
        left_out["K"] = "no random-walk bias in gnss-ins-sim"
    if _present(si.quantization):
        left_out["Q"] = "no quantization term in gnss-ins-sim"
    if _present(si.bias_instability) and si.bias_correlation_time is None:
        left_out["B"] = (
            "a bias instability needs bias_correlation_time: gnss-ins-sim's inf "
            "correlation time draws white per-sample noise"
        )
    return left_out


# --- IEEE ---------------------------------------------------------------------------------


def to_ieee(terms: AccelNoiseTerms) -> dict[str, dict]:
    """The Allan-variance coefficients under their IEEE Std 952 / 1293 names, in the units
    accelerometer specifications use and in SI. Each entry is {"name", "symbol", "value",
    "unit"}; a term absent from `terms` is absent here.

    - "N" velocity random walk [m/s/√h] (60 × m/s²/√Hz); "N_ug" the same as a noise density
      [µg/√Hz] (two-sided convention: a one-sided ASD is √2 larger); "N_si" [m/s²/√Hz].
    - "B" bias instability [µg]; "B_si" [m/s²] (the flicker coefficient; ADEV floor 0.664 B).
    - "K" acceleration random walk [m/s/h^(3/2)] (216 000 × m/s²/√s); "K_ug" [µg/√h]
      (60e6/9.80665 × m/s²/√s); "K_si" [m/s³/√Hz].
    - "Q" quantization noise [m/s] (SI already).
    - "tau_c" bias correlation time [s], when the bias is a Gauss–Markov one.
    """
    si = _terms(terms)
    out = {}

    def put(key, symbol, name, value, unit):
        out[key] = {"name": name, "symbol": symbol, "value": float(value), "unit": unit}

    n = si.noise_density
    put("N", "N", "velocity random walk", density_to_vrw(n), "m/s/√h")
    put("N_ug", "N", "velocity random walk (noise density)", si_to_micro_g(n), "µg/√Hz")
    put("N_si", "N", "velocity random walk", n, "m/s²/√Hz")
    if si.bias_instability is not None:
        b = si.bias_instability
        put("B", "B", "bias instability", si_to_micro_g(b), "µg")
        put("B_si", "B", "bias instability", b, "m/s²")
    if si.bias_correlation_time is not None:
        put("tau_c", "τ_c", "bias correlation time", si.bias_correlation_time, "s")
    if si.random_walk is not None:
        k = si.random_walk
        put("K", "K", "acceleration random walk", k * _HOUR_3_2, "m/s/h^(3/2)")
        put("K_ug", "K", "acceleration random walk", si_to_micro_g(k) * _SQRT_HOUR, "µg/√h")
        put("K_si", "K", "acceleration random walk", k, "m/s³/√Hz")
    if si.quantization is not None:
        put("Q", "Q", "quantization noise", si.quantization, "m/s")
    return out
