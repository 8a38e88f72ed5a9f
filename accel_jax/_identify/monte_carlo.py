"""`monte_carlo_oscillatory`: simulate and identify a batch of noisy step responses in one
compiled kernel — `fast_step_response` fused with the output noise and
`identify_oscillatory`, processed in chunks (`lax.map` over vmapped chunks) so that only
one chunk of records is alive at a time (GitHub issue 7; speed in `benchmarks/bench.py`)."""

from __future__ import annotations

import functools
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, PartitionSpec
from jaxtyping import ArrayLike, Float, PRNGKeyArray

from .._params import ServoParams, _concrete
from .._simulate.blocked import _check_noise_dtype, _noisy_record, record_squarings, step_system
from .._simulate.matrix import _MAX_SQUARINGS
from .._sweep import gather_processes
from .oscillatory import OscillatoryEstimate, _check_options, _oscillatory_estimate
from .record import _validate_record

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


# Half-width [samples] of the crossing fits' windows on the kernel's fast path (see
# `_oscillatory_estimate`): the transitions of noisy records take a few samples, so a chunk
# whose every fit fits in it is identified without the whole-record masked passes.
_FIT_WINDOW = 128

# The ZOH exponential's squarings on the short branch: enough for ‖[[A, B], [0, 0]]Δ‖₁ ≤ 4
# (the reference device at 1 MHz needs 2: ‖·‖₁ ≈ 0.5); a chunk that needs more takes the
# full loop.
_FEW_SQUARINGS = 4


@eqx.filter_jit
def _monte_carlo(
    params,
    keys,
    gain,
    gamma,
    ts,
    test_voltage,
    *,
    chunk_size,
    options,
    noise_dtype,
    devices,
    n_tail,
    window,
):
    size = keys.shape[0]
    n_dev = len(devices)
    # Whole chunks on every device: the batch is padded (repeating its last trajectory) to
    # a multiple of n_dev · chunk_size and each device maps over its own chunks.
    n_chunks = -(-size // (chunk_size * n_dev)) * n_dev
    padded = n_chunks * chunk_size

    def pad_and_chunk(leaf):
        if padded != size:
            leaf = jnp.concatenate([leaf, jnp.repeat(leaf[-1:], padded - size, axis=0)])
        return leaf.reshape((n_chunks, chunk_size) + leaf.shape[1:])

    batch = jax.tree_util.tree_map(pad_and_chunk, (params, keys, gain, gamma))
    options = dict(options)
    no_rail = jnp.asarray(jnp.inf, ts.dtype)

    def systems(device, max_squarings):
        return jax.vmap(lambda d: step_system(d, ts, test_voltage, max_squarings))(device)

    def records(device, key):
        # The ZOH exponential's squarings are computed masked under vmap, so a chunk whose
        # devices all need few runs a short loop (a real branch: one flag for the chunk);
        # either branch gives the same record to the bit. Only the small systems come out
        # of the branch, not the chunk's records.
        needed = jnp.max(jax.vmap(record_squarings, in_axes=(0, None))(device, ts))
        system = jax.lax.cond(
            needed <= _FEW_SQUARINGS,
            lambda: systems(device, _FEW_SQUARINGS),
            lambda: systems(device, _MAX_SQUARINGS),
        )
        n = ts.shape[0]
        return jax.vmap(lambda d, s, k: _noisy_record(d, s, n, k, noise_dtype))(
            device, system, key
        )

    def identify(u, pickoff_amplifier_gain, shape_factor, window):
        # identify_oscillatory(ts, u, ..., throw=False) with the options: step at ts[0]
        # (None: known to be the first sample, which skips the search for samples before
        # it), U_ss from the tail, no saturation level (the arguments were checked by the
        # caller).
        return _oscillatory_estimate(
            ts,
            u,
            pickoff_amplifier_gain,
            shape_factor,
            None,
            None,
            no_rail,
            n_tail,
            options["crossing"],
            options["extremum"],
            options["period"],
            window,
        )

    def one_chunk(chunk):
        device, key, pickoff_amplifier_gain, shape_factor = chunk
        u = records(device, key)
        fast, exact = jax.vmap(functools.partial(identify, window=window))(
            u, pickoff_amplifier_gain, shape_factor
        )
        # The whole-record passes only for a chunk with a fit the window does not hold
        # (a real branch: its predicate is one flag for the chunk).
        return jax.lax.cond(
            jnp.all(exact),
            lambda: fast,
            lambda: jax.vmap(functools.partial(identify, window=None))(
                u, pickoff_amplifier_gain, shape_factor
            )[0],
        )

    def chunks(local):
        return jax.lax.map(one_chunk, local)

    if n_dev > 1:
        # Each device runs the chunked loop over its share of the chunks (a shard_map over
        # the chunk axis): the same per-trajectory program, so the same numbers as on one
        # device to rounding (compiled on its own, it fuses differently: 1 ulp seen).
        # XLA:CPU's own threading gave the second core of this project's 2-core machine
        # ~8 %; two CPU devices gave ×1.7 (benchmarks/bench.py).
        mesh = Mesh(np.asarray(devices), ("batch",))
        chunks = jax.shard_map(
            chunks, mesh=mesh, in_specs=PartitionSpec("batch"), out_specs=PartitionSpec("batch")
        )
    estimates = chunks(batch)
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
    devices=None,
) -> OscillatoryEstimate:
    """Simulate and identify N noisy step responses in one compiled, chunked kernel.

    For trajectory i: the record `fast_step_response(params[i], ts, test_voltage,
    key=keys[i], noise_dtype=noise_dtype)` (the linear loop from the settled device,
    output noise ε_i) and its `identify_oscillatory` estimate with k_dp k_y =
    `pickoff_amplifier_gain[i]`, γ = `shape_factor[i]` and `throw=False`. The answers are
    those of calling the two functions in turn (the same code on the same record; XLA
    fuses the kernel differently, so they agree to rounding, ~1e-14). Fast path: the crossing
    fits are searched and summed within ±128 samples of each sign change; a chunk where one
    fit's window does not hold the whole-record fit is identified over the whole record, so
    the estimates are always `identify_oscillatory`'s (failed trajectories' placeholder
    numbers aside). The batch is processed
    `chunk_size` trajectories at a time (`lax.map` over vmapped chunks), so the memory held
    is about chunk_size·n·(a few) numbers, whatever N. Recompiles for a new N, n or
    setting, not for new values.

    Precision: that of the parameters (float64 recommended) for the simulation and the
    identification. The noise deviates are drawn in float32 by default and widened: ε is
    ~1e-4 of the step, float32 resolves each deviate to 6e-8 of itself, and the tails are
    cut at about 5.4 σ instead of 8 σ (a normal puts 1e-7 of its samples beyond). Half the
    threefry work (two 32-bit words from each 64-bit draw, see `fast_step_response`) and
    a cheaper Gaussian transform make the whole kernel faster (`benchmarks/bench.py`
    measures both).
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
    - `devices`: the devices the batch is split across (whole chunks per device), default
        all of `jax.devices()`: several GPUs, or several CPU devices
        (`XLA_FLAGS=--xla_force_host_platform_device_count=K`, one per core) with no
        change to the call. Each trajectory's estimate is the same whatever the devices (to
        rounding: the per-device program fuses differently). Under several processes
        (`jax.distributed.initialize()` in each), `jax.devices()` spans every process:
        each simulates its devices' share, and every process gets the whole result.

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
    options = dict(crossing=crossing, extremum=extremum, period=period)
    # Validate the record-level settings once, outside the compiled kernel.
    n_tail = _validate_record("monte_carlo_oscillatory", ts, ts, tail_fraction)
    _check_options(crossing, extremum, period)
    devices = tuple(jax.devices() if devices is None else devices)
    if not devices:
        raise ValueError("devices must name at least one device.")
    n_dev = len(devices)
    estimates = _monte_carlo(
        params,
        keys,
        gain,
        gamma,
        ts.astype(dtype),
        float(test_voltage),
        chunk_size=min(chunk_size, -(-size // n_dev)),
        devices=devices,
        n_tail=n_tail,
        window=_FIT_WINDOW,
        options=tuple(sorted(options.items())),
        noise_dtype=None if noise_dtype is None else noise_dtype.name,
    )
    # Under several processes (jax.distributed) each holds its devices' share: gather.
    return gather_processes(estimates)
