"""The paper's closed forms of the vibration error: the deterministic part, eq. (19) (eqs.
4-5 with σ = 0), the random part, eq. (20) (eqs. 4-5 with b = 0), their sum, eq. (3), and
the paper's asymmetry factors `ASYMMETRY_SINE_FACTOR`, `ASYMMETRY_RANDOM_FACTOR` (beside
their exact values, see `accel_jax._vibration.expectation`).
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike

from .._static import StaticTransferFunction
from .environment import VibrationEnvironment

ASYMMETRY_SINE_FACTOR = 0.673
"""The paper's factor in A1·(0.673 b − 0.5 a) (eqs. 4, 19), the vibration error of the
asymmetry term ½A1|a3|. Its exact counterpart at a = 0: ½A1·E|b sin θ| = ½A1·(2/π) b =
A1·b/π, i.e. a factor 1/π ≈ 0.318 on A1·b (the time average of |a3| itself is (2/π) b; see
`mean_abs_sine`), so the paper's 0.673 is about 2.1× the exact value."""
ASYMMETRY_RANDOM_FACTOR = 0.125
"""The paper's factor in 0.125·A1·σ (eqs. 13, 20) for the same term under random vibration;
the exact value at a = 0: ½A1·E|σZ| = ½A1·sqrt(2/π) σ, a factor ½·sqrt(2/π) ≈ 0.399 on A1·σ."""


def paper_deterministic_error(
    tf: StaticTransferFunction,
    env: VibrationEnvironment,
    a3: ArrayLike,
    *,
    k5_quartic: float = 1.875,
) -> Array:
    """The paper's deterministic-vibration error, eq. (19) (= eqs. 4-5 with σ = 0) [g]:

        A1 (0.673 b3 − 0.5 a) + ½ k2 b3² + 1.5 k3 a b3² + k4 (3 a² b3² + 0.375 b3⁴)
        + k5 (5 a³ b3² + 1.875 a b3⁴) + ½ m31 b3 b1 + ½ m32 b3 b2.

    The paper's flights have a > 0; for a < 0 we use |a| in the A1 term (the asymmetry
    term is even in a). With no sinusoid (b3 = 0) the whole expression is 0 (the paper
    applies (19) only to deterministic vibration; literally its A1 term would leave
    −0.5·A1·a). The printed (19) has 1.185 for k5's quartic factor; (5) and the exact average give
    1.875 (pass `k5_quartic=1.185` for the printed one). The cross terms assume in-phase
    sinusoids (the paper's); phases in `env` are ignored here, unlike the exact expectation.
    """
    a = jnp.asarray(a3)
    b3, b1, b2 = env.sine_amplitude[2], env.sine_amplitude[0], env.sine_amplitude[1]
    return (
        # (19) is applied only when a sinusoid is present: its −0.5·A1·a part would
        # otherwise survive at b3 = 0, an error without vibration.
        jnp.where(b3 > 0, tf.asymmetry * (ASYMMETRY_SINE_FACTOR * b3 - 0.5 * jnp.abs(a)), 0.0)
        + 0.5 * tf.k2 * b3**2
        + 1.5 * tf.k3 * a * b3**2
        + tf.k4 * (3 * a**2 * b3**2 + 0.375 * b3**4)
        + tf.k5 * (5 * a**3 * b3**2 + k5_quartic * a * b3**4)
        + 0.5 * tf.m31 * b3 * b1
        + 0.5 * tf.m32 * b3 * b2
    )


def paper_random_error(
    tf: StaticTransferFunction, env: VibrationEnvironment, a3: ArrayLike
) -> Array:
    """The paper's random-vibration error, eq. (20) (= eqs. 4-5 with b = 0) [g]:

    0.125 A1 σ3 + k2 σ3² + 3 k3 a σ3² + k4 (6 a² σ3² + 3 σ3⁴) + k5 (10 a³ σ3² + 15 a σ3⁴)
    + m31 ρ31 σ3 σ1 + m32 ρ32 σ3 σ2.
    """
    a = jnp.asarray(a3)
    s = env.random_std
    rho = env.random_correlation
    s3 = s[2]
    return (
        ASYMMETRY_RANDOM_FACTOR * tf.asymmetry * s3
        + tf.k2 * s3**2
        + 3 * tf.k3 * a * s3**2
        + tf.k4 * (6 * a**2 * s3**2 + 3 * s3**4)
        + tf.k5 * (10 * a**3 * s3**2 + 15 * a * s3**4)
        + tf.m31 * rho[2, 0] * s3 * s[0]
        + tf.m32 * rho[2, 1] * s3 * s[1]
    )


def paper_vibration_error(
    tf: StaticTransferFunction,
    env: VibrationEnvironment,
    a3: ArrayLike,
    *,
    k5_quartic: float = 1.875,
) -> Array:
    """The paper's total vibration error (3): eq. (19) + eq. (20) [g]. The paper adds the
    deterministic and random parts; the exact expectation also has their cross moments
    (e.g. 6·(b²/2)·σ² in E w⁴), which this sum omits."""
    return paper_deterministic_error(tf, env, a3, k5_quartic=k5_quartic) + paper_random_error(
        tf, env, a3
    )
