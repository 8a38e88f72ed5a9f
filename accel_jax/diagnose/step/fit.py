"""The step diagnosis's fit (JAX): the vmapped least-squares fit of every candidate of a
record (Levenberg–Marquardt from each start, then the held-out nuisances by Gauss–Newton),
with the one-step errors of the candidate's noise model (`innovations`). The candidate
model it fits — parameters, context, prediction — is `model`'s, re-exported here.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import lineax as lx
import optimistix as optx

from .effects import AbstractStepEffect, step_effects
from .innovations import innovation_terms, moment_noise_terms
from .layout import SLOT, W
from .solver import MinimumEnding, StallEnding
from .model import (
    BARRIER as BARRIER,
    DELAY_LIMIT as DELAY_LIMIT,
    DELAY_PRIOR_SIGMA as DELAY_PRIOR_SIGMA,
    GAIN_SIGMA as GAIN_SIGMA,
    KNOWN_DELAY_SIGMA as KNOWN_DELAY_SIGMA,
    MODES as MODES,
    REFIT_BOUND as REFIT_BOUND,
    REFIT_FIELDS as REFIT_FIELDS,
    TIMING_LIMIT as TIMING_LIMIT,
    TIMING_PRIOR as TIMING_PRIOR,
    CandidateModel as CandidateModel,
    StepContext as StepContext,
    moment_jumps as moment_jumps,
    n_timing as n_timing,
    predict as predict,
    refitted_device as refitted_device,
    timing_terms as timing_terms,
    unpack as unpack,
)

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
(the starts are mapped, not vmapped), so the limit costs only where a start does not; a
start that has stalled ends as at the limit (`solver.StallEnding`)."""

FIT_MAX_STEPS = 30
"""Levenberg–Marquardt steps per start. A batch runs until its slowest fit stops, and the
fits of effects that do not describe the record creep on for many steps after the loss has
settled, so a fit that is not done by then is judged by its Newton decrement instead."""

CONTACT_FIT_MAX_STEPS = 100
"""Levenberg–Marquardt steps of a compliant-stop fit: its stiffness and damping move the
record far from where a start puts them (a soft, bouncing contact). A start that has
stalled ends as at the limit (`solver.StallEnding`)."""

CONVERGED_DECREMENT = 0.5
"""A fit counts as converged when the solver says so or when a full Gauss–Newton step from
its result would lower the cost ½Σr² (r in noise-floor units) by less than this plus 1e-8
of the cost: where the cost is near quadratic, its log-likelihood is then within that of
the minimum, and the evidence (2 ln B) within 1 — the precision a significance threshold
of 10 needs. Each fit ends at the first point that passes (`_at_minimum`). Where the cost
is far from quadratic it is no bound: on the quick report's blind records, ending there
moved 5 of 131 evidences by more than 1 (at most 16 of 3,887), all noise candidates on
records they do not describe (docs/performance.md)."""

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


def _at_minimum(jac, r):
    """Whether a full Gauss–Newton step from the point of Jacobian `jac` and residuals `r`
    would lower ½Σr² by less than `CONVERGED_DECREMENT` (+ 1e-8 of it): the test by which
    `fit_one` counts a fit converged."""
    _, cost, decrement = _newton_step(jac, r, jnp.zeros(jac.shape[1], r.dtype))
    return _decrement_small(decrement, cost)


def _decrement_small(decrement, cost):
    """The test of `CONVERGED_DECREMENT` on a Newton decrement at cost ½Σr² = `cost`."""
    return decrement <= CONVERGED_DECREMENT + 1e-8 * cost


def _fit_record(base, prior_sigma, ctx, u_out, guesses, candidates, mode: str):
    """Fit every candidate (vmapped) to one record: from each start on the training part
    (Levenberg–Marquardt, optimistix), then, from the best start, the held-out change times
    on the held-out part (a few Gauss–Newton steps)."""
    n = u_out.shape[0]
    effects = step_effects()
    # The stops' programs fit only the stop effects, which carry no noise model (white
    # noise: the innovations are the errors themselves), so they need no filter at all.
    white = mode in ("clamp", "contact") and all(
        type(e).noise is AbstractStepEffect.noise for e in effects if e.nonlinear
    )

    # (A jit of its own: the solver, the Jacobian and the held-out passes call it with the
    # same shapes, and its trace is made once per `whole` and transformed, not traced again
    # from Python. Four records, one core, cold: tracing 36.9 → 28.4 s, backend compile
    # 131.1 → 120.2 s; the same evidences to the bit on four others; docs/performance.md.)
    @partial(jax.jit, static_argnames="whole")
    def error_of(w, candidate, whole=True):
        """The model's penalties at w, its prediction, and the innovations and ln V
        ((k, n), (k,)): first of the training part alone (its own: the held-out blocks are
        gaps, so that the training likelihood never reads the held-out errors; for white
        noise the same as the whole record's), then, with `whole`, of the whole record (what
        the held-out part is judged on). Both from one filter over a batch of masks, so that
        it appears once in the program; the training solve asks for the training part's
        alone."""
        m = unpack(w, candidate, effects, base, prior_sigma, ctx)
        penalties = m.penalties
        prediction = predict(m, ctx, n, mode)
        error = u_out - prediction
        masks = jnp.stack([ctx.train, jnp.ones_like(ctx.train)] if whole else [ctx.train])
        if white:  # what `innovation_terms` gives at φ = θ = ln V₀ = 0, exactly
            a = jnp.where(masks > 0, error, 0.0)
            log_v = jnp.zeros(masks.shape[0], error.dtype)
        elif mode == "moment":
            a, log_v = jax.vmap(
                lambda observed: moment_noise_terms(
                    error, m.params, ctx.dt, ctx.block, ctx.max_block,
                    m.moment_ratio, m.moment_phi, ctx.train, observed,
                )
            )(masks)
        else:
            a, log_v = jax.vmap(
                lambda train: innovation_terms(error, m.phi, m.theta, m.log_first, train)
            )(masks)
        return penalties, prediction, a, log_v

    def residuals(w, candidate):
        penalties, _, a, _ = error_of(w, candidate, whole=False)
        return jnp.concatenate([a[0] * ctx.train / ctx.sigma_ref, penalties])

    solver = optx.LevenbergMarquardt(
        rtol=FIT_TOLERANCE, atol=FIT_TOLERANCE, linear_solver=lx.Normal(lx.Cholesky())
    )
    if mode in ("clamp", "contact"):  # dear steps, a high limit: a stalled fit ends early
        solver = StallEnding(solver)
    # A fit ends once its point would count as converged (`_at_minimum`, as `fit_one`
    # judges it), not only when its steps' and cost's changes fall below FIT_TOLERANCE.
    solver = MinimumEnding(solver, _at_minimum)

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
        converged = solved[best] | _decrement_small(decrement, cost)

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
            penalties, prediction, (a_train, a), (log_v_train, log_v) = error_of(
                moved(base, delta), candidate
            )
            tail = moved(base, delta)[W.INPUT]
            n_t = n_timing(ctx)
            timing, levels = tail[:n_t], tail[n_t:]
            prior = ctx.held_out_change * timing_terms(timing, ctx)[1]
            if ctx.level_sigma is not None:  # a held-out level's error, under its prior
                prior = jnp.concatenate([prior, ctx.held_out_level * levels])
            out = jnp.concatenate([a * ctx.test / ctx.sigma_ref, prior, 1e-3 * delta[:SLOT]])
            train = jnp.sum((a_train * ctx.train / ctx.sigma_ref) ** 2)
            train = train + jnp.sum(penalties**2)
            return out, (out, train, (prediction, a, log_v), (a_train, log_v_train))

        def refine(base):
            """A few Gauss–Newton steps of the held-out nuisances from `base`: the best
            step (one pass more than there are steps: the last only costs the last step's
            result), the training cost at `base` (from the first pass), the model's
            prediction and innovations at the best step, (one pass more) the prediction
            there with the device at its prior values (`W.REFIT` zero: what the refit
            changed), and the training part's innovations and ln V at `base` (from the
            first pass) for the likelihood. Every model evaluation of the fit after the
            training solve is a pass of this one loop, so the simulation appears once here
            in the compiled program instead of once per use (a compliant contact's fit of a
            24,000-sample record compiled in 62–63 s instead of 71–76 s on the 2-core
            CPU)."""
            passes = HELD_OUT_ITERATIONS + 1

            def iterate(i, carry):
                delta, best_delta, best_cost, train_at_base, best_terms, at_train, at_prior = (
                    carry
                )
                last = i == passes  # the extra pass: the best step, the device at its prior
                # The first pass, at `base` itself (the training optimum): the training
                # part's innovations and ln V, the likelihood the evidence compares, at the
                # parameters the training part chose. Not at the best step: the held-out
                # refit moves every sample after a held-out change (the state carries
                # across the segments) and an effect's own nuisances (a stop's output
                # offset) move every sample; read there, a stop fit's training ln L ended
                # thousands below the nominal it contains, its objective better.
                training = i == 0
                point = jnp.where(last, best_delta, delta)
                origin = jnp.where(last, base.at[W.REFIT].set(0.0), base)
                jac, (r, train, terms, own) = jax.jacfwd(held_out, has_aux=True)(
                    point, origin
                )
                new, cost, _ = _newton_step(jac, r, delta)
                better = (cost < best_cost) & ~last
                return (
                    new,
                    jnp.where(better, delta, best_delta),
                    jnp.where(better, cost, best_cost),
                    jnp.where(training, train, train_at_base),
                    jax.tree_util.tree_map(partial(jnp.where, better), terms, best_terms),
                    jax.tree_util.tree_map(partial(jnp.where, training), own, at_train),
                    jnp.where(last, terms[0], at_prior),
                )

            zero = jnp.zeros_like(base[W.FROM_EFFECT])
            trace = jnp.zeros(n, base.dtype)  # a prediction's or the innovations' shape
            nothing = (trace, trace, jnp.zeros((), base.dtype))  # (prediction, a, ln V)
            carry = (zero, zero, jnp.inf, jnp.inf, nothing, nothing[1:], trace)
            _, best_delta, _, train_at_base, terms, at_train, at_prior = jax.lax.fori_loop(
                0, passes + 1, iterate, carry
            )
            return best_delta, train_at_base, terms, at_train, at_prior

        # From the fit and from its polished point at once (one batch of two, so the model
        # appears once in the program): the polished one is kept when it lowers the
        # training cost.
        # (Batches of two: vmapped, except a compliant contact's record (`mode` "contact"),
        # which branches at run time on the contact state sample by sample: mapped, so
        # that each branch stays a branch instead of both being computed.)
        def batch(f):
            return jax.vmap(f) if mode != "contact" else partial(jax.lax.map, f)

        deltas, train_costs, terms, at_train, at_prior = batch(refine)(jnp.stack([w, polished]))
        better = train_costs[1] < 2 * cost
        w = jnp.where(better, polished, w)
        trained = w  # the training optimum, before the held-out nuisances move
        # Of the start kept (one selection over every output of `refine`): the held-out
        # nuisances' best step; the fitted model (at `w`: its prediction and innovations);
        # the training part's innovations and ln V at the training optimum (the likelihood
        # the evidence compares: `refine`'s training pass); the same model with the device
        # at its prior values (what the refit changed); and the objective the solver
        # minimised (Σ of the squared training residuals and of every prior and penalty:
        # ½ of it is −ln of the penalised likelihood) at the training optimum: what a
        # nested model can never end above the nominal's on (`nested_failed`).
        best_delta, (prediction, a, _), (a_train, log_v), prior_prediction, objective = (
            jax.tree_util.tree_map(
                lambda x: jnp.where(better, x[1], x[0]),
                (deltas, terms, at_train, at_prior, train_costs),
            )
        )
        w = moved(w, best_delta)
        return (
            w,
            prediction,
            a,
            a_train,
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
