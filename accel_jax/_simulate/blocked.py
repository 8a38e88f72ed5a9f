"""`fast_step_response`: the identification record by block powers of the exact ZOH map
(GitHub issue 7), for constant inputs from a settled device.

`simulate_linear` steps the loop sample by sample (`lax.scan`, 5 000 sequential 4×4 products
for a 5 ms record at 1 MHz). For the identification record — a settled device, constant
inputs from t_0 on — the sampled state is an affine power sequence,

    z_k = M^k z_0,   z = [x; 1],   M = [[A_d, B_d u], [0, 1]]   (exact ZOH, 5×5),

and the output y_k = c·z_k. Writing k = m·B + j (0 ≤ j < B) splits the powers:

    y_{mB+j} = (c M^{mB}) · (M^j z_0),

a (n/B × 5) by (5 × B) matrix product. The two factor sequences are built by doubling
(log₂ B and log₂(n/B) batched products, no long sequential scan), and the record is one
small dense product — the closed modal form of the response, evaluated without an
eigendecomposition (so it stays exact and differentiable when two lag poles coincide, and
when T_dm = 0 or T_f = 0, which make A singular).

Precision: follows the dtype of the parameters (use float64; every test and benchmark
does). The record agrees with `simulate_linear` to ~2e-13 of the step in float64 (measured
on 64 drawn devices, 5 001 samples at 1 MHz; the two take the ZOH exponential by different
methods, Taylor here and Padé there, and a ~1e-16 difference grows over the powers).
`monte_carlo_oscillatory` draws the noise deviates in float32 by default (its docstring
says why that suffices); `noise_dtype` chooses.

The ZOH exponential is `_expm`'s (Taylor, scaling and squaring), whose squaring loop runs
every allowed squaring under vmap (masked): `monte_carlo_oscillatory` gives the chunks
whose devices need few a short loop (`record_squarings`), which cut the exponential from
~25 to ~6 µs per trajectory (docs/performance.md has the kernel's profile).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray

from .._params import ServoParams
from .loop import _drive_before, _grid_step, _Loop, _prepare
from .matrix import _MAX_SQUARINGS, _block_size, _expm, _power_columns, _power_rows, expm_squarings
from .state_space import equilibrium_state

_Samples = Float[Array, " n"]
_Affine = Float[Array, "5 5"]
_Row = Float[Array, " 5"]


def _augmented(params: ServoParams, ts: Array) -> Array:
    """[[A, B], [0, 0]]·Δ of the loop (7×7): its exponential is the exact ZOH step (Van Loan)."""
    loop = _Loop(params)
    a, b = loop.a_matrix, loop.b_matrix
    top = jnp.concatenate([a, b], axis=1)
    bottom = jnp.zeros((b.shape[1], top.shape[1]), top.dtype)
    return jnp.concatenate([top, bottom]) * _grid_step(ts)


def record_squarings(params: ServoParams, ts: Array) -> Array:
    """The squarings the record's ZOH exponential needs (see `_expm`)."""
    return expm_squarings(_augmented(params, ts))


def _affine_system(
    params: ServoParams, ts: Array, inputs: Array, max_squarings: int = _MAX_SQUARINGS
) -> tuple[_Affine, _Row, _Row, Array]:
    """(M, z_0, c, y_0) of the record in `_Loop`'s internal units (see the module docstring).

    `inputs` (n, 3) are constant in time (checked by the caller); only `inputs[0]` is used.
    The ZOH exponential is `_expm`'s with a loop of `max_squarings` (static) squarings.
    """
    loop = _Loop(params)
    initial = equilibrium_state(params, 0.0, inputs[0, 1], inputs[0, 2]).astype(inputs.dtype)
    exponential = _expm(_augmented(params, ts), max_squarings)
    n_states = loop.a_matrix.shape[0]
    transition = exponential[:n_states, :n_states]
    forcing = exponential[:n_states, n_states:]
    drive = forcing @ loop.scaled_inputs(inputs[0])
    dtype = inputs.dtype
    affine = jnp.zeros((5, 5), dtype).at[:4, :4].set(transition).at[:4, 4].set(drive)
    affine = affine.at[4, 4].set(1.0)
    start = jnp.concatenate([loop.to_internal(initial), jnp.ones(1, dtype)])

    # Output row for k ≥ 1 (the drive before t_k is k_dm U_test): U_f itself, or with an
    # ideal filter U_amp − T_f dU_amp/dt written on the internal state (`_Loop.to_physical`).
    scale = loop.scaling.state
    shift = loop.velocity_shift(params.torquer_gain * inputs[0, 0])
    zero = jnp.zeros((), dtype)
    ideal_filter_row = jnp.stack(
        [
            loop.gain * scale[0],
            -loop.gain * loop.filter_time_constant * scale[1],
            zero,
            zero,
            loop.gain * loop.filter_time_constant * shift,
        ]
    )
    filter_row = jnp.stack([zero, zero, zero, scale[3], zero])
    row = jnp.where(loop.ideal_filter, ideal_filter_row, filter_row)
    # y_0 is read before U_test(t_0) acts: the physical initial output.
    first = loop.to_physical(start[None, :4], _drive_before(loop, inputs[:1], initial))[0, 3]
    return affine, start, row, first


def _record_of_system(system, n: int) -> _Samples:
    """The n-sample record of `_affine_system`'s (M, z_0, c, y_0), by block powers."""
    affine, start, row, first = system
    block = _block_size(n)
    n_blocks = -(-n // block)
    columns, block_power = _power_columns(affine, start, block)  # M^j z_0, (B, 5)
    rows = _power_rows(block_power, row, n_blocks)[:n_blocks]  # c M^{mB}, (n/B, 5)
    record = (rows @ columns[:block].T).reshape(-1)[:n]
    return record.at[0].set(first)


def _constant_inputs(params, ts, test_voltage, acceleration, external_moment):
    for name, value in (
        ("test_voltage", test_voltage),
        ("acceleration", acceleration),
        ("external_moment", external_moment),
    ):
        if value is not None and jnp.ndim(value) != 0:
            raise ValueError(
                f"fast_step_response: {name} must be a scalar (constant input), got shape "
                f"{jnp.shape(value)}; use accel_jax.simulate_linear for time-varying inputs."
            )
    ts, inputs, _, _ = _prepare(params, ts, test_voltage, acceleration, external_moment, None)
    return ts, inputs


def _normal(key, shape, dtype, noise_dtype=None):
    """Standard normal deviates of `dtype`, drawn in `noise_dtype` (default `dtype`)."""
    if noise_dtype is None:
        return jax.random.normal(key, shape, dtype=dtype)
    if jnp.dtype(noise_dtype) == jnp.float32 and len(shape) == 1:
        return _normal_float32(key, shape[0]).astype(dtype)
    return jax.random.normal(key, shape, dtype=noise_dtype).astype(dtype)


def _normal_float32(key, n: int):
    """n float32 standard normal deviates: JAX's float32 transform (bitwise
    `jax.random.normal(key, (n,), jnp.float32)` for the same 32-bit words) applied to the
    two 32-bit halves of ⌈n/2⌉ 64-bit draws. JAX's threefry computes a whole threefry2x32
    block (two words) for each 32-bit draw and XORs them; a 64-bit draw keeps both, so this
    is half the hash work for full-quality words: other samples than `jax.random.normal`'s
    for the same key, the same distribution (tests). A threefry key's 64-bit draws are
    hashed here (`_threefry_words`: the same words, with or without x64); another
    implementation's come from `jax.random.bits`, or, without 64-bit types (x64
    disabled), the deviates are `jax.random.normal`'s."""
    m = -(-n // 2)
    if not jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
        key = jax.random.wrap_key_data(key)  # a raw uint32 key: the default implementation
    if jax.random.key_impl(key) == "threefry2x32":
        high, low = _threefry_words(jax.random.key_data(key), m)
    elif jax.dtypes.canonicalize_dtype(jnp.uint64) == jnp.uint64:
        wide = jax.random.bits(key, (m,), jnp.uint64)
        high, low = (wide >> 32).astype(jnp.uint32), wide.astype(jnp.uint32)
    else:
        return jax.random.normal(key, (n,), dtype=jnp.float32)
    return _float32_normal_from_bits(jnp.concatenate([high, low])[:n])


_THREEFRY_ROTATIONS = ((13, 15, 26, 6), (17, 29, 16, 24))


def _threefry_words(key_words, m: int):
    """Both output words of the threefry2x32 hash (20 rounds, Salmon et al. 2011) of the
    counters (0, i), i < m < 2³², under the key (k₀, k₁): the high and low halves of
    `jax.random.bits(key, (m,), jnp.uint64)` with JAX's default partitionable threefry
    (test: bitwise). Written out round by round, where JAX's CPU lowering loops over its
    five groups of four rounds (a `while` loop whose state goes through memory each time):
    XLA fuses the unrolled hash into one elementwise pass."""
    k0, k1 = key_words[0], key_words[1]
    schedule = (k0, k1, k0 ^ k1 ^ np.uint32(0x1BD11BDA))
    x0 = jnp.zeros((m,), jnp.uint32) + schedule[0]
    x1 = jax.lax.iota(jnp.uint32, m) + schedule[1]
    for group in range(5):
        for rotation in _THREEFRY_ROTATIONS[group % 2]:
            x0 = x0 + x1
            x1 = jax.lax.shift_left(x1, np.uint32(rotation)) | jax.lax.shift_right_logical(
                x1, np.uint32(32 - rotation)
            )
            x1 = x0 ^ x1
        x0 = x0 + schedule[(group + 1) % 3]
        x1 = x1 + schedule[(group + 2) % 3] + np.uint32(group + 1)
    return x0, x1


def _float32_normal_from_bits(words):
    """`jax.random.normal`'s float32 transform of 32-bit words: a uniform on
    (−1, 1) from the top 23 bits (`jax.random.uniform`'s construction), then √2·erf⁻¹."""
    one = np.array(1.0, np.float32)
    mantissa = jax.lax.shift_right_logical(words, np.uint32(9)) | one.view(np.uint32)
    floats = jax.lax.bitcast_convert_type(mantissa, jnp.float32) - one
    low = np.nextafter(np.float32(-1.0), np.float32(0.0))
    uniform = jax.lax.max(low, floats * (one - low) + low)
    return np.float32(np.sqrt(2)) * jax.lax.erf_inv(uniform)


def _check_noise_dtype(noise_dtype):
    if noise_dtype is None:
        return None
    try:
        dtype = jnp.dtype(noise_dtype)
    except TypeError:
        dtype = None
    if dtype is None or dtype not in (jnp.dtype(jnp.float32), jnp.dtype(jnp.float64)):
        raise ValueError(f"noise_dtype must be float32, float64 or None, got {noise_dtype!r}.")
    return dtype


def fast_step_response(
    params: ServoParams,
    ts: Float[ArrayLike, " n"],
    test_voltage: ArrayLike = 1.0,
    acceleration: ArrayLike = 0.0,
    external_moment: ArrayLike | None = None,
    *,
    key: PRNGKeyArray | None = None,
    noise_dtype=None,
) -> _Samples:
    """The output of `simulate_linear` for constant inputs from a settled device, fast.

    Same record as `accel_jax.simulate_linear(params, ts, test_voltage, acceleration,
    external_moment, key=key)` with the default initial state (the equilibrium with zero
    test voltage), including T_dm = 0 or T_f = 0 and the same noise samples for the same
    key: the response to the inputs applied from t_0 is y_k = c·M^k z_0 (exact ZOH in
    affine form), evaluated as a (n/B × 5)·(5 × B) product of block powers (B ≈ √n)
    instead of n sequential steps. jit-, vmap- and grad-safe.

    Precision: the dtype of the parameters and inputs (float64 recommended: the record then
    agrees with `simulate_linear` to ~2e-13 of the step).

    **Arguments:**

    - `params`: the device, a `ServoParams` (SI units).
    - `ts`: uniform sample times [s], shape (n,), n ≥ 2 (checked when concrete).
    - `test_voltage`: the constant U_test [V] applied from t_0 on (a scalar).
    - `acceleration`: the constant a [m/s²] (a scalar). Default 0.
    - `external_moment`: the constant M_ext [N·m] (a scalar); `None` means
        `params.external_moment`.
    - `key`: PRNG key for the output noise ε = `params.noise_std` (drawn exactly as
        `simulate_linear` draws it), or `None`.
    - `noise_dtype`: `None` (default) draws the deviates in the record's dtype, as
        `simulate_linear` does; `jnp.float32` draws them in float32 and widens them
        (other samples, the same distribution up to float32 resolution; each 32-bit word
        is half of a 64-bit draw, so half the threefry work of float64 deviates or of
        `jax.random.normal` in float32, and the float32 transform is cheaper).

    **Returns:**

    U_out at ts [V], shape (n,).
    """
    noise_dtype = _check_noise_dtype(noise_dtype)
    ts, inputs = _constant_inputs(params, ts, test_voltage, acceleration, external_moment)
    system = _affine_system(params, ts, inputs)
    return _noisy_record(params, system, ts.shape[0], key, noise_dtype)


def _noisy_record(params, system, n: int, key, noise_dtype):
    """The record of an `_affine_system` with the output noise of `params` drawn from `key`
    (none for `None`). `monte_carlo_oscillatory` computes a chunk's systems with a short
    squaring loop where every device in it needs few (`record_squarings`), then this."""
    record = _record_of_system(system, n)
    if key is not None:
        deviates = _normal(key, record.shape, record.dtype, noise_dtype)
        record = record + params.noise_std * deviates
    return record


def step_system(params: ServoParams, ts: Array, test_voltage, max_squarings: int):
    """`_affine_system` of a constant `test_voltage` from the settled device (no
    acceleration, the device's own external moment): the Monte Carlo kernel's records."""
    ts, inputs = _constant_inputs(params, ts, test_voltage, 0.0, None)
    return _affine_system(params, ts, inputs, max_squarings)


# Trajectories per vmapped chunk. CPU: 16 records (16 × 5001 float64 = 640 kB) stay in a
# core's L2 cache. GPU/TPU: the chunks run one after another (`lax.map`), so small chunks
# leave the device idle between tiny kernels; on an H100 chunks of 16 plateaued at
# ~1.4e4 trajectories/s whatever N (the per-trajectory kernel time is ~3 µs).
