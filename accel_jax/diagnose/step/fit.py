"""The step diagnosis's fit (JAX): the parameters of a candidate model, its prediction and
one-step errors, and the vmapped least-squares fit of every candidate of a record.

Parameters w = [refit z (4), external moment, test winding gain z, initial displacement
(2), effect slot (`layout.SLOT`), change times (J)], all O(1), each named in `layout.W`: the refit as
log-normal deviations in units of their prior σ, held within ±`REFIT_BOUND`σ by a steep
penalty; the change times in samples from where `u_test` shows each change, under a
N(−0.5, 1) prior.
"""

from __future__ import annotations

from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import optimistix as optx

from ..._params import ServoParams
from ..._simulate.contact import contact_record
from ..._simulate.sequence import SequenceInputs, accel_moment, linear_record, stop_record
from .effects import step_effects
from .innovations import innovation_terms, moment_noise_terms
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
    parameters' prior σ and clip [samples]. A measured input of few changes has one shift
    per change and the input channel's delay, common to all (the map [I | 1]). None (the
    default): one timing and one level parameter per change, as above.
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
    (L tanh(p/L)), the map's offsets then added as they are."""
    if ctx.timing_map is None:
        clipped = jnp.clip(timing, -TIMING_LIMIT, TIMING_LIMIT)
        return clipped, (timing - TIMING_PRIOR[0]) / TIMING_PRIOR[1]
    # A smooth limit (L tanh(p/L)): a hard clip has no gradient beyond it, where a fit
    # that overshoots in its first steps would stay (seen on a measured record: the delay
    # at +4 and every level strained).
    limited = ctx.timing_limit * jnp.tanh(timing / ctx.timing_limit)
    shift = ctx.timing_offset + ctx.timing_map @ limited
    return shift, (timing - ctx.timing_mean) / ctx.timing_sigma


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


FIT_TOLERANCE = 1e-6
"""rtol = atol of the Levenberg–Marquardt fits (on the O(1) parameters)."""

BATCH_CHUNK = 1
"""Records fitted per compiled call. One: each record's fits stop at their own step counts.
A vmapped batch of records runs every fit to its slowest member's step count, and a
vmapped solver turns each branch into both branches; the stop candidate's sample-by-sample
fits suffer most. On the 2-core CPU, warm, 18 records of the blind validation's step truths
took 39.7 s one at a time against 52.3 s in batches of 8 (`benchmarks/bench.py
--only-diagnose`), and the report's blind step diagnoses (200 records) 704 s against
1,337 s, with the same verdicts. On several devices `sweep` still gives each device its
own records."""


STOP_FIT_MAX_STEPS = 100
"""The same for the inelastic-stop candidate (`mode` "clamp"). Each step costs a
sample-by-sample simulation, but a start far from the optimum needs many: on a measured
input, the nominal refit can take up the clipping in the input's level errors (thousands
of their standard errors), and the stop fit must walk them back. Harness record 319
(a stop at 0.97 of the largest level, measured twin): with 20 steps no start converged and
the best left 0.0055 V (25× the noise floor), read `unexplained`; the start from the
nominal's device with the levels as read, continued in rounds of 20, reached the floor in
four (objective 5.4e6 → 1.1e5 → 835 → 827), and with 100 steps the record reads
`stop_saturation` (gap 0, shrink 1.0). A fit that converges stops at its own step count
(the starts are mapped, not vmapped), so the limit costs only where a start does not."""

FIT_MAX_STEPS = 30
"""Levenberg–Marquardt steps per start. A batch runs until its slowest fit stops, and the
fits of effects that do not describe the record creep on for many steps after the loss has
settled, so a fit that is not done by then is judged by its Newton decrement instead."""

CONTACT_FIT_MAX_STEPS = 100
"""Levenberg–Marquardt steps of a compliant-stop fit: its stiffness and damping move the
record far from where a start puts them (a soft, bouncing contact)."""

CONVERGED_DECREMENT = 0.5
"""A fit counts as converged when the solver says so or when a full Gauss–Newton step from
its result would lower the cost ½Σr² (r in noise-floor units) by less than this plus 1e-8
of the cost: its log-likelihood is then within that of the minimum, and the evidence (2 ln
B) within 1 — the precision a significance threshold of 10 needs."""

HELD_OUT_ITERATIONS = 4
"""Gauss–Newton iterations of the held-out change times (nearly linear: a few suffice)."""


def dense_jacobian(fn):
    """`fn(w, args)` whose derivative is its Jacobian in w, computed once by forward mode
    (`jax.jacfwd`) and applied as a matrix. Optimistix's Levenberg–Marquardt linearises the
    residuals and then materialises, transposes and applies the linearised function; for a
    residual that is a simulation, each of those is another copy of the simulation in the
    compiled program. With the matrix it is one copy and matrix products: the single-record
    fit compiled in 7.1 s instead of 9.8 s and ran faster (2-core CPU). The same values
    (the linearisation is the same Jacobian). `args` is not differentiated."""

    @jax.custom_jvp
    def dense(w, args):
        return fn(w, args)

    @dense.defjvp
    def _jvp(primals, tangents):
        w, args = primals
        jac, value = jax.jacfwd(lambda v: (fn(v, args),) * 2, has_aux=True)(w)
        return value, jac @ tangents[0]

    return dense


def _gauss_newton_step(fn, x):
    """(x − (JᵀJ + μI)⁻¹Jᵀr, ½‖r‖², Newton decrement rᵀJ(JᵀJ + μI)⁻¹Jᵀr) at x."""
    jac, r = jax.jacfwd(lambda v: (fn(v), fn(v)), has_aux=True)(x)
    return _newton_step(jac, r, x)


def _newton_step(jac, r, x):
    """`_gauss_newton_step` from the Jacobian and residuals at x."""
    normal = jac.T @ jac
    mu = 1e-12 * jnp.trace(normal) / x.shape[0] + 1e-300
    gradient = jac.T @ r
    step = jnp.linalg.solve(normal + mu * jnp.eye(x.shape[0], dtype=x.dtype), gradient)
    return x - step, 0.5 * jnp.sum(r**2), gradient @ step


def _fit_record(base, prior_sigma, ctx, u_out, guesses, candidates, mode: str):
    """Fit every candidate (vmapped) to one record: from each start on the training part
    (Levenberg–Marquardt, optimistix), then, from the best start, the held-out change times
    on the held-out part (a few Gauss–Newton steps)."""
    n = u_out.shape[0]
    effects = step_effects()

    def error_of(w, candidate):
        m = unpack(w, candidate, effects, base, prior_sigma, ctx)
        prediction = predict(m, ctx, n, mode)
        if mode == "moment":
            a, log_v = moment_noise_terms(
                u_out - prediction, m.params, ctx.dt, ctx.block, ctx.max_block,
                m.moment_ratio, m.moment_phi, ctx.train,
            )
        else:
            a, log_v = innovation_terms(u_out - prediction, m.phi, m.theta, m.log_first)
        return m, prediction, a, log_v

    def residuals(w, candidate):
        m, _, a, _ = error_of(w, candidate)
        return jnp.concatenate([a * ctx.train / ctx.sigma_ref, m.penalties])

    solver = optx.LevenbergMarquardt(
        rtol=FIT_TOLERANCE, atol=FIT_TOLERANCE, linear_solver=lx.Normal(lx.Cholesky())
    )

    dense_residuals = dense_jacobian(residuals)

    def train_fit(guess, candidate):
        solution = optx.least_squares(
            dense_residuals,
            solver,
            guess,
            args=candidate,
            max_steps={
                "linear": FIT_MAX_STEPS, "moment": FIT_MAX_STEPS, "clamp": STOP_FIT_MAX_STEPS
            }.get(
                mode, CONTACT_FIT_MAX_STEPS
            ),
            throw=False,
        )
        # The residuals and the Jacobian at the solution as the solver left them: its state
        # holds the linearisation at the accepted point (with `dense_jacobian`, a matrix;
        # checked against a fresh evaluation in tests/test_diagnose_step.py), so neither
        # needs another copy of the simulation in the program.
        r = solution.state.f_info.residual
        jac = solution.state.f_info.jac.as_matrix()
        cost = jnp.sum(r**2)
        cost = jnp.where(jnp.isfinite(cost), cost, jnp.inf)
        solved = solution.result == optx.RESULTS.successful
        return solution.value, cost, solved, solution.stats["num_steps"], r, jac

    def fit_one(ws, costs, solved, steps, rs, jacs, candidate):
        best = jnp.argmin(costs)
        w = ws[best]
        # One Gauss–Newton step from the result: its predicted decrease (the Newton
        # decrement) tells whether the fit is at a minimum; taken when it lowers the cost.
        polished, cost, decrement = _newton_step(jacs[best], rs[best], w)
        converged = solved[best] | (decrement <= CONVERGED_DECREMENT + 1e-8 * cost)

        # The held-out nuisances: the times of the held-out changes, and parameters that an
        # effect declares nuisances (`held_out_nuisance`: e.g. the output offset that only
        # a stop contact reveals, which the training part may not have).
        nuisance = jnp.zeros(SLOT, w.dtype)
        for i, effect in enumerate(effects, start=1):
            mask = jnp.isin(jnp.arange(SLOT), jnp.asarray(effect.held_out_nuisance, int))
            nuisance = jnp.where(candidate == i, mask.astype(w.dtype), nuisance)
        held_levels = () if ctx.level_sigma is None else (ctx.held_out_level,)
        free = jnp.concatenate([nuisance, ctx.held_out_change, *held_levels])

        def moved(base, delta):
            return base.at[W.FROM_EFFECT].add(free * delta)

        def held_out(delta, base):
            """The held-out residuals at `base` moved by `delta`, and (aux) the training
            cost Σr² of `residuals` there and the model's prediction, innovations and ln V
            (what the fit returns)."""
            m, prediction, a, log_v = error_of(moved(base, delta), candidate)
            tail = moved(base, delta)[W.INPUT]
            n_t = n_timing(ctx)
            timing, levels = tail[:n_t], tail[n_t:]
            prior = ctx.held_out_change * timing_terms(timing, ctx)[1]
            if ctx.level_sigma is not None:  # a held-out level's error, under its prior
                prior = jnp.concatenate([prior, ctx.held_out_level * levels])
            out = jnp.concatenate([a * ctx.test / ctx.sigma_ref, prior, 1e-3 * delta[:SLOT]])
            train = jnp.sum((a * ctx.train / ctx.sigma_ref) ** 2) + jnp.sum(m.penalties**2)
            return out, (out, train, (prediction, a, log_v))

        def refine(base):
            """A few Gauss–Newton steps of the held-out nuisances from `base`: the best
            step (one pass more than there are steps: the last only costs the last step's
            result), the training cost at `base` (from the first pass), the model's
            prediction, innovations and ln V at the best step, and (one pass more) the
            prediction there with the device at its prior values (`W.REFIT` zero: what the
            refit changed). Every model evaluation of the fit after the training solve is
            a pass of this one loop, so the simulation appears once here in the compiled
            program instead of once per use (a compliant contact's fit of a 24,000-sample
            record compiled in 62–63 s instead of 71–76 s on the 2-core CPU)."""
            passes = HELD_OUT_ITERATIONS + 1

            def iterate(i, carry):
                delta, best_delta, best_cost, train_at_base, best_terms, at_prior = carry
                last = i == passes  # the extra pass: the best step, the device at its prior
                point = jnp.where(last, best_delta, delta)
                origin = jnp.where(last, base.at[W.REFIT].set(0.0), base)
                jac, (r, train, terms) = jax.jacfwd(held_out, has_aux=True)(point, origin)
                new, cost, _ = _newton_step(jac, r, delta)
                better = (cost < best_cost) & ~last
                return (
                    new,
                    jnp.where(better, delta, best_delta),
                    jnp.where(better, cost, best_cost),
                    jnp.where(i == 0, train, train_at_base),
                    jax.tree_util.tree_map(partial(jnp.where, better), terms, best_terms),
                    jnp.where(last, terms[0], at_prior),
                )

            zero = jnp.zeros_like(base[W.FROM_EFFECT])
            trace = jnp.zeros(n, base.dtype)  # a prediction's or the innovations' shape
            nothing = (trace, trace, jnp.zeros((), base.dtype))  # (prediction, a, ln V)
            carry = (zero, zero, jnp.inf, jnp.inf, nothing, trace)
            _, best_delta, _, train_at_base, terms, at_prior = jax.lax.fori_loop(
                0, passes + 1, iterate, carry
            )
            return best_delta, train_at_base, terms, at_prior

        # From the fit and from its polished point at once (one batch of two, so the model
        # appears once in the program): the polished one is kept when it lowers the
        # training cost.
        # (Batches of two: vmapped, except a compliant contact's record (`mode` "contact"),
        # which branches at run time on the contact state sample by sample: mapped, so
        # that each branch stays a branch instead of both being computed.)
        def batch(f):
            return jax.vmap(f) if mode != "contact" else partial(jax.lax.map, f)

        deltas, train_costs, terms, at_prior = batch(refine)(jnp.stack([w, polished]))
        better = train_costs[1] < 2 * cost
        w = jnp.where(better, polished, w)
        trained = w  # the training optimum, before the held-out nuisances move
        best_delta = jnp.where(better, deltas[1], deltas[0])
        w = moved(w, best_delta)
        # The fitted model (at `w`) and the same model with the device at its prior values
        # (what the refit changed), from the refine's passes of the start kept.
        prediction, a, log_v = jax.tree_util.tree_map(
            lambda x: jnp.where(better, x[1], x[0]), terms
        )
        prior_prediction = jnp.where(better, at_prior[1], at_prior[0])
        # The objective the solver minimised (Σ of the squared training residuals and of
        # every prior and penalty: ½ of it is −ln of the penalised likelihood) at the
        # training optimum kept, and that optimum: what a nested model can never end above
        # the nominal's on (`nested_failed`), and where its restart begins.
        objective = jnp.where(better, train_costs[1], train_costs[0])
        return (
            w,
            prediction,
            a,
            log_v,
            converged,
            steps[best],
            prior_prediction,
            decrement,
            objective,
            trained,
        )

    # Every (candidate, start) pair fitted in turn (`lax.map`), not vmapped: a vmapped
    # solver turns each of its branches into both branches and each loop into a masked
    # loop, and the program took twice as long to compile and five times as long to trace
    # (measured on the 2-core CPU: a single record's fit 35 → 21 s cold), while a batch of
    # 8 records ran as fast either way (each fit stops at its own step count instead of
    # waiting for the slowest). A batch of records is still vmapped outside (`sweep`).
    count, starts = guesses.shape[:2]
    pairs = (
        guesses.reshape((count * starts,) + guesses.shape[2:]),
        jnp.repeat(candidates, starts),
    )
    flat = jax.lax.map(lambda pair: train_fit(*pair), pairs)
    per_start = jax.tree_util.tree_map(lambda x: x.reshape((count, starts) + x.shape[1:]), flat)
    return jax.lax.map(lambda args: fit_one(*args), (*per_start, candidates))


def fit_linear(base, prior_sigma, ctx, u_out, guesses, candidates):
    return _fit_record(base, prior_sigma, ctx, u_out, guesses, candidates, "linear")


def fit_nonlinear(base, prior_sigma, ctx, u_out, guesses, candidates):
    return _fit_record(base, prior_sigma, ctx, u_out, guesses, candidates, "clamp")


def fit_contact(base, prior_sigma, ctx, u_out, guesses, candidates):
    return _fit_record(base, prior_sigma, ctx, u_out, guesses, candidates, "contact")


def fit_moment(base, prior_sigma, ctx, u_out, guesses, candidates):
    return _fit_record(base, prior_sigma, ctx, u_out, guesses, candidates, "moment")
