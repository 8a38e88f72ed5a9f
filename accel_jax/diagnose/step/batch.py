"""Batched fits of a stage's candidates: the records of one shape (`RecordShape`) as one
batch, vmapped and sharded across devices (`accel_jax.sweep`), one compiled program per
shape and stage (`fit.fit_linear`, …; σ_ref and the starts are data)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ..._sweep import compile_ahead, even_chunk_size, sweep
from .assess import fit_entries
from .fit import BATCH_CHUNK
from .record import prior_sigma_of, stack_on_host
from .state import RecordShape, StepFit, StepRecord


def _arguments(nominal, records: list[StepRecord], starts: list[np.ndarray], candidates):
    """The stage's `sweep` arguments, `in_axes` and chunk size for `records` (one shape)."""
    args = (
        nominal.params,
        jnp.asarray(prior_sigma_of(nominal)),
        stack_on_host([rec.ctx for rec in records]),
        stack_on_host([rec.u_out for rec in records]),
        jnp.asarray(np.stack(starts)),
        jnp.asarray(candidates),
    )
    return args, (None, None, 0, 0, 0, None), even_chunk_size(len(records), BATCH_CHUNK)


def _run(fn, nominal, records: list[StepRecord], starts: list[np.ndarray], candidates, desc):
    """Fit `candidates` of `records` (one shape) from `starts` (one array of starts per
    record), batched."""
    args, in_axes, chunk = _arguments(nominal, records, starts, candidates)
    outputs = sweep(fn, *args, in_axes=in_axes, chunk_size=chunk, desc=desc)
    return [np.asarray(o) for o in outputs]


def compile_grouped(fn, nominal, records: list[StepRecord], shapes: dict[int, tuple], candidates):
    """Compile, without running, the programs `fit_grouped` will run for the records
    `shapes` names ({record index: the shape of its starts}): `_sweep.compile_ahead` of
    each record shape's batch (the starts as zeros: only their shape matters)."""
    groups: dict[tuple, list[int]] = {}
    for i, shape in shapes.items():
        groups.setdefault((records[i].shape, tuple(shape)), []).append(i)
    for (_, shape), members in groups.items():
        starts = [np.zeros(shape) for _ in members]
        args, in_axes, chunk = _arguments(
            nominal, [records[i] for i in members], starts, candidates
        )
        compile_ahead(fn, *args, in_axes=in_axes, chunk_size=chunk)


def fit_grouped(
    fn, nominal, records: list[StepRecord], starts: dict[int, np.ndarray], candidates, effects, desc
) -> dict[int, list[StepFit]]:
    """Fit `candidates` of the records `starts` names ({record index: its starts}), one
    batch per record shape (one compiled program each); returns {i: each candidate's fit}."""
    groups: dict[RecordShape, list[int]] = {}
    for i in starts:
        groups.setdefault(records[i].shape, []).append(i)
    entries = {}
    for members in groups.values():
        outputs = _run(
            fn, nominal, [records[i] for i in members], [starts[i] for i in members],
            candidates, desc,
        )
        for j, i in enumerate(members):
            entries[i] = fit_entries(
                records[i], effects, candidates, [o[j] for o in outputs], records[i].u_out,
                base=nominal.params,
            )
    return entries
