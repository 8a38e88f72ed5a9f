"""The discovery's model of a step record with terms (`discover`), and its compiled
programs: the screen's linearisation, the confirming refit's residuals and Jacobian, the
held-out part's refit and free-run error, the network reference's residuals and Jacobian
(`ceiling`). The record's model (`RecordModel`) and arrays
(`Data`) are the programs' arguments, not constants baked into them, so that every record of
one layout (its block count, block size, change count and free entries) reuses the programs
compiled for the first. Float64 (the caller's `jax.enable_x64`)."""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..._data import NominalDevice
from ..._params import ServoParams
from ..._simulate.sequence import SequenceInputs
from . import ceiling
from .model import StepContext, moment_jumps, unpack
from .state import StepRecord
from .terms import N_COEFFICIENTS, Scales, term_record


class RecordModel(eqx.Module):
    """The record's model with terms at the nominal fit: `prediction(θ, coefficients,
    scales)` [V] of the record's blocks and `penalties(θ)`, with θ = [w's `free` entries, an
    output offset in units of `ctx.scale`]; w's other entries stay as given. The output
    offset is a nuisance of its own here (standard normal prior): with the nominal loop it
    is the external moment's double, with a nonlinear term it is not (a term acts on the
    deflection, not on the ADC's zero).

    A pytree of the record's arrays (its layout static): the discovery's programs take it
    as an argument, so that records of one layout share them (compiled once)."""

    ctx: StepContext
    base: ServoParams
    prior_sigma: jax.Array
    w: jax.Array
    index: jax.Array  # w's free entries
    n: int = eqx.field(static=True)
    m: int = eqx.field(static=True)
    effects: tuple = eqx.field(static=True)

    def unpacked(self, theta):
        w = self.w.at[self.index].set(theta[:-1])
        return unpack(w, 0, self.effects, self.base, self.prior_sigma, self.ctx)

    def prediction(self, theta, coefficients, scales, amplitude=1.0, network=None):
        # (`coefficients` None: no terms; `amplitude`: the test steps scaled, for the record
        # that would excite a term; `network`: the network reference's flat parameters,
        # `ceiling`.)
        ctx, model = self.ctx, self.unpacked(theta)
        sequence = SequenceInputs(
            ctx.first_level * amplitude, model.gain, model.moment, model.rate, model.dv,
            model.dw, ctx.change_index, model.step * amplitude, model.shift,
            moment_jumps(model.params, ctx),
        )
        residual = None if network is None else ceiling.residual(network, scales.half)
        blocks = term_record(
            model.params, ctx.dt, self.n, self.m, sequence, coefficients, scales, residual
        )
        return blocks + model.output_offset + ctx.scale * theta[-1]

    def penalties(self, theta):
        return jnp.concatenate([self.unpacked(theta).penalties, theta[-1:]])


def record_model(
    rec: StepRecord, nominal: NominalDevice, w: np.ndarray, free: np.ndarray, effects
) -> RecordModel:
    """`rec`'s `RecordModel` with w's `free` entries free."""
    return RecordModel(
        ctx=rec.ctx, base=nominal.params, prior_sigma=jnp.asarray(rec.prior_sigma),
        w=jnp.asarray(w), index=jnp.asarray(np.flatnonzero(free)), n=len(rec.u_out),
        m=int(rec.block), effects=tuple(effects),
    )


class Data(NamedTuple):
    """The record's arrays that the discovery's programs read beside its model."""

    u_out: jax.Array
    train: jax.Array  # 1 on the training part's blocks, else 0
    test: jax.Array  # 1 on the held-out part's
    sigma: jax.Array
    scales: Scales
    resolution: jax.Array  # the record's frequency resolution [rad/s]
    free: jax.Array  # w's free entries in the training refit
    held: jax.Array  # w's entries refitted on the held-out part


# The discovery's compiled programs: module-level, the record's model and arrays their
# arguments (a record of a layout seen before reuses them).


@eqx.filter_jit
def linearised(model: RecordModel, theta, scales):
    zero = jnp.zeros(N_COEFFICIENTS)
    pred = model.prediction(theta, zero, scales)
    j_theta = jax.jacfwd(model.prediction, argnums=0)(theta, zero, scales)
    j_coef = jax.jacfwd(model.prediction, argnums=1)(theta, zero, scales)
    return pred, j_theta, j_coef, model.penalties(theta), jax.jacfwd(model.penalties)(theta)


def _whitened(data: Data, prediction, mask):
    """The output's error on the blocks of `mask` (the training or held-out part's), in
    units of the floor."""
    return (data.u_out - prediction) * mask / data.sigma


def _tuned(data: Data, shift):
    return data.scales._replace(omega=data.scales.omega + data.resolution * shift)


def _refit_residuals(model: RecordModel, data: Data, params, args):
    n_free = data.free.size + 1
    pick, used, tone, fixed = args  # `fixed`: coefficients held (`profile`), else 0
    theta, c, shift = params[:n_free], params[n_free:-1], params[-1]
    e = _whitened(data, model.prediction(theta, c @ pick + fixed, _tuned(data, shift)), data.train)
    pinned = jnp.concatenate([c * (1 - used), shift * (1 - tone)[None]])
    return jnp.concatenate([e, model.penalties(theta), pinned])


refit_at = eqx.filter_jit(_refit_residuals)
refit_jacobian_at = eqx.filter_jit(jax.jacfwd(_refit_residuals, argnums=2))


def _network_residuals(model: RecordModel, data: Data, params):
    """The network reference's training residuals (`ceiling`): params = [θ, the network's
    flat weights], each weight under its normal prior."""
    n_free = data.free.size + 1
    theta, flat = params[:n_free], params[n_free:]
    # (No terms: `term_record` then leaves their signals out of the Jacobian's ~120
    # columns, the same residuals as zero coefficients.)
    e = _whitened(data, model.prediction(theta, None, data.scales, network=flat), data.train)
    return jnp.concatenate([e, model.penalties(theta), flat / ceiling.PRIOR])


network_at = eqx.filter_jit(_network_residuals)
network_jacobian_at = eqx.filter_jit(jax.jacfwd(_network_residuals, argnums=2))


@eqx.filter_jit
def error_at(model: RecordModel, data: Data, params, pick):
    n_free = data.free.size + 1
    tuned = _tuned(data, params[-1])
    predicted = model.prediction(params[:n_free], params[n_free:-1] @ pick, tuned)
    return data.u_out - predicted


def _held_full(model_all: RecordModel, data: Data, x, theta):
    """θ of `model_all` (every entry of w free) from a training refit's θ and the held-out
    part's nuisances x."""
    w_full = model_all.w.at[data.free].set(theta[:-1]).at[data.held].set(x)
    return jnp.concatenate([w_full, theta[-1:]])


def _held_residuals(model_all: RecordModel, data: Data, x, args):
    theta, coefficients, tuned, network = args
    full = _held_full(model_all, data, x, theta)
    predicted = model_all.prediction(full, coefficients, tuned, network=network)
    e = _whitened(data, predicted, data.test)
    return jnp.concatenate([e, model_all.penalties(full)])


held_at = eqx.filter_jit(_held_residuals)
held_jacobian_at = eqx.filter_jit(jax.jacfwd(_held_residuals, argnums=2))


@eqx.filter_jit
def held_error(model_all: RecordModel, data: Data, x, theta, coefficients, tuned, network):
    full = _held_full(model_all, data, x, theta)
    return data.u_out - model_all.prediction(full, coefficients, tuned, network=network)
