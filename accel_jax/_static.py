"""Static transfer function of a navigation accelerometer and its basic error (docs/models.md §3).

The static transfer function works in units of g, as the paper does; ppm and mg appear only
at the edges (presets, tables, reports). Every unit conversion of this part of the package
lives here: `PPM`, `MILLI_G`, `STANDARD_GRAVITY`, `to_ppm`.

Precision: the coefficients are 1e-8..1e-3 and the errors they cause are ppm-level; float32
resolves 1 g only to 6e-8 g, so evaluate in float64 (`jax.config.update("jax_enable_x64",
True)`) whenever a ppm-level *difference* is taken. The functions keep the caller's dtype.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._params import _as_float as _as_float_weak
from ._params import _concrete

PPM = 1e-6
"""One part per million: 1 ppm of a coefficient = 1e-6 in the g-unit convention below."""
MILLI_G = 1e-3
"""1 mg in g."""
STANDARD_GRAVITY = 9.80665
"""1 g in m/s² (the only g → SI conversion factor of the package's static model)."""


def _as_float(value) -> Array:
    # As `_params._as_float`, but never weakly typed: modules built from Python scalars and
    # from arrays then share one pytree type signature, so jit does not retrace between them.
    array = _as_float_weak(value)
    if isinstance(array, jax.core.Tracer) or not getattr(array, "weak_type", False):
        return array
    return jnp.array(array, dtype=array.dtype)


def to_ppm(value: ArrayLike) -> Array:
    """A dimensionless (or g-per-g^n) coefficient, or an error in g at 1 g, as ppm."""
    return jnp.asarray(value) / PPM


def g_to_si(value: ArrayLike) -> Array:
    """An acceleration in g as m/s²."""
    return jnp.asarray(value) * STANDARD_GRAVITY


def si_to_g(value: ArrayLike) -> Array:
    """An acceleration in m/s² as g."""
    return jnp.asarray(value) / STANDARD_GRAVITY


COEFFICIENTS = (
    "bias",
    "asymmetry",
    "scale_factor_error",
    "k2",
    "k3",
    "k4",
    "k5",
    "m1",
    "m2",
    "m31",
    "m32",
)
"""Field names of `StaticTransferFunction`, in the paper's order (a0, A1, δ, k2..k5, m…)."""

COEFFICIENT_UNITS = {
    "bias": "g",
    "asymmetry": "1",
    "scale_factor_error": "1",
    "k2": "1/g",
    "k3": "1/g²",
    "k4": "1/g³",
    "k5": "1/g⁴",
    "m1": "1",
    "m2": "1",
    "m31": "1/g",
    "m32": "1/g",
}
"""SI-free units of each coefficient (accelerations in g); ×1e6 gives the paper's ppm units."""

PPM_UNITS = {
    name: {"g": "µg", "1": "ppm"}.get(unit, "ppm" + unit[1:])
    for name, unit in COEFFICIENT_UNITS.items()
}
"""The paper's display units of each coefficient ×1e6: a0 in µg, δ and A1 in ppm, k2 in ppm/g,
k3 in ppm/g², …"""


class StaticTransferFunction(eqx.Module):
    """Static transfer function of a pendulum accelerometer in acceleration units, eq. (1):

        a_F = a0 + (1 + ½ A1 sign a3 + δ) a3 + k2 a3² + k3 a3³ + k4 a3⁴ + k5 a3⁵
              + m1 a1 + m2 a2 + m31 a3 a1 + m32 a3 a2                                  [g]

    with a3 the apparent acceleration along the input axis (IA), a1 along the output axis
    (OA), a2 along the pendulum axis (PA), all in g. The output-voltage form is K1·a_F.

    Every field is an array leaf (so `jax.grad`, `jax.vmap` and optimistix fits act on them);
    finiteness is checked on construction when the values are concrete. Coefficients are
    stored as plain numbers in g-units (1 ppm = 1e-6); use `from_ppm` to build from the
    paper's tables.

    **Fields:**

    - `bias`: a0 [g].
    - `asymmetry`: A1 [1], scale-factor asymmetry (scale factor 1 ± A1/2 for a3 ≷ 0).
    - `scale_factor_error`: δ(ω) [1], the scale-factor deviation at the frequency of the
      measured acceleration (0 Hz for the static case; a linear term, so it leaves the mean
      output under zero-mean vibration unchanged).
    - `k2`, `k3`, `k4`, `k5`: nonlinearity [1/g, 1/g², 1/g³, 1/g⁴].
    - `m1`, `m2`: additive cross-sensitivity to a1, a2 [1].
    - `m31`, `m32`: multiplicative cross-coupling a3·a1, a3·a2 [1/g].
    """

    bias: Float[Array, ""] = eqx.field(converter=_as_float, default=0.0)
    asymmetry: Float[Array, ""] = eqx.field(converter=_as_float, default=0.0)
    scale_factor_error: Float[Array, ""] = eqx.field(converter=_as_float, default=0.0)
    k2: Float[Array, ""] = eqx.field(converter=_as_float, default=0.0)
    k3: Float[Array, ""] = eqx.field(converter=_as_float, default=0.0)
    k4: Float[Array, ""] = eqx.field(converter=_as_float, default=0.0)
    k5: Float[Array, ""] = eqx.field(converter=_as_float, default=0.0)
    m1: Float[Array, ""] = eqx.field(converter=_as_float, default=0.0)
    m2: Float[Array, ""] = eqx.field(converter=_as_float, default=0.0)
    m31: Float[Array, ""] = eqx.field(converter=_as_float, default=0.0)
    m32: Float[Array, ""] = eqx.field(converter=_as_float, default=0.0)

    def __check_init__(self):
        for name in COEFFICIENTS:
            value = _concrete(getattr(self, name))
            if value is not None and not np.all(np.isfinite(value)):
                raise ValueError(
                    f"StaticTransferFunction.{name} must be finite, got {value!r} "
                    f"{COEFFICIENT_UNITS[name]}."
                )

    @classmethod
    def from_ppm(cls, *, bias_mg: float = 0.0, **ppm) -> StaticTransferFunction:
        """Build from the paper's units: `bias_mg` [mg], every other coefficient in ppm
        (A1 [ppm], k_n [ppm/g^(n−1)], m_i [ppm], m_3i [ppm/g])."""
        unknown = set(ppm) - set(COEFFICIENTS[1:])
        if unknown:
            raise ValueError(
                f"Unknown coefficient(s) {sorted(unknown)}; valid names are "
                f"{list(COEFFICIENTS[1:])} (ppm) and bias_mg (mg)."
            )
        return cls(bias=bias_mg * MILLI_G, **{k: v * PPM for k, v in ppm.items()})

    @classmethod
    def aks05(cls) -> StaticTransferFunction:
        """AKS-05 passport coefficients, the paper's Table 4 (a0 = 0.5 mg, A1 = 15 ppm,
        k2 = 2 ppm/g, k3 = 7 ppm/g², k4 = 0.02 ppm/g³, k5 = 0.3 ppm/g⁴; δ, m not given: 0)."""
        return cls.from_ppm(bias_mg=0.5, asymmetry=15, k2=2, k3=7, k4=0.02, k5=0.3)

    @classmethod
    def al1m(cls) -> StaticTransferFunction:
        """AL-1M passport coefficients, the paper's Table 4 (a0 = 1.2 mg, A1 = 25 ppm,
        k2 = 105 ppm/g, k3 = 87 ppm/g², k4 = 10 ppm/g³, k5 = 0.9 ppm/g⁴; δ, m not given: 0)."""
        return cls.from_ppm(bias_mg=1.2, asymmetry=25, k2=105, k3=87, k4=10, k5=0.9)

    def as_ppm(self) -> dict[str, float]:
        """Plain floats for JSON: `bias_mg` [mg] and every other coefficient in ppm units."""
        out = {"bias_mg": float(self.bias) / MILLI_G}
        out.update({name: float(getattr(self, name)) / PPM for name in COEFFICIENTS[1:]})
        return out


def indicated_acceleration(
    tf: StaticTransferFunction,
    a3: ArrayLike,
    a1: ArrayLike = 0.0,
    a2: ArrayLike = 0.0,
) -> Array:
    """The accelerometer's indicated acceleration a_F, eq. (1), elementwise.

    **Arguments:**

    - `tf`: the transfer-function coefficients.
    - `a3`, `a1`, `a2`: apparent accelerations along IA, OA, PA [g] (broadcast together).

    **Returns:** a_F [g]. Pure and jit/vmap/grad-safe (the gradient of |a3| at exactly 0 is
    JAX's convention for `abs`, 0). Precision: the caller's dtype; see the module docstring.
    """
    a3 = jnp.asarray(a3)
    return (
        tf.bias
        + (1 + tf.scale_factor_error) * a3
        + 0.5 * tf.asymmetry * jnp.abs(a3)
        + tf.k2 * a3**2
        + tf.k3 * a3**3
        + tf.k4 * a3**4
        + tf.k5 * a3**5
        + tf.m1 * a1
        + tf.m2 * a2
        + tf.m31 * a3 * a1
        + tf.m32 * a3 * a2
    )


def basic_error(
    tf: StaticTransferFunction,
    a3: ArrayLike,
    a1: ArrayLike = 0.0,
    a2: ArrayLike = 0.0,
    *,
    include_bias: bool = True,
) -> Array:
    """The basic (no-vibration) error δ_OP, eq. (2):

        δ_OP = a0 + ½ A1 sign(a3) a3 + Σ_{n=2..5} k_n a3ⁿ + Σ_i m_i a_i + Σ_i m_3i a3 a_i   [g]

    i.e. a_F − (1 + δ) a3 (eq. (2) leaves the scale-factor deviation δ out).

    **Arguments:**

    - `tf`, `a3`, `a1`, `a2`: as in `indicated_acceleration` [g].
    - `include_bias`: False drops a0 — the form the compensation algorithm subtracts in
      step (18), a0 having been removed already in step (17).

    **Returns:** δ_OP [g]. Precision: the caller's dtype (float64 for ppm work).
    """
    err = indicated_acceleration(tf, a3, a1, a2) - (1 + tf.scale_factor_error) * jnp.asarray(a3)
    return err if include_bias else err - tf.bias


PASSPORTS = {"AKS-05": StaticTransferFunction.aks05, "AL-1M": StaticTransferFunction.al1m}
"""The paper's two accelerometers (docs/models.md §3, Table 4) by name: the constructors of their
passport transfer functions."""
