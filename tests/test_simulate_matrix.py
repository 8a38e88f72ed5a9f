"""The small matrix functions the simulators share (accel_jax/_simulate/matrix.py): the three
matrix exponentials against each other and against JAX's Padé `expm` on the loop's own
augmented matrices, and the power sequences against explicit powers."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import accel_jax as aj
from accel_jax._simulate.matrix import (
    _block_size,
    _expm,
    _power_columns,
    _power_rows,
    expm_minus_identity,
    power_rows,
)


def test_expm_minus_identity_small_and_stiff():
    from jax.scipy.linalg import expm

    rng = np.random.default_rng(3)
    for scale in (1e-6, 1e-2, 3.0, 300.0):
        x = rng.normal(size=(5, 5)) * scale - 2 * scale * np.eye(5)
        if scale < 1e-3:  # e^X − I without the cancellation of e^X − I: its series
            exact = x + x @ x / 2 + x @ x @ x / 6
        else:
            exact = np.asarray(expm(jnp.asarray(x), max_squarings=64)) - np.eye(5)
        np.testing.assert_allclose(
            expm_minus_identity(jnp.asarray(x)), exact, rtol=1e-10, atol=1e-13 * scale
        )


@pytest.mark.parametrize("torquer_lag", [0.0, 1e-4, 1e-8])
@pytest.mark.parametrize("dt", [1e-6, 1e-4])
def test_the_three_exponentials_agree_on_the_loop(torquer_lag, dt):
    """e^{[[A, B], [0, 0]]Δ} of the loop in the simulators' scaled internal units
    (`_Loop`; docs/models.md reference device, and a stiff torquer lag of 10 ns): the Taylor
    `_expm` of the identification fits, `expm_minus_identity` + I of the sequence simulator
    and `jax.scipy.linalg.expm` (Padé) of `discretise` agree to 2e-12 of the largest entry
    (measured: ≤ 1.9e-12, the stiff lag at Δ = 0.1 ms; ≤ 3e-14 otherwise).

    Not so on the physical `state_space` matrices (entries from 1e-5 to 1e6): there Padé
    differs from both Taylor forms by 4e-9 at Δ = 0.1 ms while they agree with each other —
    the reason the simulators exponentiate the scaled matrices."""
    from accel_jax._simulate.loop import _Loop

    loop = _Loop(aj.ServoParams.reference(torquer_time_constant=torquer_lag))
    a, b = loop.a_matrix, loop.b_matrix
    n, m = b.shape
    augmented = jnp.zeros((n + m, n + m)).at[:n, :n].set(a).at[:n, n:].set(b) * dt
    pade = np.asarray(jax.scipy.linalg.expm(augmented, max_squarings=64))
    scale = np.max(np.abs(pade))
    np.testing.assert_allclose(np.asarray(_expm(augmented)), pade, rtol=0, atol=2e-12 * scale)
    minus = np.asarray(expm_minus_identity(augmented)) + np.eye(n + m)
    np.testing.assert_allclose(minus, pade, rtol=0, atol=2e-12 * scale)


def test_power_sequences_match_explicit_powers():
    rng = np.random.default_rng(7)
    matrix = jnp.asarray(np.eye(5) * 0.9 + rng.normal(size=(5, 5)) * 0.02)
    row, column = (jnp.asarray(rng.normal(size=5)) for _ in range(2))
    count = 37
    powers = [np.linalg.matrix_power(np.asarray(matrix), k) for k in range(64)]
    explicit_rows = np.stack([np.asarray(row) @ p for p in powers])
    np.testing.assert_allclose(power_rows(matrix, row, count), explicit_rows[:count], rtol=1e-12)
    rows = _power_rows(matrix, row, count)
    assert rows.shape[0] == 64  # 2^ceil(log2 37) by doubling
    np.testing.assert_allclose(rows, explicit_rows, rtol=1e-12)
    columns, power = _power_columns(matrix, column, count)
    np.testing.assert_allclose(
        columns, np.stack([p @ np.asarray(column) for p in powers]), rtol=1e-12
    )
    np.testing.assert_allclose(power, powers[1] @ powers[63], rtol=1e-11)
    assert _block_size(5001) == 64 and _block_size(1) == 1


def test_expm_short_loop_is_the_full_loop_or_nan():
    """`_expm(X, k)` runs k masked squarings: bitwise the full loop's exponential when X
    needs at most k (`expm_squarings`), NaN when it needs more — never a wrong exponential.
    The Monte Carlo kernel relies on both (its short branch for chunks that need few)."""
    from accel_jax._simulate.matrix import expm_squarings

    rng = np.random.default_rng(11)
    x = rng.normal(size=(7, 7))
    x = jnp.asarray(x * 3.0 / np.max(np.sum(np.abs(x), axis=0)))  # ‖X‖₁ = 3: 4 squarings
    assert float(expm_squarings(x)) == 4
    full = _expm(x)
    np.testing.assert_array_equal(_expm(x, 4), full)
    np.testing.assert_array_equal(jax.vmap(lambda m: _expm(m, 4))(x[None]), full[None])
    assert bool(jnp.all(jnp.isnan(_expm(x, 3))))
    np.testing.assert_allclose(full, jax.scipy.linalg.expm(x), rtol=1e-13, atol=1e-14)
    # Reverse mode through the short loop: the full loop's gradient.
    grad_short = jax.grad(lambda m: jnp.sum(_expm(m, 4) ** 2))(x)
    grad_full = jax.grad(lambda m: jnp.sum(_expm(m) ** 2))(x)
    np.testing.assert_array_equal(grad_short, grad_full)
