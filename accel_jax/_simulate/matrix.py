"""The small matrix functions the simulators share, each once.

- `_expm` (e^X): scaling and squaring of a degree-13 Taylor polynomial with a fixed loop of
  64 masked squarings — forward- and reverse-differentiable (the identification fits'
  implicit gradients go through it), cheaper to compile than `jax.scipy.linalg.expm`.
- `expm_minus_identity` (e^X − I) and `zoh` (Van Loan's augmented exponential): keeps full
  relative precision for the small X of a sample step; a traced squaring count (forward-
  mode differentiable only). Used by the record simulator with sub-sample change times.
- `power_rows` (row·M^i, blocked two-level doubling) and `_power_rows` / `_power_columns`
  (plain doubling of rows / columns, with `_block_size`): the power sequences of the
  blocked ZOH record and of the sequence simulator.

`discretise` (`state_space.py`) uses `jax.scipy.linalg.expm` (Padé) for the general
simulators; the three exponentials agree to ~1e-15 relative on the loop's matrices (tests).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

_Affine = Float[Array, "5 5"]
_Row = Float[Array, " 5"]


# Squarings available to `_expm`: matrices up to 1-norm 2^62.
_MAX_SQUARINGS = 64


def expm_squarings(matrix):
    """The squarings `_expm` needs for `matrix`: s with ‖X‖₁/2^s ≤ 1/4 (a float, ≥ 0)."""
    norm = jnp.max(jnp.sum(jnp.abs(matrix), axis=-2))
    return jnp.maximum(jnp.ceil(jnp.log2(jnp.maximum(norm, 1e-300) / 0.25)), 0)


def _expm(matrix, max_squarings: int = _MAX_SQUARINGS):
    """Matrix exponential of a small matrix: scaling and squaring of a Taylor polynomial.

    The matrix is scaled by 2^-s to 1-norm ≤ 1/4, where the degree-13 Taylor remainder is
    below 0.25^14/14! ≈ 2e-20, then squared s times. Cheaper to compile than the general
    `jax.scipy.linalg.expm` (which carries five Padé orders), and forward- and
    reverse-differentiable.

    `max_squarings` (static) is the loop's length: every one of them is computed under
    vmap (masked), so a caller that knows its matrices need few (`expm_squarings`) passes
    that few; the result is then bitwise the one of the full loop. A matrix that needs
    more than `max_squarings` gets NaN, never a silently wrong exponential.
    """
    squarings = jax.lax.stop_gradient(expm_squarings(matrix))
    scaled = matrix * 2.0 ** -jnp.minimum(squarings, max_squarings)
    identity = jnp.eye(matrix.shape[-1], dtype=matrix.dtype)
    result = identity
    for degree in range(13, 0, -1):  # Horner: I + A(I + A/2(I + A/3(…)))
        result = identity + scaled @ result / degree
    result = jax.lax.fori_loop(
        0,
        max_squarings,
        lambda i, power: jnp.where(i < squarings, power @ power, power),
        result,
    )
    return jnp.where(squarings <= max_squarings, result, jnp.nan)


TAYLOR_TERMS = 8
"""Taylor terms of `expm_minus_identity` on X/2^s, ‖X/2^s‖₁ ≤ 0.05: error 0.05⁹/9! ≈ 5e-18."""


def expm_minus_identity(x):
    """e^X − I by scaling and squaring in the "minus identity" form: the Taylor series of
    e^{X/2^s} − I with s the fewest squarings that bring ‖X‖₁/2^s to 0.05, then s times
    F ← 2F + F² (that is (I + F)² − I). Working with F instead of I + F keeps full relative
    precision when X is small (a sample step of a loop that is slow against it), and a stiff
    lag only costs more squarings (a loop with a traced count: forward-mode differentiable,
    and vmapped batches run to their largest count)."""
    norm = jnp.max(jnp.sum(jnp.abs(x), axis=0))
    s = jnp.clip(jnp.ceil(jnp.log2(jnp.maximum(norm, 1e-300) / 0.05)), 0, 60).astype(jnp.int32)
    scaled = x / 2.0 ** s.astype(x.dtype)
    term = scaled
    out = scaled
    for k in range(2, TAYLOR_TERMS + 1):
        term = term @ scaled / k
        out = out + term
    return jax.lax.fori_loop(0, s, lambda _, f: 2 * f + f @ f, out)


def zoh(a, b, dt):
    """(e^{AΔ}, ∫_0^Δ e^{As} ds b) of x' = A x + b u (u held over the step), from the
    exponential of the augmented matrix [[A, b], [0, 0]]Δ (Van Loan)."""
    n = a.shape[0]
    augmented = jnp.zeros((n + 1, n + 1), a.dtype).at[:n, :n].set(a).at[:n, n].set(b)
    f = expm_minus_identity(augmented * dt)
    return f[:n, :n] + jnp.eye(n, dtype=a.dtype), f[:n, n]


def power_rows(matrix, row, count: int):
    """[row·M^i for i < count], shape (count, len(row)).

    Blocked: i = kB + j with B ≈ √count; M^j (j < B) and row·M^{kB} by doubling, then one
    product row·M^{kB}·M^j for all (k, j) — a few small products and one larger one, which
    stays fast when vmapped and differentiated (a doubling of the rows alone is a long
    chain of tiny batched products)."""
    d = matrix.shape[0]
    levels = max(0, math.ceil(math.log2(max(count, 1)) / 2))
    n_outer = -(-count // 2**levels)
    stack, power = jnp.eye(d, dtype=matrix.dtype)[None], matrix
    for _ in range(levels):
        stack = jnp.concatenate([stack, stack @ power])
        power = power @ power
    outer = row[None, :]
    for _ in range(max(0, math.ceil(math.log2(n_outer)))):
        outer = jnp.concatenate([outer, outer @ power])
        power = power @ power
    return jnp.einsum("kd,jde->kje", outer[:n_outer], stack).reshape(-1, d)[:count]


def _ceil_log2(count: int) -> int:
    return max(0, math.ceil(math.log2(count))) if count > 1 else 0


def _block_size(n: int) -> int:
    """B = a power of two near √n: both factor sequences are then short."""
    return 2 ** max(0, round(math.log2(max(1.0, math.sqrt(n)))))


def _power_columns(matrix: _Affine, vector: _Row, count: int) -> tuple[Array, _Affine]:
    """[M^j v for j < 2^⌈log₂ count⌉] by doubling (rows of the result), and that power of M."""
    columns, power = vector[None, :], matrix
    for _ in range(_ceil_log2(count)):
        columns = jnp.concatenate([columns, columns @ power.T])
        power = power @ power
    return columns, power


def _power_rows(matrix: _Affine, row: _Row, count: int) -> Array:
    """[r M^m for m < 2^⌈log₂ count⌉] by doubling."""
    rows, power = row[None, :], matrix
    for _ in range(_ceil_log2(count)):
        rows = jnp.concatenate([rows, rows @ power])
        power = power @ power
    return rows
