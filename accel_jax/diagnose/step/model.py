"""The step diagnosis's candidate model (JAX): its parameters, the record's context, the model
a parameter vector stands for (`unpack`: a `CandidateModel`) and its noise-free prediction
(`predict`). The fit that adjusts the parameters is `fit`.

Parameters w = [refit z (4), external moment, test winding gain z, initial displacement
(2), effect slot (`layout.SLOT`), change times (J)], all O(1), each named in `layout.W`: the refit as
log-normal deviations in units of their prior σ, held within ±`REFIT_BOUND`σ by a steep
penalty; the change times in samples from where `u_test` shows each change, under a
N(−0.5, 1) prior.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ..._params import ServoParams
from ..._simulate.contact import contact_record
from ..._simulate.sequence import SequenceInputs, accel_moment, linear_record, stop_record
from .layout import SLOT, W

REFIT_FIELDS = ("moment_of_inertia", "damping", "stiffness", "torquer_gain")
"""ServoParams fields the refit moves, each under its log-normal prior (a field given no
uncertainty in the device file stays at its nominal value)."""

REFIT_BOUND = 6.0
"""|z| of a refitted value (and of the test winding's gain) stays within about this many σ:
beyond it a steep penalty (`BARRIER`) acts, so a refit stays inside its prior by
construction. A refit beyond `openworld.PRIOR_LIMIT` (5σ) is reported as not credible."""

BARRIER = 30.0
"""Slope of the penalty residual BARRIER·max(|w| − bound, 0) that keeps a parameter within
its bound (a fit that wants more stays at the bound instead of running away)."""

GAIN_SIGMA = 0.1
"""Relative (1σ) uncertainty of the test winding's gain."""

TIMING_PRIOR = (-0.5, 1.0)
"""Prior (mean, σ) of each change's time in samples from the sample where `u_test` shows
it: a sampled u_test column puts it up to one sample earlier, the library's own records
exactly there. Clipped to ±`TIMING_LIMIT` samples."""

TIMING_LIMIT = 4.0

DELAY_PRIOR_SIGMA = 4.0
"""Prior σ [samples] of a measured input channel's delay behind the output's, N(0, σ): a
common shift of every change (an ADC's group delay, an anti-alias filter); clipped to
±`DELAY_LIMIT`."""

DELAY_LIMIT = 8.0

DELAY_LATE_SIGMA = 0.5
"""Prior σ [samples] of a measured input channel's delay on its late side (the changes
placed later than its column shows them; `DELAY_PRIOR_SIGMA` on the other). The channel's
filters and converter come after the drive, so its column shows a change late, never
early: the fitted delay moves the changes earlier, and later by about the sampling phase
at most (`nuisance.LATE_OUTPUT_SIGMA`, which judges the output's lateness, is the same
scale). An output later than that is a lag the model lacks (a torquer lag, an output
filter). With the symmetric σ alone, the delay took up lags of 5–9 µs at 0.5–2 MHz in the
nominal fit at a cost of about 1 in ln L (the output 3.5–9.5 samples late), the lag fits
gained too little to be significant, and the measured twins of eight lag records of the
measured-input harness read `unexplained` where their exact-input twins tie the two lags
(`cannot_tell`). A prior, not a tighter limit: limited smoothly to one sample, a stop fit's
delay ran out to 107 in its first steps, where the limit has no gradient, and stayed."""

KNOWN_DELAY_SIGMA = 0.5
"""Prior σ [samples] of a measured input channel's delay about the delay the user gives
(`StepData.input_delay`): known to about the sampling phase."""



class StepContext(eqx.Module):
    """Per-record scales, masks and the test sequence (array leaves: vmappable).

    **Fields:** `dt` [s] the sample period; `duration` [s] of the fitted record (the drift
    is per this); `first_level` U_test at the first sample [V];
    `polarity` ±1 of
    the test winding; `sigma_ref` [V] the residual scale (the noise floor); `scale` [V] of
    the offset and initial-state parameters; `lag_unit` [s] the lag departure per unit z (3 % of the
    nominal T); `mid`, `half` [V] the middle and half range of the training output (where
    the stops start); `change_index` (J,), `change_step` ΔU (J,) [V] (0 pads),
    `held_out_change` (J,) 1 for changes in the held-out part; `train`, `test` masks of the
    fitted outputs (block means; 0 on padding); `block` m, samples per block; `max_block`
    (static) the largest m of the batch; `change_accel` (J,) Δa [g] of the input
    acceleration at each change and `accel_sign` ±1 the input axis's direction in the
    record (None: a record without `a_in`). For a measured test input
    (`inputs.read_inputs`): `level_sigma` (J,) [V] the standard error of the test
    level after each change (0 pads), `held_out_level` (J + 1,) 1 where that level's segment
    is held out (the last entry, the drift nuisance's, 0) and `drift_step` (J,) [V] each
    step's change per unit of the input channel's drift nuisance; None for an exact input
    (then the fit has no level parameters).

    A sequence of many changes on one clock (a PRBS or random telegraph: `record`'s
    clocked layout) is fitted with few nuisances instead of one per change:
    `timing_map` (J, P) and `timing_offset` (J,) [samples] give each change's shift as
    offset + map·p from P clock parameters p (the common shift, the clock's rate), whose
    prior means are `timing_mean` (P,) (σ 1); `level_map` (J + 1, L) [V] gives each level's
    error from L level-group errors (one per distinct level of the input: a DAC puts out the
    same value each time), standard normal; `timing_sigma`, `timing_limit` (P,) the timing
    parameters' prior σ and clip [samples], `timing_sigma_late` (P,) the prior σ on the late
    side (a parameter above its mean; None: `timing_sigma`). A measured input of few
    changes has one shift per change and the input channel's delay, common to all (the map
    [I | 1]). None (the default): one timing and one level parameter per change, as above.
    """

    dt: jax.Array
    duration: jax.Array
    first_level: jax.Array
    polarity: jax.Array
    sigma_ref: jax.Array
    scale: jax.Array
    lag_unit: jax.Array
    mid: jax.Array
    half: jax.Array
    change_index: jax.Array
    change_step: jax.Array
    held_out_change: jax.Array
    train: jax.Array
    test: jax.Array
    block: jax.Array
    max_block: int = eqx.field(static=True, default=1)
    change_accel: jax.Array | None = None
    accel_sign: jax.Array | None = None
    level_sigma: jax.Array | None = None
    held_out_level: jax.Array | None = None
    drift_step: jax.Array | None = None
    timing_map: jax.Array | None = None
    timing_offset: jax.Array | None = None
    timing_mean: jax.Array | None = None
    timing_sigma: jax.Array | None = None
    timing_limit: jax.Array | None = None
    timing_sigma_late: jax.Array | None = None
    level_map: jax.Array | None = None


def n_timing(ctx) -> int:
    """Number of timing parameters in w: one per change, or the clock's (`timing_map`)."""
    if ctx.timing_map is not None:
        return ctx.timing_map.shape[-1]
    return ctx.change_index.shape[-1]


def timing_terms(timing, ctx):
    """(each change's shift [samples], the timing parameters' prior residuals) from the
    timing parameters `timing`. Each change's own shift is clipped to ±`TIMING_LIMIT`
    samples; the parameters of a `timing_map` are limited smoothly to ±`timing_limit`
    (L tanh(p/L)), the map's offsets then added as they are, and their prior residuals
    taken with `timing_sigma_late` above their means where it is given."""
    if ctx.timing_map is None:
        clipped = jnp.clip(timing, -TIMING_LIMIT, TIMING_LIMIT)
        return clipped, (timing - TIMING_PRIOR[0]) / TIMING_PRIOR[1]
    # A smooth limit (L tanh(p/L)): a hard clip has no gradient beyond it, where a fit
    # that overshoots in its first steps would stay (seen on a measured record: the delay
    # at +4 and every level strained).
    limited = ctx.timing_limit * jnp.tanh(timing / ctx.timing_limit)
    shift = ctx.timing_offset + ctx.timing_map @ limited
    sigma = ctx.timing_sigma
    if ctx.timing_sigma_late is not None:
        sigma = jnp.where(timing > ctx.timing_mean, ctx.timing_sigma_late, sigma)
    return shift, (timing - ctx.timing_mean) / sigma


def refitted_device(base: ServoParams, z, prior_sigma) -> ServoParams:
    """The nominal device with J, μ, c, k_dm moved by z (in units of their prior σ). Every
    other value is the nominal device's as given, its lags T_dm and T_f included: the lag
    effects are departures from those (`effects._AbstractLag`)."""
    values = [getattr(base, f) * jnp.exp(prior_sigma[i] * z[i]) for i, f in enumerate(REFIT_FIELDS)]
    return eqx.tree_at(lambda p: [getattr(p, f) for f in REFIT_FIELDS], base, values)


def _barrier(w, bound):
    return BARRIER * jnp.maximum(jnp.abs(w) - bound, 0.0)


class CandidateModel(eqx.Module):
    """One candidate model at its parameters w (`unpack`), as `predict` simulates it.

    **Fields:** `params` the device (`ServoParams`: refitted, the effect's change applied);
    `gain` [V/V] the test winding's gain with its polarity; `moment` [V] the external
    moment; `rate` [V/s] a drift's rate; `dv`, `dw` [V] the initial displacement and
    velocity; `shift` (J,) [samples] each change's time shift; `step` (J,) [V] each
    change's ΔU_test (a measured input's level errors added); `inverse_high`,
    `inverse_low` the upper and lower stop's inverse clearance in units of the training
    output's half range (0: no stop on that side); `stiffness`, `damping_ratio` a compliant
    contact's κ and ζ_c (`_simulate.contact`; used by a `contact` candidate only: the other
    stops are inelastic); `output_offset` [V]; `phi`, `theta`,
    `log_first` the noise model's ARMA(1,1) on the block means (`effects.block_noise`;
    0, 0, 0: white); `moment_ratio`, `moment_phi` a Gauss–Markov moment noise's λ² and
    φ_block (`innovations.moment_noise_terms`; used by a `moment` candidate only);
    `penalties` the residuals of
    every prior and barrier.
    """

    params: ServoParams
    gain: jax.Array
    moment: jax.Array
    rate: jax.Array
    dv: jax.Array
    dw: jax.Array
    shift: jax.Array
    step: jax.Array
    inverse_high: jax.Array
    inverse_low: jax.Array
    stiffness: jax.Array
    damping_ratio: jax.Array
    output_offset: jax.Array
    phi: jax.Array
    theta: jax.Array
    log_first: jax.Array
    moment_ratio: jax.Array
    moment_phi: jax.Array
    penalties: jax.Array


def unpack(w, candidate, effects, base, prior_sigma, ctx) -> CandidateModel:
    """The model of candidate `candidate` (0: nominal; i: effect i − 1 of `effects`) at the
    parameters w = [refit z (4), moment, gain z, dv, dw, effect slot (2), change times (J)]
    and, for a measured test input (`ctx.level_sigma`), the errors of the levels after each
    change (J, in units of their standard error: errors in variables, a standard normal
    prior; the first level's error is an output offset, the moment's) and the input
    channel's drift (1, standard normal)."""
    z = w[W.REFIT]
    params = refitted_device(base, z, prior_sigma)
    gain = ctx.polarity * jnp.exp(GAIN_SIGMA * w[W.GAIN])
    slot = w[W.EFFECT]
    rate = jnp.zeros_like(w[0])
    high = low = stiffness = damping = offset = phi = theta = first = jnp.zeros_like(w[0])
    moment_ratio = moment_phi = jnp.zeros_like(w[0])
    used = jnp.zeros(SLOT, w.dtype)
    bounds = jnp.full(SLOT, jnp.inf, w.dtype)
    prior = jnp.zeros(SLOT, w.dtype)
    for i, effect in enumerate(effects, start=1):
        # Every effect sees zeros unless it is the candidate: exactly the nominal model.
        on = candidate == i
        ze = jnp.where(on, slot, 0.0)
        params = effect.device(params, ze, ctx)
        rate = rate + effect.drift(ze, ctx)
        symmetric = effect.inverse_stop(ze, ctx)
        contact = effect.contact(ze, ctx)
        high, low = high + symmetric + contact[0], low + symmetric + contact[1]
        stiffness, damping = stiffness + contact[2], damping + contact[3]
        offset = offset + effect.output_offset(ze, ctx)
        p, q, v = effect.noise(ze, ctx)
        phi, theta, first = phi + p, theta + q, first + v
        ratio_e, phi_e = effect.moment_noise(ze, ctx)
        moment_ratio, moment_phi = moment_ratio + ratio_e, moment_phi + phi_e
        mask = jnp.arange(SLOT) < effect.n_params
        used = jnp.where(on, mask.astype(w.dtype), used)
        bound = jnp.asarray(effect.bounds + (jnp.inf,) * (SLOT - len(effect.bounds)), w.dtype)
        bounds = jnp.where(on, bound, bounds)
        prior = jnp.where(on, effect.prior(ze, ctx), prior)
    n_t = n_timing(ctx)
    timing = w[W.timing(n_t)]
    levels = w[W.levels(n_t)]
    shift, timing_prior = timing_terms(timing, ctx)
    step = ctx.change_step
    if ctx.level_sigma is not None:
        # ΔU_j moves by e_j − e_{j−1} (e the level errors [V]; pads carry none) and by the
        # input channel's drift nuisance (the last level parameter) along `drift_step`.
        if ctx.level_map is None:
            error = ctx.level_sigma * levels[:-1]
            previous = jnp.concatenate([jnp.zeros(1, w.dtype), error[:-1]])
        else:  # each level's error from its level group's
            both = ctx.level_map @ levels[:-1]
            error, previous = both[1:], both[:-1]
        step = step + jnp.where(ctx.level_sigma > 0, error - previous, 0.0)
        step = step + ctx.drift_step * levels[-1]
    penalties = jnp.concatenate(
        [
            z,  # the standard normal prior of the refit
            w[W.GAIN][None],  # and of the test winding's gain
            _barrier(z, REFIT_BOUND),
            _barrier(w[W.GAIN][None], REFIT_BOUND),
            slot * (1 - used),  # an effect's unused parameters are pinned at 0
            _barrier(slot, bounds) * used,
            prior * used,  # an effect's own prior, where it has one
            timing_prior,
            levels,  # the level errors' standard normal prior (empty for an exact input)
        ]
    )
    return CandidateModel(
        params=params,
        gain=gain,
        moment=ctx.scale * w[W.MOMENT],
        rate=rate,
        dv=ctx.scale * w[W.DV],
        dw=ctx.scale * w[W.DW],
        shift=shift,
        step=step,
        inverse_high=high,
        inverse_low=low,
        stiffness=stiffness,
        damping_ratio=damping,
        output_offset=offset,
        phi=phi,
        theta=theta,
        log_first=first,
        moment_ratio=moment_ratio,
        moment_phi=moment_phi,
        penalties=penalties,
    )


def moment_jumps(params, ctx, gain: float | jax.Array = 1.0):
    """ΔM̃ [V] of the record's acceleration steps (None without `a_in`): Δa·g₀·m·l/k_dm
    along the record's input axis (`accel_sign`), times the pendulosity's `gain`."""
    if ctx.change_accel is None:
        return None
    return ctx.accel_sign * gain * accel_moment(params) * ctx.change_accel


MODES = ("linear", "clamp", "contact", "moment")
"""How `predict` simulates a candidate (static): the linear loop (`linear_record`), with
inelastic stops (`stop_record`) or with compliant ones (`_simulate.contact`); "moment" is
the linear loop with the noise model of a moment inside it (`innovations.moment_noise_terms`,
in `_fit_record`)."""


def predict(m: CandidateModel, ctx, n, mode: str):
    """The candidate's noise-free output [V] at the record's blocks, simulated as `mode`
    (`MODES`) says."""
    sequence = SequenceInputs(
        ctx.first_level,
        m.gain,
        m.moment,
        m.rate,
        m.dv,
        m.dw,
        ctx.change_index,
        m.step,
        m.shift,
        moment_jumps(m.params, ctx),
    )
    args = (m.params, ctx.dt, n, sequence)
    if mode in ("linear", "moment"):
        record = linear_record(
            *args, block=ctx.block, max_block=ctx.max_block, duration=ctx.duration
        )
        return record + m.output_offset

    def clearance(inverse):  # a stop's voltage, far out of reach for none
        safe = jnp.where(inverse > 0, inverse, 1.0)
        return jnp.where(inverse > 0, ctx.half / safe, 1e6 * ctx.half)

    high, low = clearance(m.inverse_high), -clearance(m.inverse_low)
    if mode == "contact":
        record = contact_record(
            *args, high, low, m.stiffness, m.damping_ratio, block=ctx.block,
            max_block=ctx.max_block, duration=ctx.duration,
        )
    else:
        record = stop_record(
            *args, high, low, block=ctx.block, max_block=ctx.max_block, duration=ctx.duration
        )
    return record + m.output_offset
