"""The deterministic terms of a real sensor's static record — periodic lines and the start-up
transient — as `eqx.Module`s: the one definition of each, used wherever one is fitted,
evaluated or reported (`sensor_model`, `sensor`, and the open-world diagnosis's periodic
predictor, `accel_jax.diagnose.openworld`).

They are terms of the record's **mean**, x_k = ℓ + Σ_lines s_line(t_k) + s_tr(t_k) + noise
(`spectral`'s model), not noise: each gives its `signal(t)`, which the sensor-noise
selection regresses out of the record before the noise of `models` is fitted to what is
left. A line has no spectral *density*: its power A²/2 sits at ±f as two atoms of the
spectral measure (`PeriodicLine.line_spectrum`), which no `spectrum(ω)` of `models` can
hold. A transient has finite energy and no power at all: nothing of it is in the spectrum
of a long record (the selection judges it in the time domain).

Fields are parameters of any sign, kept in NumPy float64 when given as numbers (the
selection runs on the host; full precision whether or not JAX's x64 is on), as given when
JAX arrays or tracers. `signal` evaluates in NumPy when t and the fields are concrete
(exactly the arithmetic the selection always used), in `jax.numpy` otherwise (jit/vmap/
grad-safe).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike

from .models import _positive_fields


Value = Array | np.ndarray
"""A field: NumPy float64 on the host, a JAX array (or tracer) where one was given."""


def _as_float64(value: ArrayLike) -> Value:
    """A number or NumPy array as NumPy float64; a JAX array or tracer as given."""
    return value if isinstance(value, jax.Array) else np.asarray(value, np.float64)


def _on_host(*values) -> bool:
    """Whether none of `values` is a JAX array (or tracer): then NumPy evaluates."""
    return not any(isinstance(v, jax.Array) for v in values)


class PeriodicLine(eqx.Module):
    """A periodic line s(t) = c cos 2πft + s sin 2πft = A cos(2πft − φ), A = √(c² + s²),
    φ = atan2(s, c): a deterministic term of the record's mean (the `sinusoid` effect).
    **Fields:** `frequency`: f [Hz]; `cosine`: c, `sine`: s [record unit]."""

    frequency: Value = eqx.field(converter=_as_float64)
    cosine: Value = eqx.field(converter=_as_float64)
    sine: Value = eqx.field(converter=_as_float64)

    def __check_init__(self):
        if _on_host(self.frequency) and not np.all(np.isfinite(self.frequency)):
            raise ValueError(f"PeriodicLine.frequency must be finite, got {self.frequency} Hz.")

    @staticmethod
    def basis(t, frequency) -> tuple:
        """(cos 2πft, sin 2πft) at times `t` [s]: the line's regressors (a least-squares fit
        of c and s stacks them beside a constant)."""
        xp = np if _on_host(t, frequency) else jnp
        w = 2 * xp.pi * frequency * t
        return xp.cos(w), xp.sin(w)

    def signal(self, t):
        """s(t) at times `t` [s] (the term the line adds to the mean)."""
        cos, sin = self.basis(t, self.frequency)
        return self.cosine * cos + self.sine * sin

    @property
    def amplitude(self):
        """A = √(c² + s²) (a float when the fields are concrete)."""
        if _on_host(self.cosine, self.sine):
            return math.hypot(float(self.cosine), float(self.sine))
        return jnp.hypot(self.cosine, self.sine)

    @property
    def power(self):
        """The line's power, its mean square over whole periods: A²/2 [record unit²]."""
        return self.amplitude**2 / 2

    def line_spectrum(self) -> tuple[Value, Value]:
        """The line's part of the two-sided spectrum: the atoms (A²/4)[δ(f + f₀) + δ(f − f₀)]
        of the spectral measure, as ((−f₀, f₀) [Hz], (A²/4, A²/4) [record unit²]); their sum
        is `power`. A power at a frequency, not a density (no value per Hz)."""
        xp = np if _on_host(self.frequency, self.cosine, self.sine) else jnp
        quarter = self.power / 2
        return xp.stack([-self.frequency, self.frequency]), xp.stack([quarter, quarter])

    def to_dict(self) -> dict:
        """The line as the selection reports it: {"frequency_Hz", "amplitude"} (the phase is
        not reported)."""
        return {"frequency_Hz": float(self.frequency), "amplitude": float(self.amplitude)}


class StartupTransient(eqx.Module):
    """A start-up transient (a warm-up) s(t) = a e^{−t/τ}, t from the record's first sample:
    a deterministic term of the record's mean (the `startup_transient` effect). Its energy
    a²τ/2 is finite; it has no power. **Fields:** `amplitude`: a [record unit] (either
    sign); `time_constant`: τ [s] (positive; an array of them gives a template per τ)."""

    amplitude: Value = eqx.field(converter=_as_float64)
    time_constant: Value = eqx.field(converter=_as_float64)

    def __check_init__(self):
        _positive_fields(self, {"time_constant": "s"})

    def signal(self, t):
        """s(t) at times `t` [s] since the record's first sample."""
        xp = np if _on_host(t, self.amplitude, self.time_constant) else jnp
        return self.amplitude * xp.exp(-t / self.time_constant)

    def to_dict(self) -> dict:
        """The transient as the selection reports it: {"time_constant_s", "amplitude"}."""
        return {"time_constant_s": float(self.time_constant), "amplitude": float(self.amplitude)}
