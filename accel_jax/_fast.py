"""A fast, fused path for Monte Carlo scale-factor identification (GitHub issue 7).

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

`monte_carlo_oscillatory` fuses it with the output noise and `identify_oscillatory` for a
batch of devices, processed in chunks (`lax.map` over vmapped chunks) so that only one
chunk of records is alive at a time.

Precision: follows the dtype of the parameters (use float64; every test and benchmark
does). The record agrees with `simulate_linear` to ~1e-13 of the step in float64 (the tests
measure ~2e-14). `monte_carlo_oscillatory` draws the noise deviates in float32 by
default (its docstring says why that suffices); `noise_dtype` chooses.

Speed (`benchmarks/bench.py`, 2-core CPU, 5 001-sample records, chunks of 16): the
record costs ~1/5 of the `lax.scan` one; per trajectory the fused kernel spends about
40 µs on the record, 30 µs on the noise (float32 draws) and 110 µs in
`identify_oscillatory`, whose ~30 dependent passes over the record (summary, band
labels, three crossing fits, two extrema) are what is left: 7e3 trajectories/s, ×3.7 a
per-trajectory SciPy `lfilter` loop.
"""

from __future__ import annotations

import math
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray

from ._identify import OscillatoryEstimate, identify_oscillatory
from ._params import ServoParams, _concrete
from ._simulate import _drive_before, _grid_step, _Loop, _prepare, discretise, equilibrium_state

_Samples = Float[Array, " n"]
_Affine = Float[Array, "5 5"]
_Row = Float[Array, " 5"]


def _ceil_log2(count: int) -> int:
    return max(0, math.ceil(math.log2(count))) if count > 1 else 0


def _block_size(n: int) -> int:
    """B = a power of two near √n: both factor sequences are then short."""
    return 2 ** max(0, round(math.log2(max(1.0, math.sqrt(n)))))


def _affine_system(
    params: ServoParams, ts: Array, inputs: Array
) -> tuple[_Affine, _Row, _Row, Array]:
    """(M, z_0, c, y_0) of the record in `_Loop`'s internal units (see the module docstring).

    `inputs` (n, 3) are constant in time (checked by the caller); only `inputs[0]` is used.
    """
    loop = _Loop(params)
    initial = equilibrium_state(params, 0.0, inputs[0, 1], inputs[0, 2]).astype(inputs.dtype)
    transition, forcing = discretise(loop.a_matrix, loop.b_matrix, _grid_step(ts))
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


def _blocked_record(params: ServoParams, ts: Array, inputs: Array) -> _Samples:
    n = ts.shape[0]
    block = _block_size(n)
    n_blocks = -(-n // block)
    affine, start, row, first = _affine_system(params, ts, inputs)
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
    return jax.random.normal(key, shape, dtype=noise_dtype).astype(dtype)


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
    agrees with `simulate_linear` to ~1e-13 of the step).

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
        (other samples, the same distribution up to float32 resolution; half the random
        bits and a cheaper transform).

    **Returns:**

    U_out at ts [V], shape (n,).
    """
    noise_dtype = _check_noise_dtype(noise_dtype)
    ts, inputs = _constant_inputs(params, ts, test_voltage, acceleration, external_moment)
    record = _blocked_record(params, ts, inputs)
    if key is not None:
        deviates = _normal(key, record.shape, record.dtype, noise_dtype)
        record = record + params.noise_std * deviates
    return record


# Trajectories per vmapped chunk. CPU: 16 records (16 × 5001 float64 = 640 kB) stay in a
# core's L2 cache. GPU/TPU: the chunks run one after another (`lax.map`), so small chunks
# leave the device idle between tiny kernels; on an H100 chunks of 16 plateaued at
# ~1.4e4 trajectories/s whatever N (the per-trajectory kernel time is ~3 µs).
_CHUNK_CPU = 16
_CHUNK_ACCELERATOR = 4096


def default_chunk_size() -> int:
    """The chunk size `monte_carlo_oscillatory` uses when given none, for the default
    backend: 16 on CPU (cache-sized), 4096 on a GPU or TPU (occupancy)."""
    return _CHUNK_CPU if jax.default_backend() == "cpu" else _CHUNK_ACCELERATOR


def _batch_size(params: ServoParams, keys) -> int:
    sizes = {
        int(jnp.shape(leaf)[0]) for leaf in jax.tree_util.tree_leaves(params) if jnp.ndim(leaf) > 0
    }
    if any(jnp.ndim(leaf) == 0 for leaf in jax.tree_util.tree_leaves(params)):
        raise ValueError(
            "monte_carlo_oscillatory: every ServoParams field needs a leading batch axis "
            "(one value per trajectory); broadcast shared values, e.g. with "
            "eqx.filter_vmap(lambda v: eqx.tree_at(...))(values)."
        )
    sizes.add(int(jnp.shape(keys)[0]))
    if len(sizes) != 1:
        raise ValueError(
            f"monte_carlo_oscillatory: params and keys disagree on the batch size: {sorted(sizes)}."
        )
    return sizes.pop()


@eqx.filter_jit
def _monte_carlo(params, keys, gain, gamma, ts, test_voltage, *, chunk_size, options, noise_dtype):
    size = keys.shape[0]
    n_chunks = -(-size // chunk_size)
    padded = n_chunks * chunk_size

    def pad_and_chunk(leaf):
        if padded != size:
            leaf = jnp.concatenate([leaf, jnp.repeat(leaf[-1:], padded - size, axis=0)])
        return leaf.reshape((n_chunks, chunk_size) + leaf.shape[1:])

    batch = jax.tree_util.tree_map(pad_and_chunk, (params, keys, gain, gamma))

    def one(device, key, pickoff_amplifier_gain, shape_factor):
        record = fast_step_response(device, ts, test_voltage, key=key, noise_dtype=noise_dtype)
        return identify_oscillatory(
            ts,
            record,
            pickoff_amplifier_gain=pickoff_amplifier_gain,
            shape_factor=shape_factor,
            throw=False,
            **dict(options),
        )

    estimates = jax.lax.map(lambda chunk: jax.vmap(one)(*chunk), batch)
    return jax.tree_util.tree_map(lambda x: x.reshape((padded,) + x.shape[2:])[:size], estimates)


def monte_carlo_oscillatory(
    params: ServoParams,
    keys: PRNGKeyArray,
    ts: Float[ArrayLike, " n"],
    *,
    pickoff_amplifier_gain: ArrayLike,
    shape_factor: ArrayLike,
    test_voltage: float = 1.0,
    tail_fraction: float = 0.2,
    crossing: Literal["linear", "nearest"] = "linear",
    extremum: Literal["sample", "parabolic"] = "sample",
    period: Literal["full", "half"] = "full",
    chunk_size: int | None = None,
    noise_dtype=jnp.float32,
) -> OscillatoryEstimate:
    """Simulate and identify N noisy step responses in one compiled, chunked kernel.

    For trajectory i: the record `fast_step_response(params[i], ts, test_voltage,
    key=keys[i], noise_dtype=noise_dtype)` (the linear loop from the settled device,
    output noise ε_i) and its `identify_oscillatory` estimate with k_dp k_y =
    `pickoff_amplifier_gain[i]`, γ = `shape_factor[i]` and `throw=False`. The answers are
    those of calling the two functions in turn (the same code on the same record; XLA
    fuses the kernel differently, so they agree to rounding, ~1e-14). The batch is processed
    `chunk_size` trajectories at a time (`lax.map` over vmapped chunks), so the memory held
    is about chunk_size·n·(a few) numbers, whatever N. Recompiles for a new N, n or
    setting, not for new values.

    Precision: that of the parameters (float64 recommended) for the simulation and the
    identification. The noise deviates are drawn in float32 by default and widened: ε is
    ~1e-4 of the step, float32 resolves each deviate to 6e-8 of itself, and the tails are
    cut at about 5.4 σ instead of 8 σ (a normal puts 1e-7 of its samples beyond). Half the
    random bits and a cheaper Gaussian transform make the whole kernel faster
    (`benchmarks/bench.py` measures both).
    `noise_dtype=jnp.float64` (or `None`) draws exactly what `simulate_linear(...,
    key=keys[i])` draws.

    **Arguments:**

    - `params`: a batched `ServoParams`, every field of shape (N,).
    - `keys`: N PRNG keys (shape (N,)), one per trajectory. The key implementation sets
        the generator. threefry (the default) is exact under vmap and `lax.map`: each
        trajectory's noise is what `simulate_linear(..., key=keys[i])` draws. With
        `jax.random.key(seed, impl="rbg")` JAX's CPU generator under vmap draws the chunk
        from one stream, so the noise of trajectory i depends on `chunk_size` (still
        i.i.d. N(0, ε²), and reproducible for the same chunking); on this project's CPU
        it was no faster on the whole kernel (`benchmarks/bench.py` measures both).
    - `ts`: the uniform sample grid [s], shape (n,), starting at the step.
    - `pickoff_amplifier_gain`: k_dp k_y [V/m], a scalar or shape (N,).
    - `shape_factor`: γ, a scalar or shape (N,).
    - `test_voltage`: U_test [V], a Python float.
    - `tail_fraction`, `crossing`, `extremum`, `period`: as in `identify_oscillatory`.
    - `chunk_size`: trajectories per vmapped chunk (a positive int), or `None` for
        `default_chunk_size()`: 16 on CPU, which keeps a chunk's records (16 × n float64,
        640 kB at n = 5001) in a core's L2 cache; 4096 on a GPU or TPU, where small chunks
        leave the device idle.
    - `noise_dtype`: the dtype the noise deviates are drawn in: `jnp.float32` (default),
        `jnp.float64` or `None` (the parameters' dtype).

    **Returns:**

    An `OscillatoryEstimate` whose fields have a leading axis N (check `result` per
    element; failed trajectories carry finite placeholders).
    """
    if not isinstance(params, ServoParams):
        raise ValueError(f"params must be a batched ServoParams, got {type(params).__name__}.")
    if chunk_size is None:
        chunk_size = default_chunk_size()
    if not (isinstance(chunk_size, int) and chunk_size > 0):
        raise ValueError(f"chunk_size must be a positive int, got {chunk_size!r}.")
    concrete_voltage = _concrete(test_voltage)
    if concrete_voltage is None or concrete_voltage.ndim != 0 or not np.isfinite(concrete_voltage):
        raise ValueError(f"test_voltage must be a finite Python float [V], got {test_voltage!r}.")
    size = _batch_size(params, keys)
    ts = jnp.asarray(ts)
    if ts.ndim != 1:
        raise ValueError(f"ts must be 1-D, got shape {ts.shape}.")
    dtype = jnp.result_type(float, *jax.tree_util.tree_leaves(params), ts)
    # One dtype, strongly typed: a weakly typed leaf (e.g. from jnp.where with Python
    # numbers) would otherwise compile a second kernel for the same shapes.
    params = jax.tree_util.tree_map(lambda leaf: jnp.asarray(leaf, dtype), params)
    gain = jnp.broadcast_to(jnp.asarray(pickoff_amplifier_gain, dtype), (size,))
    gamma = jnp.broadcast_to(jnp.asarray(shape_factor, dtype), (size,))
    noise_dtype = _check_noise_dtype(noise_dtype)
    options = dict(tail_fraction=tail_fraction, crossing=crossing, extremum=extremum, period=period)
    # Validate the record-level settings once, outside the compiled kernel.
    if not 0.0 < tail_fraction <= 0.5:
        raise ValueError(f"tail_fraction must be in (0, 0.5], got {tail_fraction!r}.")
    return _monte_carlo(
        params,
        keys,
        gain,
        gamma,
        ts.astype(dtype),
        float(test_voltage),
        chunk_size=min(chunk_size, size),
        options=tuple(sorted(options.items())),
        noise_dtype=None if noise_dtype is None else noise_dtype.name,
    )
