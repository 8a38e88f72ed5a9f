"""Batched fits of a stage's candidates: the records of one shape (`RecordShape`) as one
batch, vmapped and sharded across devices (`accel_jax.sweep`), one compiled program per
shape and stage (`fit.fit_linear`, …; σ_ref and the starts are data)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ..._sweep import even_chunk_size, sweep
from .assess import fit_entries
from .fit import BATCH_CHUNK
from .record import prior_sigma_of, stack_on_host
from .state import RecordShape, StepFit, StepRecord


def _run(fn, nominal, records: list[StepRecord], starts: list[np.ndarray], candidates, desc):
    """Fit `candidates` of `records` (one shape) from `starts` (one array of starts per
    record), batched."""
    ctx = stack_on_host([rec.ctx for rec in records])
    u_out = stack_on_host([rec.u_out for rec in records])
    guesses = jnp.asarray(np.stack(starts))
    outputs = sweep(
        fn,
        nominal.params,
        jnp.asarray(prior_sigma_of(nominal)),
        ctx,
        u_out,
        guesses,
        jnp.asarray(candidates),
        in_axes=(None, None, 0, 0, 0, None),
        chunk_size=even_chunk_size(len(records), BATCH_CHUNK),
        desc=desc,
    )
    return [np.asarray(o) for o in outputs]


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
