"""Batch sweeps sharded across every device JAX sees.

A study writes a function for one trajectory / one device and sweeps it with `sweep`:
the batch axis is split across `jax.devices()` (several GPUs, several hosts after
`jax.distributed.initialize()`, or simulated CPU devices via
`XLA_FLAGS=--xla_force_host_platform_device_count=N`) with no change to the caller.

Under several processes (`jax.distributed`, one per host or per GPU) every process runs the
same script: each computes its devices' share of the batch, and the result is gathered so
that every process holds the whole batch, as one process would (`gather_processes`).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from ._progress import bar, progress_enabled

# With progress bars on and no chunk size given, a batch is cut into about this many
# chunks so the bar moves; each chunk has the same (padded) shape, so one compilation.
_PROGRESS_CHUNKS = 16


@functools.lru_cache(maxsize=64)
def _compiled(fn: Callable, in_axes: tuple, single: bool = False) -> Callable:
    # One compiled object per (function, batching pattern): calling a sweep repeatedly with
    # new values of the same shapes never retraces.
    if single:
        return eqx.filter_jit(_one_element(fn, in_axes))
    return eqx.filter_jit(eqx.filter_vmap(fn, in_axes=in_axes))


def _one_element(fn: Callable, in_axes: tuple) -> Callable:
    """`fn` on a batch of one, unbatched: the element is taken out, `fn` called, the batch
    axis put back. The same values as the vmap of one (vmap does not change the order of
    any reduction), for a smaller program: every level of vmap re-batches each nested loop
    and solver of `fn`, which made tracing a single-record diagnosis a third slower."""

    def take(arg, axis):
        if axis is None:
            return arg
        dynamic, static = eqx.partition(arg, eqx.is_array)
        return eqx.combine(jax.tree_util.tree_map(lambda x: x[0], dynamic), static)

    def wrapped(*args):
        out = fn(*(take(a, ax) for a, ax in zip(args, in_axes, strict=True)))
        dynamic, static = eqx.partition(out, eqx.is_array)
        return eqx.combine(jax.tree_util.tree_map(lambda x: x[None], dynamic), static)

    return wrapped


def _batch_size(args, in_axes) -> int:
    sizes = set()
    for arg, axis in zip(args, in_axes, strict=True):
        if axis is None:
            continue
        for leaf in jax.tree_util.tree_leaves(eqx.filter(arg, eqx.is_array)):
            if jnp.ndim(leaf) == 0:
                raise ValueError(
                    f"sweep: a batched argument has a scalar leaf {leaf!r}; every array leaf "
                    "of a batched argument needs a leading batch axis (or use in_axes=None)."
                )
            sizes.add(int(jnp.shape(leaf)[0]))
    if not sizes:
        raise ValueError("sweep: no batched argument; give at least one in_axes entry 0.")
    if len(sizes) > 1:
        raise ValueError(f"sweep: batched arguments disagree on the batch size: {sorted(sizes)}.")
    return sizes.pop()


class _Plan:
    """How `sweep` cuts its arguments: validated `in_axes`, the chunk (a multiple of the
    device count), the batch padded to whole chunks by repeating its last element, each
    chunk's pieces placed on the devices."""

    def __init__(self, args, in_axes, devices, chunk_size):
        in_axes = tuple(0 for _ in args) if in_axes is None else tuple(in_axes)
        if len(in_axes) != len(args):
            raise ValueError(f"sweep: {len(args)} arguments but {len(in_axes)} in_axes entries.")
        if any(axis not in (0, None) for axis in in_axes):
            raise ValueError(f"sweep: in_axes entries must be 0 or None, got {in_axes}.")
        if chunk_size is not None and (not isinstance(chunk_size, int) or chunk_size < 1):
            raise ValueError(f"sweep: chunk_size must be a positive int, got {chunk_size!r}.")
        size = _batch_size(args, in_axes)
        devices = list(jax.devices() if devices is None else devices)
        n_dev = len(devices)
        if chunk_size is None:
            chunk_size = -(-size // _PROGRESS_CHUNKS) if progress_enabled() else size
        chunk = -(-min(chunk_size, size) // n_dev) * n_dev
        self.in_axes, self.size, self.chunk = in_axes, size, chunk
        self.n_chunks = -(-size // chunk)
        self.padded = padded = self.n_chunks * chunk
        mesh = Mesh(np.asarray(devices), ("batch",))
        self._sharded = NamedSharding(mesh, PartitionSpec("batch"))
        self._n_dev = n_dev
        # Array leaves enter strongly typed: a batch built from Python numbers carries JAX's
        # weak-type flag on some leaves and not on others, and each pattern is a new
        # signature of the compiled function (the scale-factor study compiled one kernel up
        # to 9 times). Values and dtypes are unchanged.
        args = tuple(_strong(arg) for arg in args)

        def pad(leaf):
            if padded == size:
                return leaf
            return jnp.concatenate([leaf, jnp.repeat(leaf[-1:], padded - size, axis=0)], axis=0)

        self._args = []
        for arg, axis in zip(args, in_axes, strict=True):
            if axis is None:
                self._args.append(arg)
            else:
                dynamic, static = eqx.partition(arg, eqx.is_array)
                self._args.append(eqx.combine(jax.tree_util.tree_map(pad, dynamic), static))

    def pieces(self, start: int) -> list:
        """The arguments of the chunk that starts at element `start`."""

        def place(leaf):
            return jax.device_put(leaf, self._sharded) if self._n_dev > 1 else leaf

        def split(arg, axis):
            if axis is None:
                return arg
            dynamic, static = eqx.partition(arg, eqx.is_array)
            piece = jax.tree_util.tree_map(
                lambda x: place(x[start : start + self.chunk]), dynamic
            )
            return eqx.combine(piece, static)

        return [split(a, ax) for a, ax in zip(self._args, self.in_axes, strict=True)]


def compile_ahead(
    fn: Callable,
    *args,
    in_axes: Sequence[int | None] | None = None,
    devices: Sequence[jax.Device] | None = None,  # pyright: ignore[reportInvalidTypeForm]  # alias
    chunk_size: int | None = None,
) -> None:
    """Compile the program that `sweep(fn, *args, in_axes=…, devices=…, chunk_size=…)`
    runs, without running it: a later `sweep` with arguments of the same shapes, dtypes and
    static parts (any values) calls the compiled program at once. For a caller that knows
    a later stage's shapes early and has a CPU to spare (a background thread: XLA compiles
    one program on one core). The arguments are read for their shapes only."""
    plan = _Plan(args, in_axes, devices, chunk_size)
    program: Any = _compiled(fn, plan.in_axes, plan.chunk == 1)  # an `eqx.filter_jit`
    program.lower(*plan.pieces(0)).compile()


def sweep(
    fn: Callable,
    *args,
    in_axes: Sequence[int | None] | None = None,
    devices: Sequence[jax.Device] | None = None,  # pyright: ignore[reportInvalidTypeForm]  # alias
    chunk_size: int | None = None,
    desc: str = "sweep",
):
    """Map `fn` over a leading batch axis, sharded across devices, jit-compiled once.

    **Arguments:**

    - `fn`: a function of one element (one trajectory, one device, one seed).
    - `*args`: its arguments; pytrees (e.g. a batched `ServoParams`) are fine.
    - `in_axes`: one entry per argument, `0` (batched along the leading axis of every array
      leaf) or `None` (shared). Default: all batched.
    - `devices`: devices to shard over; default all of `jax.devices()`.
    - `chunk_size`: evaluate the batch in chunks of this many elements (rounded up to a
        multiple of the device count), to bound memory or to show progress; every chunk has
        the same padded shape, so it compiles once. Default: the whole batch at once, or
        about 16 chunks when progress bars are on (`accel_jax.show_progress`).
    - `desc`: the progress bar's label.

    **Returns:** `fn`'s output with a leading batch axis, identical (to floating-point
    reduction order, which vmap does not change) to a single-device `jax.vmap`, whatever
    the chunking. The batch is padded to a multiple of the device count (and of the chunk)
    by repeating its last element, and the padding is dropped from the output.
    """
    plan = _Plan(args, in_axes, devices, chunk_size)
    padded, chunk, n_chunks, size = plan.padded, plan.chunk, plan.n_chunks, plan.size
    compiled = _compiled(fn, plan.in_axes, chunk == 1)
    outs = []
    with bar(padded, desc, unit="el") as progress:
        for start in range(0, padded, chunk):
            out = compiled(*plan.pieces(start))
            if n_chunks > 1:
                jax.block_until_ready(out)
            outs.append(out)
            progress.update(chunk)
    if n_chunks == 1:
        out = outs[0]
    else:
        dynamic = [eqx.filter(o, eqx.is_array) for o in outs]
        static = eqx.filter(outs[0], eqx.is_array, inverse=True)
        out = eqx.combine(
            jax.tree_util.tree_map(lambda *xs: jnp.concatenate(xs, axis=0), *dynamic), static
        )
    if padded != size:
        out = jax.tree_util.tree_map(lambda x: x[:size] if eqx.is_array(x) else x, out)
    return gather_processes(out)


def gather_processes(tree):
    """`tree` with every array leaf whole on this process.

    Under `jax.distributed` with several processes, a sweep's output is one global array
    whose shards sit on every process's devices, and a process can read only its own
    (`np.asarray` of it raises). This gathers the shards (an all-gather over the processes)
    so that each process holds the whole batch as a local array: the caller's code is that
    of one process. With one process it returns `tree` unchanged (no copy).
    """
    if jax.process_count() == 1:
        return tree
    from jax.experimental import multihost_utils

    dynamic, static = eqx.partition(tree, eqx.is_array)
    local = multihost_utils.process_allgather(dynamic, tiled=True)
    return eqx.combine(jax.tree_util.tree_map(jnp.asarray, local), static)


def even_chunk_size(size: int, largest: int) -> int:
    """The chunk size that splits `size` elements into as few chunks of at most `largest` as
    possible, all of (nearly) equal size: 18 at most 16 at a time gives 9 (2 × 9), not 16
    (16 + 2 padded to 16, where a vmapped chunk of iterative fits costs about as much as
    its slowest element whatever its fill)."""
    if size < 1 or largest < 1:
        raise ValueError(
            f"even_chunk_size: size and largest must be positive, got {size}, {largest}."
        )
    return -(-size // -(-size // largest))


def _strong(tree):
    def leaf_fn(leaf):
        if isinstance(leaf, jax.Array) and getattr(leaf, "weak_type", False):
            return jnp.asarray(leaf, dtype=leaf.dtype)
        return leaf

    return jax.tree_util.tree_map(leaf_fn, tree)


def device_count() -> int:
    """Number of devices a sweep shards over."""
    return len(jax.devices())
