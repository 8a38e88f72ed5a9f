"""Noise models — white noise, first-order Gauss-Markov, exponential-cosine, random walk and
their sums — as `eqx.Module`s with positive array fields, each giving its exact discrete
state-space form (no approximation in Δt) and, where stationary, its autocovariance. GM
x_{k+1} = φ x_k + w, φ = e^{−Δ/τ}, var w = σ²(1 − φ²). The exponential-cosine autocovariance
σ² e^{−α|τ|} cos βτ is that of the first component of the 2-D state s_{k+1} = e^{−αΔ}
Rot(βΔ) s_k + w, cov w = σ²(1 − e^{−2αΔ}) I (a damped rotation; the continuous form is ds =
(−α I + β J) s dt + σ√(2α) dW). The paper's second-order shaping filter (17), with
b² = α² + β², is garbled in the source; read as the standard form σ√(2α)(p + b)/(p² + 2αp +
b²) driven by unit white noise it has exactly the autocorrelation (16) (its spectrum is
2ασ²(ω² + b²)/((b² − ω²)² + 4α²ω²), that of (16); tests/test_noise.py checks the two
autocovariances through the filter's Lyapunov covariance). Without the zero at −b, a constant
numerator gives e^{−α|τ|}(cos βτ + (α/β) sin β|τ|) instead. Either way the process
identified is (16), realised here exactly. Random walk x_{k+1} = x_k + w, var w = q
Δ, with a diffuse start. `simulate_noise` draws records from a model and `model_parameters`
lists its parameters as plain floats.

This module is the one definition of the noise spectra that the Whittle fits use (the
sensor analysis `spectral` and the noise diagnosis `accel_jax.diagnose.noise.fit`): each
model's `spectrum(ω, Δ)` is its two-sided spectral density per sample, f(ω) at ω in
rad/sample, |ω| ≤ π, with R_k = (1/2π) ∫ f(ω) e^{iωk} dω (the continuous two-sided PSD
below the Nyquist frequency is Δ f(2πfΔ), aliasing aside), computed by a static
`discrete_spectrum` of the per-sample parameters, which the fits call with their own
parameterisation. Two further pieces of the sensor's model live here, without a state-space
form: `Flicker` (1/f noise, f_c = B²/|ω|) and `ButterworthLowPass` (the output low-pass, a
gain on the spectrum); `difference_parts` assembles the spectrum of the first difference of
a record (the Whittle fits' y_k = x_k − x_{k−1}). tests/test_noise_one_model.py checks the
spectra against the autocovariances (and so the state-space forms) and each path's spectrum
against these. The record's deterministic terms (periodic lines, the start-up transient)
are `mean_models`'.
"""

from __future__ import annotations

import math
from typing import cast

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike

from .._params import _as_float, _concrete, _shown
from .record import Scalar, Series, _sample_interval


def _positive_fields(self, units: dict[str, str]):
    for name, unit in units.items():
        value = _concrete(getattr(self, name))
        if value is not None and not (np.all(np.isfinite(value)) and np.all(value > 0)):
            raise ValueError(
                f"{type(self).__name__}.{name} must be positive and finite, got "
                f"{_shown(value)} {unit}."
            )


class Frequencies(eqx.Module):
    """Angular frequencies ω [rad/sample] with sin(ω/2) and cos(ω/2), from which every
    discrete spectrum here is written with arithmetic alone (1 − cos ω = 2 sin²(ω/2), and
    sin((ω ∓ θ)/2) by the angle-sum rule). Every `discrete_spectrum` and `discrete_gain`
    takes either ω or this; a fit that evaluates the spectra at the same frequencies
    thousands of times builds it once (`Frequencies.of`). Measured on the 2-core CPU, one
    core: the value and gradient of the sensor analysis's spectra on a grid of 8,193
    frequencies (an 8,000-sample record) took 2.65 ms with a sine, cosine or tangent per
    frequency and component, 0.37 ms from this."""

    omega: Array
    half_sin: Array
    half_cos: Array

    @classmethod
    def of(cls, omega) -> Frequencies:
        omega = jnp.asarray(omega)
        return cls(omega, jnp.sin(omega / 2), jnp.cos(omega / 2))

    @classmethod
    def table(cls, omega) -> Frequencies:
        """The same from concrete ω, computed on the host in NumPy float64 (a fit's fixed
        frequencies, e.g. a periodogram's bins and its correction grid)."""
        omega = np.asarray(omega, np.float64)
        return cls(
            jnp.asarray(omega), jnp.asarray(np.sin(omega / 2)), jnp.asarray(np.cos(omega / 2))
        )


def _frequencies(omega) -> Frequencies:
    """`omega` as `Frequencies` (built with `Frequencies.of` unless it already is)."""
    return omega if isinstance(omega, Frequencies) else Frequencies.of(omega)


def differencing_gain(omega) -> Array:
    """λ(ω) = |1 − e^{−iω}|² = 2 − 2 cos ω = 4 sin²(ω/2): the power gain of the first
    difference (`omega`: ω or `Frequencies`)."""
    return 4 * _frequencies(omega).half_sin ** 2


def _poisson(half_sin, decay) -> Array:
    """(1 − ρ²)/|1 − ρ e^{−iu}|² with sin(u/2) = `half_sin`, written as (1 − ρ)(1 + ρ)/((1 −
    ρ)² + 4ρ sin²(u/2)): exact near u = 0 as ρ → 1, where 1 − ρ² and 1 − 2ρ cos u + ρ²
    cancel."""
    gap = 1 - decay
    return gap * (1 + decay) / (gap**2 + 4 * decay * half_sin**2)


def difference_parts(omega, coloured, increment, gain=None, floor=None) -> tuple[Array, Array]:
    """The spectral density of y_k = x_k − x_{k−1} for x = ℓ + h * c + p (a level ℓ that
    walks, a noise c of spectrum `coloured` seen through a low-pass of power `gain` H(ω), a
    white floor p of variance `floor` after it), in two parts: (stationary λ(H f_c + p),
    random-walk H qΔ) with `increment` the walk's difference spectrum qΔ; their sum is f_y.
    `gain` None: no low-pass (H = 1); `floor` None: p = 0."""
    filtered = coloured if gain is None else gain * coloured
    if floor is not None:
        filtered = filtered + floor
    return differencing_gain(omega) * filtered, increment if gain is None else gain * increment


class AbstractNoiseModel(eqx.Module):
    """A scalar noise process observed every Δ seconds.

    Concrete models give `state_space(Δ)` = (F, Q, H, P0, r): a latent linear Gaussian state
    with stationary (or diffuse) prior P0 and additive white observation variance r; and,
    where stationary, `autocovariance(τ)`. All array fields are positive parameters.
    """

    def state_space(self, sample_interval) -> tuple[Array, Array, Array, Array, Array]:
        raise NotImplementedError

    def autocovariance(self, lag_times) -> Array:
        raise NotImplementedError

    def spectrum(self, omega, sample_interval) -> Array:
        """Two-sided spectral density per sample f(ω), ω in rad/sample (module docstring)."""
        raise NotImplementedError

    def difference_spectrum(self, omega, sample_interval) -> Array:
        """Spectral density of the first difference x_k − x_{k−1}: λ(ω) f(ω)."""
        return differencing_gain(omega) * self.spectrum(omega, sample_interval)

    def one_sided_psd(self, frequency, sample_interval) -> Array:
        """One-sided PSD [unit²/Hz] of the sampled process at `frequency` [Hz] up to the
        Nyquist frequency: 2Δ f(2πfΔ) (2Δσ² for white noise)."""
        omega = 2 * math.pi * jnp.asarray(frequency) * sample_interval
        return 2 * sample_interval * self.spectrum(omega, sample_interval)

    @property
    def name(self) -> str:
        raise NotImplementedError

    @property
    def stationary(self) -> bool:
        return True


class WhiteNoise(AbstractNoiseModel):
    """White noise, R(τ) = σ² δ_{τ,0} (per sample). **Fields:** `sigma`: σ [record unit]."""

    sigma: Scalar = eqx.field(converter=_as_float)

    def __check_init__(self):
        _positive_fields(self, {"sigma": "(record unit)"})

    @property
    def name(self) -> str:
        return "white"

    def state_space(self, sample_interval):
        zero = jnp.zeros((1, 1), self.sigma.dtype)
        return zero, zero, zero, zero, self.sigma**2

    def autocovariance(self, lag_times):
        lag_times = jnp.asarray(lag_times)
        return jnp.where(lag_times == 0, self.sigma**2, 0.0)

    @staticmethod
    def discrete_spectrum(omega, variance) -> Array:
        """f(ω) = σ² (variance σ² per sample)."""
        return jnp.broadcast_to(variance, jnp.shape(_frequencies(omega).omega))

    def spectrum(self, omega, sample_interval):
        return self.discrete_spectrum(omega, self.sigma**2)


class GaussMarkov(AbstractNoiseModel):
    """First-order Gauss-Markov process (7)-(8): Δ' = −Δ/τ_c + σ √(2/τ_c) w.

    R(τ) = σ² e^{−|τ|/τ_c}; α = 1/τ_c. **Fields:** `sigma`: σ [record unit];
    `correlation_time`: τ_c [s].
    """

    sigma: Scalar = eqx.field(converter=_as_float)
    correlation_time: Scalar = eqx.field(converter=_as_float)

    def __check_init__(self):
        _positive_fields(self, {"sigma": "(record unit)", "correlation_time": "s"})

    @property
    def name(self) -> str:
        return "gauss_markov"

    def state_space(self, sample_interval):
        phi = jnp.exp(-sample_interval / self.correlation_time)
        var = self.sigma**2
        f = jnp.reshape(phi, (1, 1))
        q = jnp.reshape(var * -jnp.expm1(-2 * sample_interval / self.correlation_time), (1, 1))
        h = jnp.ones((1, 1), f.dtype)
        return f, q, h, jnp.reshape(var, (1, 1)), jnp.zeros((), f.dtype)

    def autocovariance(self, lag_times):
        return self.sigma**2 * jnp.exp(-jnp.abs(jnp.asarray(lag_times)) / self.correlation_time)

    @staticmethod
    def discrete_spectrum(omega, variance, decay) -> Array:
        """f(ω) = σ² (1 − ρ²)/|1 − ρ e^{−iω}|², the spectrum of R_k = σ² ρ^|k|
        (`variance` σ², `decay` ρ = e^{−Δ/τ_c})."""
        return variance * _poisson(_frequencies(omega).half_sin, decay)

    def spectrum(self, omega, sample_interval):
        decay = jnp.exp(-sample_interval / self.correlation_time)
        return self.discrete_spectrum(omega, self.sigma**2, decay)


class ExponentialCosine(AbstractNoiseModel):
    """Exponential-cosine process (16): R(τ) = σ² e^{−α|τ|} cos βτ.

    Realised exactly as the first component of a damped rotation (see the module
    docstring). **Fields:** `sigma`: σ [record unit]; `decay_rate`: α [1/s];
    `angular_frequency`: β [rad/s].
    """

    sigma: Scalar = eqx.field(converter=_as_float)
    decay_rate: Scalar = eqx.field(converter=_as_float)
    angular_frequency: Scalar = eqx.field(converter=_as_float)

    def __check_init__(self):
        _positive_fields(
            self, {"sigma": "(record unit)", "decay_rate": "1/s", "angular_frequency": "rad/s"}
        )

    @property
    def name(self) -> str:
        return "exp_cosine"

    def state_space(self, sample_interval):
        decay = jnp.exp(-self.decay_rate * sample_interval)
        refresh = -jnp.expm1(-2 * self.decay_rate * sample_interval)  # 1 − ρ², to full precision
        rotation = self.angular_frequency * sample_interval
        return self.discrete_state_space(self.sigma**2, decay, rotation, refresh)

    @staticmethod
    def discrete_state_space(variance, decay, rotation, refresh=None):
        """(F, Q, H, P0, r) of the per-sample parameters (`variance` σ², `decay` ρ = e^{−αΔ},
        `rotation` θ = βΔ): F = ρ Rot(θ), Q = σ²(1 − ρ²) I, H = [1, 0], P0 = σ² I, r = 0.
        Finite, with finite derivatives, at ρ = 0 and σ² = 0 (a fit's nominal candidate: no
        log of ρ is taken); at θ = 0 the Gauss–Markov process in s₁. `refresh`: 1 − ρ² where
        the caller has it to better precision (`state_space`: −expm1(−2αΔ))."""
        along, across = decay * jnp.cos(rotation), decay * jnp.sin(rotation)
        f = jnp.array([[along, -across], [across, along]])
        refresh = 1 - decay**2 if refresh is None else refresh
        eye = jnp.eye(2, dtype=f.dtype)
        q = variance * refresh * eye
        h = jnp.array([[1.0, 0.0]], dtype=f.dtype)
        return f, q, h, variance * eye, jnp.zeros((), f.dtype)

    def autocovariance(self, lag_times):
        lag_times = jnp.asarray(lag_times)
        return (
            self.sigma**2
            * jnp.exp(-self.decay_rate * jnp.abs(lag_times))
            * jnp.cos(self.angular_frequency * lag_times)
        )

    @staticmethod
    def discrete_spectrum(omega, variance, decay, rotation) -> Array:
        """f(ω) = σ²/2 [P(ω − θ) + P(ω + θ)], P(u) = (1 − ρ²)/(1 − 2ρ cos u + ρ²), the
        spectrum of R_k = σ² ρ^|k| cos kθ (`variance` σ², `decay` ρ = e^{−αΔ}, `rotation`
        θ = βΔ; at θ = 0 the Gauss–Markov spectrum)."""
        f = _frequencies(omega)
        # sin((ω ∓ θ)/2) by the angle-sum rule: no transcendental per frequency
        along, across = f.half_sin * jnp.cos(rotation / 2), f.half_cos * jnp.sin(rotation / 2)
        return variance / 2 * (_poisson(along - across, decay) + _poisson(along + across, decay))

    def spectrum(self, omega, sample_interval):
        decay = jnp.exp(-self.decay_rate * sample_interval)
        rotation = self.angular_frequency * sample_interval
        return self.discrete_spectrum(omega, self.sigma**2, decay, rotation)


class RandomWalk(AbstractNoiseModel):
    """Random walk x' = √q w (rate random walk for a gyro, velocity random walk for an
    accelerometer's integral): var(x_{k+1} − x_k) = q Δ. Not stationary (no
    autocovariance); its start is diffuse. **Fields:** `intensity`: q [record unit²/s]."""

    intensity: Scalar = eqx.field(converter=_as_float)

    def __check_init__(self):
        _positive_fields(self, {"intensity": "(record unit)²/s"})

    @property
    def name(self) -> str:
        return "random_walk"

    @property
    def stationary(self) -> bool:
        return False

    def state_space(self, sample_interval):
        one = jnp.ones((1, 1), self.intensity.dtype)
        # P0 = −1 flags "diffuse": `_state_space` replaces it by _DIFFUSE × var(record).
        return one, self.intensity * sample_interval * one, one, -one, jnp.zeros((), one.dtype)

    def autocovariance(self, lag_times):
        raise ValueError("RandomWalk is not stationary: it has no autocovariance R(τ).")

    @staticmethod
    def discrete_difference_spectrum(omega, increment) -> Array:
        """The spectrum of the walk's increments, white: qΔ (`increment` qΔ)."""
        return jnp.broadcast_to(increment, jnp.shape(_frequencies(omega).omega))

    def spectrum(self, omega, sample_interval):
        """The pseudo-spectrum qΔ/λ(ω) (infinite at ω = 0)."""
        return self.intensity * sample_interval / differencing_gain(omega)

    def difference_spectrum(self, omega, sample_interval):
        return self.discrete_difference_spectrum(omega, self.intensity * sample_interval)


class Flicker(AbstractNoiseModel):
    """Flicker (1/f, bias-instability) noise of IEEE Std 952 coefficient B: two-sided PSD
    S(f) = B²/(2π|f|), so f(ω) = S(ω/2πΔ)/Δ = B²/|ω| per sample (Δ drops out) and the
    Allan deviation's floor is √(2 ln 2/π)·B = 0.664 B. No finite state-space form and no
    autocovariance (`state_space` and `autocovariance` raise); its spectrum is defined as 0
    at ω = 0. **Fields:** `coefficient`: B [record unit]."""

    coefficient: Scalar = eqx.field(converter=_as_float)

    def __check_init__(self):
        _positive_fields(self, {"coefficient": "(record unit)"})

    @property
    def name(self) -> str:
        return "flicker"

    @property
    def stationary(self) -> bool:
        return False

    def state_space(self, sample_interval):
        raise ValueError("Flicker noise has no finite state-space form.")

    def autocovariance(self, lag_times):
        raise ValueError("Flicker noise has no autocovariance R(τ) (its variance diverges).")

    @staticmethod
    def discrete_spectrum(omega, coefficient_squared) -> Array:
        """f(ω) = B²/|ω|, 0 at ω = 0 (`coefficient_squared` B²)."""
        size = jnp.abs(_frequencies(omega).omega)
        safe = jnp.where(size > 0, size, 1.0)
        return jnp.where(size > 0, coefficient_squared / safe, 0.0)

    def spectrum(self, omega, sample_interval):
        return self.discrete_spectrum(omega, self.coefficient**2)


_HALF_COS_AT_NYQUIST = math.cos(math.pi * (1 - 1e-12) / 2)


class HighFrequencyNoise(AbstractNoiseModel):
    """Noise whose spectrum rises above a corner f_h to a plateau σ_h² at the Nyquist
    frequency: white noise through a second-order Butterworth high-pass (bilinear
    transform), f(ω) = σ_h² (1 − H(ω)) with H the `ButterworthLowPass` gain of corner f_h —
    a servo loop's noise gain beyond its bandwidth, or a converter's shaped quantisation
    noise. A spectrum only: its state-space form (second order) and autocovariance are not
    written out (no path filters through it; both raise). **Fields:** `sigma`: σ_h [record
    unit]; `corner_frequency`: f_h [Hz]."""

    sigma: Scalar = eqx.field(converter=_as_float)
    corner_frequency: Scalar = eqx.field(converter=_as_float)

    def __check_init__(self):
        _positive_fields(self, {"sigma": "(record unit)", "corner_frequency": "Hz"})

    @property
    def name(self) -> str:
        return "high_frequency_noise"

    def state_space(self, sample_interval):
        raise ValueError("HighFrequencyNoise is a spectrum only: no state-space form is written.")

    def autocovariance(self, lag_times):
        raise ValueError("HighFrequencyNoise is a spectrum only: no autocovariance is written.")

    @staticmethod
    def discrete_spectrum(omega, variance, corner) -> Array:
        """f(ω) = σ_h² (1 − H(ω)) at `corner` = π f_h Δ (`variance` σ_h²)."""
        return variance * (1 - ButterworthLowPass.discrete_gain(omega, corner, 2))

    def spectrum(self, omega, sample_interval):
        corner = math.pi * self.corner_frequency * sample_interval
        return self.discrete_spectrum(omega, self.sigma**2, corner)


class ButterworthLowPass(eqx.Module):
    """The sensor's output low-pass: a Butterworth filter of order N (1–4; bilinear
    transform) and corner f_b, power gain H(ω) = 1/(1 + (tan(|ω|/2)/tan(π f_b Δ))^{2N}) —
    exactly 1 at f_b = the Nyquist frequency. A gain on the spectrum of the noise it
    filters (its state-space form, an ARMA filter of order N, is not written out: no path
    filters through it). **Fields:** `corner_frequency`: f_b [Hz]; `order`: N (default 2)."""

    corner_frequency: Scalar = eqx.field(converter=_as_float)
    order: int = eqx.field(static=True, default=2)

    def __check_init__(self):
        _positive_fields(self, {"corner_frequency": "Hz"})
        if self.order not in (1, 2, 3, 4):
            raise ValueError(f"ButterworthLowPass order must be 1, 2, 3 or 4, got {self.order!r}.")

    @staticmethod
    def squared_ratio(omega, corner) -> Array:
        """r² = (tan(|ω|/2)/tan(`corner`))², the bilinear transform's frequency over the
        prewarped corner (tan(|ω|/2) = |sin(ω/2)|/cos(ω/2) held finite at ω = π: the cosine
        at least that of |ω| = π(1 − 10⁻¹²))."""
        f = _frequencies(omega)
        tangent = jnp.abs(f.half_sin) / jnp.maximum(f.half_cos, _HALF_COS_AT_NYQUIST)
        return (tangent / jnp.tan(corner)) ** 2

    @staticmethod
    def discrete_gain(omega, corner, order: ArrayLike = 2) -> Array:
        """H(ω) at `corner` = π f_b Δ ∈ (0, π/2] for |ω| ≤ π and order N ∈ {1, 2, 3, 4}
        (traced or not), r² from `squared_ratio`."""
        r2 = ButterworthLowPass.squared_ratio(omega, corner)
        r4 = r2 * r2
        order = jnp.asarray(order)
        # r^{2N} by products (a traced N through `power` costs a log and an exp per bin)
        steep = jnp.where(order <= 3, r4 * r2, r4 * r4)
        ratio = jnp.where(order <= 1, r2, jnp.where(order <= 2, r4, steep))
        return 1 / (1 + ratio)

    def gain(self, omega, sample_interval) -> Array:
        corner = math.pi * self.corner_frequency * sample_interval
        return self.discrete_gain(omega, corner, self.order)


class NoiseSum(AbstractNoiseModel):
    """Sum of independent noise processes (block-diagonal state, summed white variance).
    **Fields:** `components`: a tuple of models (not nested sums)."""

    components: tuple

    def __check_init__(self):
        if len(self.components) < 2:
            raise ValueError(f"NoiseSum needs at least two components, got {len(self.components)}.")
        for c in self.components:
            if not isinstance(c, AbstractNoiseModel) or isinstance(c, NoiseSum):
                raise ValueError(f"NoiseSum components must be single noise models, got {c!r}.")

    @property
    def name(self) -> str:
        return "+".join(c.name for c in self.components)

    @property
    def stationary(self) -> bool:
        return all(c.stationary for c in self.components)

    def state_space(self, sample_interval):
        import jax.scipy.linalg as jsl

        parts = [c.state_space(sample_interval) for c in self.components]
        f = jsl.block_diag(*[p[0] for p in parts])
        q = jsl.block_diag(*[p[1] for p in parts])
        h = jnp.concatenate([p[2] for p in parts], axis=1)
        p0 = jsl.block_diag(*[p[3] for p in parts])
        r = cast(Array, sum(p[4] for p in parts))  # an array: ≥ 2 components, not the 0 start
        return f, q, h, p0, r

    def autocovariance(self, lag_times):
        return cast(Array, sum(c.autocovariance(lag_times) for c in self.components))

    def spectrum(self, omega, sample_interval):
        return cast(Array, sum(c.spectrum(omega, sample_interval) for c in self.components))

    def difference_spectrum(self, omega, sample_interval):
        parts = (c.difference_spectrum(omega, sample_interval) for c in self.components)
        return cast(Array, sum(parts))


def simulate_noise(
    model: AbstractNoiseModel, sample_interval: float, num_samples: int, *, key: Array
) -> Series:
    """One record of `num_samples` samples of the model, exactly in discrete time
    (stationary start; a random walk starts at 0). Jit/vmap-safe over `key`."""
    if int(num_samples) < 1:
        raise ValueError(f"simulate_noise: num_samples must be ≥ 1, got {num_samples!r}.")
    _sample_interval("simulate_noise", sample_interval)
    f, q, h, p0, r = model.state_space(sample_interval)
    p0 = jnp.where(p0 < 0, 0.0, p0)
    n = f.shape[0]
    dtype = f.dtype

    def root(cov):
        vals, vecs = jnp.linalg.eigh(0.5 * (cov + cov.T))
        return vecs * jnp.sqrt(jnp.clip(vals, 0.0))

    k0, kw, kv = jax.random.split(key, 3)
    x0 = root(p0) @ jax.random.normal(k0, (n,), dtype)
    w = jax.random.normal(kw, (num_samples, n), dtype) @ root(q).T
    v = jnp.sqrt(r) * jax.random.normal(kv, (num_samples,), dtype)

    def step(x, w_k):
        return f @ x + w_k, x

    _, states = jax.lax.scan(step, x0, w)
    return states @ h[0] + v


def model_parameters(model: AbstractNoiseModel) -> dict[str, float]:
    """Plain floats keyed by component and parameter name, units in the key."""
    units = {
        "sigma": "",
        "correlation_time": "_s",
        "decay_rate": "_per_s",
        "angular_frequency": "_rad_per_s",
        "intensity": "_unit2_per_s",
        "coefficient": "",
    }
    components = model.components if isinstance(model, NoiseSum) else (model,)
    out = {}
    for c in components:
        for field, suffix in units.items():
            if hasattr(c, field):
                out[f"{c.name}.{field}{suffix}"] = float(getattr(c, field))
    return out
