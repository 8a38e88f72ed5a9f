"""A set of step records of one device made ready for the joint fit (`joint`): each
record prepared alone (`record.prepare`), told whether its test levels reach the stops
(`STOP_REACH`), padded to the set's common shapes and stacked (`prepare_set`, `stack`);
the set's static facts (`SetLayout`).

Float64 (x64 must be enabled), arrays on the host (NumPy): an eager jnp op would compile a
program per new shape.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import numpy as np

from ..._data import DataError, NominalDevice, StepData
from .fit import StepContext
from .layout import N_LAG_STATES, Own
from .record import MAX_CHANGES, prepare, stack_on_host
from .state import StepRecord

STOP_REACH = 0.5
"""A record is simulated with the stops when its largest test level times the nominal test
gain reaches this fraction of the nominal stop voltage (an overshoot can reach the stops
from there)."""


def _pad_context(ctx, n_padded: int, j_padded: int, max_block: int):
    """A record's `StepContext` padded to the set's common shapes (zero weight)."""

    def pad(x, size):  # on the host: an eager jnp op compiles a program per new shape
        x = np.asarray(x)
        return np.concatenate([x, np.zeros(size - x.shape[0], x.dtype)])

    return dataclasses.replace(
        ctx,
        change_index=pad(ctx.change_index, j_padded),
        change_step=pad(ctx.change_step, j_padded),
        # (one entry per change: a measured input's common delay is not fitted jointly)
        held_out_change=pad(ctx.held_out_change[: ctx.change_index.shape[0]], j_padded),
        change_accel=pad(ctx.change_accel, j_padded),
        train=pad(ctx.train, n_padded),
        test=pad(ctx.test, n_padded),
        max_block=max_block,
        # The joint fit takes a measured input's levels as read (no errors in variables).
        **dict.fromkeys(_MEASURED_INPUT_FIELDS, None),
    )


# The context's fields of a measured input's errors in variables: none in the joint fit.
_MEASURED_INPUT_FIELDS = (
    "level_sigma", "held_out_level", "drift_step", "level_map", "timing_map",
    "timing_offset", "timing_mean", "timing_sigma", "timing_limit", "timing_sigma_late",
)


class SetLayout(eqx.Module):
    """Static facts of a set: the records' common shapes and which are stop records."""

    n_padded: int = eqx.field(static=True)
    j_padded: int = eqx.field(static=True)
    stops: tuple = eqx.field(static=True)
    lag_states: bool = eqx.field(static=True, default=False)

    @property
    def width(self) -> int:
        """Each record's number of own parameters."""
        return Own.TIMING + self.j_padded + (N_LAG_STATES if self.lag_states else 0)


def nominal_stop_voltage(params) -> float:
    """k_dp k_y h_max [V]: the deflection voltage at the stops (docs/models.md §1, eq. (11))."""
    return float(params.pickoff_gain * params.amplifier_gain * params.stop_displacement)


@dataclasses.dataclass
class PreparedSet:
    """A set of records ready for the joint fit (`prepare_set`, `stack`).

    **Fields:** `preps` each record (`StepRecord`, `on_stops` set); `layout` the set's
    shapes (`SetLayout`); `ctx` the records' `StepContext`s padded and stacked (leading
    axis: the record); `data` (records, `layout.n_padded`) [V] the block means, `weight`
    1 on a record's blocks and 0 on its padding; `stop_voltage` [V] the nominal
    k_dp k_y h_max.
    """

    preps: list[StepRecord]
    layout: SetLayout
    ctx: StepContext
    data: np.ndarray
    weight: np.ndarray
    stop_voltage: float


def prepare_set(datasets: list[StepData], nominal: NominalDevice) -> PreparedSet:
    """Each record's context (`record.prepare`), padded to common shapes and stacked."""
    if not datasets:
        raise DataError("no records to diagnose.")
    preps = [prepare(d, nominal, []) for d in datasets]
    for i, p in enumerate(preps):
        if p.clock is not None:
            raise DataError(
                f"record {i + 1}: a clocked sequence of {p.change_index.size} changes; the "
                f"joint diagnosis of a set takes at most {MAX_CHANGES} changes per record "
                "(diagnose it alone, or split it into shorter records)."
            )
    v_stop = nominal_stop_voltage(nominal.params)
    # The inputs as read (a measured column's spikes are not levels).
    reach = [float(np.max(np.abs(np.asarray(p.data.u_test)))) * p.k_test for p in preps]
    preps = [
        dataclasses.replace(p, on_stops=bool(r >= STOP_REACH * v_stop))
        for p, r in zip(preps, reach, strict=True)
    ]
    return stack(preps, v_stop)


def stack(
    preps: list[StepRecord],
    stop_voltage: float,
    lag_states: bool = False,
    at_least: tuple[int, int, int] = (0, 0, 0),
) -> PreparedSet:
    """Prepared records (`prepare`'s, with `on_stops` set) as one padded, stacked set;
    `lag_states` whether each record's initial lag states are free (`SetLayout`);
    `at_least` (blocks, changes, largest block m) the least padded shapes: sets of several
    shapes padded to the largest share one compiled fit (`design.next_experiments`)."""
    n_padded = max(at_least[0], *(p.shape.n_padded for p in preps))
    j_padded = max(at_least[1], *(p.shape.j_padded for p in preps))
    max_block = max(at_least[2], *(p.shape.max_block for p in preps))
    ctxs = [_pad_context(p.ctx, n_padded, j_padded, max_block) for p in preps]
    ctxs = [
        dataclasses.replace(c, sigma_ref=np.asarray(p.sigma, np.float64))
        for c, p in zip(ctxs, preps, strict=True)
    ]
    ctx = stack_on_host(ctxs)
    data = np.zeros((len(preps), n_padded))
    weight = np.zeros((len(preps), n_padded))
    for r, p in enumerate(preps):
        data[r, : p.n] = p.u_out[: p.n]
        weight[r, : p.n] = 1.0
    layout = SetLayout(
        n_padded=n_padded,
        j_padded=j_padded,
        stops=tuple(p.on_stops for p in preps),
        lag_states=lag_states,
    )
    return PreparedSet(preps, layout, ctx, data, weight, stop_voltage)
