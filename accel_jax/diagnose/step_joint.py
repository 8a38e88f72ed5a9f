"""Several step records of one device, diagnosed together (issue 20): one shared set of
device and effect parameters, per-record nuisances, and the experiment that would break a
tie.

A torquer lag inside the loop and a filter on the output give the same all-pole cubic from
a small test step, so one small-step record cannot tell them apart. Two experiments do:

- **stop-level test steps** (the in-flight test of docs/models.md §1, eq. (11)): the pendulum is
  driven onto its mechanical stops, where the loop is open. The output filter then rounds
  the corner of the clipped deflection; the torquer lag does not (it delays the release);
- **an acceleration step** (`a_in`, a tilt or centrifuge step): through W(p) the torquer lag
  adds a zero (1 + T_dm p) that the output filter does not.

**Joint model.** Candidates: the nominal device, `torquer_lag`, `output_filter` (the lag
effects of `step_effects`, departures from the nominal device's T_dm, T_f). Shared by every
record: the refit of J, μ, c, k_dm (log-normal prior, as `step.py`), the lag departure, the
stop voltage v_stop = k_dp k_y h_max (log-normal, `STOP_SIGMA`), the test winding's gain
(`step_fit.GAIN_SIGMA`) and the pendulosity's (`ACCEL_SIGMA`). Per record: the polarity of
the test winding and of the input axis (from the settled levels), the external moment, the
initial state, the output offset (seen only on the stops; N(0, `OFFSET_PRIOR`)) and the
time of every input change. A record whose test levels can reach the nominal stops is
simulated with them (`_simulate.sequence.stop_record`), the others exactly
(`linear_record`). White output noise, each record's floor measured without the model
(`step_record.prepare`).

**Verdict.** Fitted on every block of every record (the models have ≤ 1 parameter beyond the
shared device; held-out testing is the single-record diagnosis's, `diagnose_step`): the
evidence 2 ln B of each lag against the nominal (Schwarz, profiled noise per record), and
each record's excess RMS over its floor. `none` when the nominal leaves every record at its
floor and no lag is significant; a lag's name when it is significant, leaves every record at
its floor, and beats the other lag by `INDISTINCT`; `cannot_tell` when both do within it;
`unexplained` when no candidate brings every record to its floor.

**Second stage.** Each record's initial lag states follow its initial deflection and
velocity by a first-order rule (`_simulate.sequence.initial_state`), exact to
O((T_lag/T)²). A record that starts in a transient soon after an earlier level or a stop
contact, with a long lag, departs from it. When no candidate brings every record to its
floor, every candidate is refitted from its own solution with those states free as well
(`release_lag_states`; N(0, 1) in the record's scale) and judged again; the note says so.
The second stage nests the first and starts at its solution, so its penalised cost cannot
rise. (Free
from the start, the states let the stop-level torquer-lag fit stall far from the floor.)

**Next experiment.** With `cannot_tell`, each experiment of a menu (`experiment_menu`) is
simulated noise-free from the fitted first candidate and refitted by the second (all
records together, the new one added): the expected 2 ln B is the misfit that remains,
Σ r²/σ², and the same the other way round; the smaller of the two is reported.

Float64 throughout (x64 must be enabled).
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx

from .._data import DataError, NominalDevice, StepData
from .._servo import closed_loop_test_gain
from .._simulate.sequence import SequenceInputs, accel_moment, linear_record, stop_record
from . import openworld
from .base import INDISTINCT, SIGNIFICANCE, require_float64, verdict_line
from .step_effects import OutputFilter, TorquerLag
from .step_fit import (
    _I_DV,
    _I_DW,
    _I_GAIN,
    _I_MOMENT,
    _I_TIMING,
    BARRIER,
    GAIN_SIGMA,
    REFIT_BOUND,
    REFIT_FIELDS,
    TIMING_LIMIT,
    TIMING_PRIOR,
    dense_jacobian,
    moment_jumps,
    refitted_device,
)
from .step_record import MAX_CHANGES, prepare, prior_sigma_of, stack_on_host, time_text

CANDIDATES = ("nominal", "torquer_lag", "output_filter")
"""The joint fit's models: the nominal device and the two lags that a small step cannot
tell apart."""

STOP_SIGMA = 0.1
"""Relative (1σ) prior uncertainty of the stop voltage k_dp k_y h_max."""

ACCEL_SIGMA = 0.05
"""Relative (1σ) prior uncertainty of the pendulosity m l (the acceleration's gain)."""

OFFSET_PRIOR = 0.02
"""σ [V] of the prior of a record's output offset (told from the moment only on the stops)."""

STOP_REACH = 0.5
"""A record is simulated with the stops when its largest test level times the nominal test
gain reaches this fraction of the nominal stop voltage (an overshoot can reach the stops
from there)."""

LAG_BOUND = 100.0
LAG_STARTS = (2.0,)
"""Start of each lag's departure z (units of 3 % of the loop's T, ~9 µs for the reference
device), from the nominal fit's solution: one start (the two starts z = 1 and z = 5 of the
first version ended at the same cost on the records tried)."""

MAX_STEPS = 60
NOMINAL_MAX_STEPS = 30
"""The nominal fit's step limit: when it is the right model it converges in a few steps;
when a lag is missing it grinds on a misfit thousands of floors wide, where a few more
steps change nothing in the verdict."""

TOLERANCE = 1e-7

# Shared parameters: refit z (4), lag z, stop z, test-gain z, pendulosity z.
_S_LAG, _S_STOP, _S_GAIN, _S_ACCEL = 4, 5, 6, 7
N_SHARED = 8
# Per record: moment, dv, dw, offset, change times (J), and in the second stage the initial
# lag states' departures from their first-order rule (2; `SetLayout.lag_states`).
_R_MOMENT, _R_DV, _R_DW, _R_OFFSET = 0, 1, 2, 3
_R_TIMING = 4
N_LAG_STATES = 2


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
        level_sigma=None,
        held_out_level=None,
        drift_step=None,
        timing_map=None,
        timing_offset=None,
        timing_mean=None,
        timing_sigma=None,
        timing_limit=None,
        level_map=None,
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
        return _R_TIMING + self.j_padded + (N_LAG_STATES if self.lag_states else 0)


def _lag_params(params, lag_z, candidate, ctx):
    torquer, output = TorquerLag(), OutputFilter()
    zero = jnp.zeros_like(lag_z)
    params = torquer.device(params, jnp.stack([jnp.where(candidate == 1, lag_z, 0.0), zero]), ctx)
    return output.device(params, jnp.stack([jnp.where(candidate == 2, lag_z, 0.0), zero]), ctx)


def _record_prediction(shared, own, candidate, base, prior_sigma, ctx, n, stop_voltage, on_stops):
    params = refitted_device(base, shared[:4], prior_sigma)
    params = _lag_params(params, shared[_S_LAG], candidate, ctx)
    gain = ctx.polarity * jnp.exp(GAIN_SIGMA * shared[_S_GAIN])
    jumps = moment_jumps(params, ctx, jnp.exp(ACCEL_SIGMA * shared[_S_ACCEL]))
    j = ctx.change_step.shape[-1]
    lag_states = own[_R_TIMING + j :]
    lag_states = (
        (ctx.scale * lag_states[0], ctx.scale * lag_states[1]) if lag_states.size else (0.0, 0.0)
    )
    sequence = SequenceInputs(
        ctx.first_level,
        gain,
        ctx.scale * own[_R_MOMENT],
        jnp.zeros_like(own[0]),
        ctx.scale * own[_R_DV],
        ctx.scale * own[_R_DW],
        ctx.change_index,
        ctx.change_step,
        jnp.clip(own[_R_TIMING : _R_TIMING + j], -TIMING_LIMIT, TIMING_LIMIT),
        jumps,
        lag_states,
    )
    offset = OFFSET_PRIOR * own[_R_OFFSET]
    if on_stops:
        stop = stop_voltage * jnp.exp(STOP_SIGMA * shared[_S_STOP])
        out = stop_record(
            params, ctx.dt, n, sequence, stop, -stop, block=ctx.block, duration=ctx.duration
        )
    else:
        out = linear_record(
            params,
            ctx.dt,
            n,
            sequence,
            block=ctx.block,
            max_block=ctx.max_block,
            duration=ctx.duration,
        )
    return out + offset


def _split(x, n_records, layout):
    shared = x[:N_SHARED]
    own = x[N_SHARED:].reshape(n_records, layout.width)
    return shared, own


def _penalties(shared, own, candidate, ctx_stack):
    lag = shared[_S_LAG]
    used = (candidate != 0).astype(shared.dtype)
    j = ctx_stack.change_step.shape[-1]
    timing = own[:, _R_TIMING : _R_TIMING + j]
    active = ((ctx_stack.change_step != 0) | (ctx_stack.change_accel != 0)).astype(shared.dtype)
    return jnp.concatenate(
        [
            shared[:4],
            shared[_S_STOP : _S_ACCEL + 1],
            BARRIER * jnp.maximum(jnp.abs(shared[:4]) - REFIT_BOUND, 0.0),
            BARRIER * jnp.maximum(jnp.abs(shared[_S_GAIN : _S_ACCEL + 1]) - REFIT_BOUND, 0.0),
            (lag * (1 - used))[None],
            (BARRIER * jnp.maximum(jnp.abs(lag) - LAG_BOUND, 0.0) * used)[None],
            own[:, _R_OFFSET],
            own[:, _R_TIMING + j :].ravel(),  # lag states: N(0, 1) in the record's scale
            ((timing - TIMING_PRIOR[0]) / TIMING_PRIOR[1] * active).ravel(),
            (timing * (1 - active)).ravel(),
        ]
    )


def _predictions(x, candidate, base, prior_sigma, ctx_stack, layout, stop_voltage):
    n_records = ctx_stack.dt.shape[0]
    shared, own = _split(x, n_records, layout)
    outs = []
    for r in range(n_records):
        ctx = jax.tree_util.tree_map(lambda leaf, r=r: leaf[r], ctx_stack)
        outs.append(
            _record_prediction(
                shared,
                own[r],
                candidate,
                base,
                prior_sigma,
                ctx,
                layout.n_padded,
                stop_voltage,
                layout.stops[r],
            )
        )
    return jnp.stack(outs)


def _residuals(x, candidate, base, prior_sigma, ctx_stack, layout, stop_voltage, data, weight):
    prediction = _predictions(x, candidate, base, prior_sigma, ctx_stack, layout, stop_voltage)
    return _misfit(prediction, x, candidate, ctx_stack, layout, data, weight)


def _misfit(prediction, x, candidate, ctx_stack, layout, data, weight):
    """The residuals of a prediction: each record's misfit over its floor, then the
    penalties (priors and barriers) of x."""
    shared, own = _split(x, ctx_stack.dt.shape[0], layout)
    scaled = (data - prediction) * weight / ctx_stack.sigma_ref[:, None]
    return jnp.concatenate([scaled.ravel(), _penalties(shared, own, candidate, ctx_stack)])


@eqx.filter_jit
def _fit(
    starts, candidates, base, prior_sigma, ctx_stack, layout, stop_voltage, data, weight, max_steps
):
    """Levenberg–Marquardt fits (optimistix), one per (start, candidate) pair."""
    solver = optx.LevenbergMarquardt(
        rtol=TOLERANCE, atol=TOLERANCE, linear_solver=lx.Normal(lx.Cholesky())
    )

    def one(x0, candidate):
        def fn(x, _):
            return _residuals(
                x, candidate, base, prior_sigma, ctx_stack, layout, stop_voltage, data, weight
            )

        # The Jacobian as a matrix (`dense_jacobian`): one copy of the simulation in the
        # solver's program instead of its linearisation, materialisation and transpose.
        solution = optx.least_squares(
            dense_jacobian(fn), solver, x0, max_steps=max_steps, throw=False
        )
        x = solution.value
        prediction = _predictions(x, candidate, base, prior_sigma, ctx_stack, layout, stop_voltage)
        penalties = _penalties(*_split(x, ctx_stack.dt.shape[0], layout), candidate, ctx_stack)
        # The cost from the same prediction (no second simulation).
        cost = jnp.sum(_misfit(prediction, x, candidate, ctx_stack, layout, data, weight) ** 2)
        return (
            x,
            jnp.where(jnp.isfinite(cost), cost, jnp.inf),
            prediction,
            penalties,
            (solution.result == optx.RESULTS.successful),
            solution.stats["num_steps"],
        )

    # One fit after another (`lax.map`, not `vmap`): a record with stops then takes the
    # contact branch of `stop_record` only at the steps that reach a stop.
    return jax.lax.map(lambda pair: one(*pair), (starts, candidates))


# --------------------------------------------------------------------------------------
# Host side: preparing a set, fitting it, judging it
# --------------------------------------------------------------------------------------


def nominal_stop_voltage(params) -> float:
    """k_dp k_y h_max [V]: the deflection voltage at the stops (docs/models.md §1, eq. (11))."""
    return float(params.pickoff_gain * params.amplifier_gain * params.stop_displacement)


@dataclasses.dataclass
class PreparedSet:
    preps: list
    layout: SetLayout
    ctx: object
    data: np.ndarray
    weight: np.ndarray
    stop_voltage: float


def prepare_set(datasets: list[StepData], nominal: NominalDevice) -> PreparedSet:
    """Each record's context (`step_record.prepare`), padded to common shapes and stacked."""
    if not datasets:
        raise DataError("no records to diagnose.")
    preps = [prepare(d, nominal, []) for d in datasets]
    for i, p in enumerate(preps):
        if p["clock"] is not None:
            raise DataError(
                f"record {i + 1}: a clocked sequence of {p['change_index'].size} changes; the "
                f"joint diagnosis of a set takes at most {MAX_CHANGES} changes per record "
                "(diagnose it alone, or split it into shorter records)."
            )
    v_stop = nominal_stop_voltage(nominal.params)
    for p in preps:  # the inputs as read (a measured column's spikes are not levels)
        reach = float(np.max(np.abs(np.asarray(p["data"].u_test)))) * p["k_test"]
        p["on_stops"] = bool(reach >= STOP_REACH * v_stop)
    return stack(preps, v_stop)


def stack(preps: list[dict], stop_voltage: float, lag_states: bool = False) -> PreparedSet:
    """Prepared records (`prepare` dicts with `on_stops`) as one padded, stacked set;
    `lag_states` whether each record's initial lag states are free (`SetLayout`)."""
    n_padded = max(p["group"][0] for p in preps)
    j_padded = max(p["group"][1] for p in preps)
    max_block = max(p["group"][2] for p in preps)
    ctxs = [_pad_context(p["ctx"], n_padded, j_padded, max_block) for p in preps]
    ctxs = [
        dataclasses.replace(c, sigma_ref=np.asarray(p["sigma"], np.float64))
        for c, p in zip(ctxs, preps, strict=True)
    ]
    ctx = stack_on_host(ctxs)
    data = np.zeros((len(preps), n_padded))
    weight = np.zeros((len(preps), n_padded))
    for r, p in enumerate(preps):
        data[r, : p["n"]] = p["u_out"][: p["n"]]
        weight[r, : p["n"]] = 1.0
    layout = SetLayout(
        n_padded=n_padded,
        j_padded=j_padded,
        stops=tuple(p["on_stops"] for p in preps),
        lag_states=lag_states,
    )
    return PreparedSet(preps, layout, ctx, data, weight, stop_voltage)


def _start(prepared: PreparedSet) -> np.ndarray:
    """The nominal start: each record's own levels regression (`prepare`'s guesses)."""
    preps = prepared.preps
    shared = np.zeros(N_SHARED)
    linear = [p for p in preps if not p["on_stops"] and np.any(p["change_step"] != 0)]
    if linear:
        shared[_S_GAIN] = float(np.mean([p["guesses_linear"][0, 0, _I_GAIN] for p in linear]))
    accel = [p for p in preps if p["has_accel"] and np.any(p["change_accel"] != 0)]
    if accel:
        k = [abs(p["accel_slope"]) / (p["k_test"] * p["host"]["accel_per_g"]) for p in accel]
        shared[_S_ACCEL] = float(np.clip(np.log(np.mean(k)) / ACCEL_SIGMA, -5, 5))
    own = np.zeros((len(preps), prepared.layout.width))
    for r, p in enumerate(preps):
        w = p["guesses_linear"][0, 0]
        own[r, _R_MOMENT] = w[_I_MOMENT]
        own[r, _R_DV] = w[_I_DV]
        own[r, _R_DW] = w[_I_DW]
        timing = w[_I_TIMING : _I_TIMING + p["group"][1]]  # (not a measured input's levels)
        own[r, _R_TIMING : _R_TIMING + timing.size] = timing
        if p["on_stops"]:
            own[r, _R_DV] = own[r, _R_DW] = 0.0
    return np.concatenate([shared, own.ravel()])


def fit_set(
    prepared: PreparedSet, nominal: NominalDevice, candidates=CANDIDATES, start=None, starts=None
):
    """Fit the candidates to the set. Returns one dict per candidate: x, cost, prediction
    (records, blocks), penalties, converged. The nominal is fitted first (from `start`, by
    default `_start`'s regression); each lag starts from its solution with the lag at
    `LAG_STARTS`. `starts` {candidate: x} instead starts each candidate from its own x, its
    lag included (all in one batch, at most `MAX_STEPS`)."""
    names = list(candidates)
    base = nominal.params
    prior_sigma = jnp.asarray(prior_sigma_of(nominal))
    args = (
        base,
        prior_sigma,
        prepared.ctx,
        prepared.layout,
        jnp.asarray(prepared.stop_voltage),
        jnp.asarray(prepared.data),
        jnp.asarray(prepared.weight),
    )
    if starts is not None:
        ids = jnp.asarray([CANDIDATES.index(c) for c in names], jnp.int32)
        x = jnp.asarray(np.stack([np.asarray(starts[c]) for c in names]))
        out = _fit(x, ids, *args, MAX_STEPS)
        return {c: _best(out, [i]) for i, c in enumerate(names)}
    x0 = _start(prepared) if start is None else np.asarray(start)
    fits = {}
    if "nominal" in names:
        starts = np.stack([x0])
        out = _fit(jnp.asarray(starts), jnp.zeros(1, jnp.int32), *args, NOMINAL_MAX_STEPS)
        fits["nominal"] = _best(out, [0])
        x0 = np.asarray(fits["nominal"]["x"])
    lags = [c for c in names if c != "nominal"]
    if lags:
        starts, ids, owners = [], [], []
        for name in lags:
            for s in LAG_STARTS:
                x = x0.copy()
                x[_S_LAG] = s
                starts.append(x)
                ids.append(CANDIDATES.index(name))
                owners.append(name)
        out = _fit(jnp.asarray(np.stack(starts)), jnp.asarray(ids, jnp.int32), *args, MAX_STEPS)
        for name in lags:
            fits[name] = _best(out, [i for i, o in enumerate(owners) if o == name])
    return fits


def _best(out, rows):
    x, cost, prediction, penalties, solved, steps = (np.asarray(o) for o in out)
    i = rows[int(np.argmin(cost[rows]))]
    return {
        "x": x[i],
        "cost": float(cost[i]),
        "prediction": prediction[i],
        "penalties": penalties[i],
        "converged": bool(solved[i]),
        "steps": [int(steps[k]) for k in rows],
    }


def _score(fit, prepared: PreparedSet, nominal: NominalDevice) -> dict:
    """Profiled log-likelihood, per-record excess over the floor, and the physical values."""
    preps = prepared.preps
    log_like = 0.0
    records = []
    for r, p in enumerate(preps):
        n = p["n"]
        error = prepared.data[r, :n] - fit["prediction"][r, :n]
        rss = max(float(np.sum(error**2)), 1e-300)
        log_like += -0.5 * n * math.log(rss / n)
        sigma = p["sigma"]
        over = openworld.excess(rss / n, sigma**2) / sigma
        records.append(
            {
                "rms_V": math.sqrt(rss / n),
                "noise_floor_V": sigma,
                "excess_over_floor": over,
                "at_floor": bool(over <= openworld.FLOOR_FACTOR),
            }
        )
    shared = fit["x"][:N_SHARED]
    priors = np.concatenate([shared[:4], shared[_S_STOP : _S_ACCEL + 1]])
    log_like -= 0.5 * float(np.sum(priors**2))
    return {"log_likelihood": log_like, "records": records, "n": sum(p["n"] for p in preps)}


def shared_values(fit, prepared: PreparedSet, nominal: NominalDevice, candidate: str) -> dict:
    """The shared physical values of a fitted candidate."""
    base = nominal.params
    x = fit["x"]
    sigma = prior_sigma_of(nominal)
    values = {}
    for i, field in enumerate(REFIT_FIELDS):
        if sigma[i] > 0:
            values[field] = {
                "value": float(getattr(base, field)) * math.exp(sigma[i] * x[i]),
                "nominal": float(getattr(base, field)),
                "shift_sigma": float(x[i]),
            }
    unit = prepared.preps[0]["host"]["lag_unit"]
    lags = prepared.preps[0]["host"]["nominal_lags"]
    for name, field in (
        ("torquer_lag", "torquer_time_constant"),
        ("output_filter", "filter_time_constant"),
    ):
        z = x[_S_LAG] if candidate == name else 0.0
        values[field] = max(lags[field] + unit * z, 0.0)
    if any(prepared.layout.stops):
        stop = prepared.stop_voltage * math.exp(STOP_SIGMA * x[_S_STOP])
        values["stop_voltage_V"] = stop
        values["stop_voltage_nominal_V"] = prepared.stop_voltage
        # eq. (11): on the stop the output is k_dp k_y h_max; with h_max known, k_dp k_y.
        values["pickoff_amplifier_gain_from_stops"] = stop / float(base.stop_displacement)
    values["test_gain_relative"] = math.exp(GAIN_SIGMA * x[_S_GAIN])
    if any(p["has_accel"] for p in prepared.preps):
        values["pendulosity_relative"] = math.exp(ACCEL_SIGMA * x[_S_ACCEL])
    return values


@dataclasses.dataclass
class SetDiagnosis:
    """The diagnosis of several step records of one device.

    **Fields:** `verdict` (`none`, `torquer_lag`, `output_filter`, `cannot_tell`,
    `unexplained`); `tied` (with `cannot_tell`); `reason`; `ranking` (per candidate: evidence
    2 ln B against the nominal, records at their floor, shared values); `records` (per
    record: name, whether simulated with the stops, its excess over the floor under the
    chosen model); `shared` (the chosen model's shared device values); `next_experiment`
    (with `cannot_tell`: the best experiments of `experiment_menu`, each with its expected
    2 ln B); `notes`.
    """

    verdict: str
    tied: list
    reason: str
    ranking: list
    records: list
    shared: dict
    next_experiment: list = dataclasses.field(default_factory=list)
    notes: list = dataclasses.field(default_factory=list)
    kind: str = "step_set"
    traces: dict = dataclasses.field(default_factory=dict, repr=False)

    def to_dict(self) -> dict:
        return {
            "kind": self.kind,
            "verdict": self.verdict,
            "tied": list(self.tied),
            "reason": self.reason,
            "ranking": self.ranking,
            "records": self.records,
            "shared": self.shared,
            "next_experiment": self.next_experiment,
            "notes": list(self.notes),
        }

    def summary(self) -> str:
        lines = [f"kind: step (joint diagnosis of {len(self.records)} records of one device)"]
        lines.append(verdict_line(self.verdict, self.tied))
        lines.append(f"why: {self.reason}")
        for r in self.records:
            stops = ", simulated with the stops" if r["on_stops"] else ""
            lines.append(
                f"record {r['name']}{stops}: residual {r['excess_over_floor']:.2f} floors above "
                f"its {r['noise_floor_V']:.3g} V noise floor"
            )
        lines.append("ranking (evidence = 2 ln B against the nominal model, all records together):")
        for r in self.ranking:
            at = "every record at its floor" if r["all_at_floor"] else "misfit remains"
            lines.append(f"  {r['effect']:<14} evidence {r['evidence']:>9.1f}  {at}")
        values = self.shared
        lag = [
            f"T_dm {time_text(values['torquer_time_constant'])}",
            f"T_f {time_text(values['filter_time_constant'])}",
        ]
        lines.append("shared: " + ", ".join(lag) + _shared_extra(values))
        for e in self.next_experiment[:3]:
            lines.append(
                f"next experiment: {e['description']} (expected 2 ln B ≈ {e['expected_2lnB']:.0f})"
            )
        lines.extend(f"note: {n}" for n in self.notes)
        return "\n".join(lines)


def _shared_extra(values) -> str:
    parts = []
    for field in REFIT_FIELDS:
        if field in values:
            parts.append(f"{field} {values[field]['shift_sigma']:+.1f}σ")
    if "stop_voltage_V" in values:
        parts.append(
            f"stop voltage k_dp·k_y·h_max {values['stop_voltage_V']:.4g} V (nominal "
            f"{values['stop_voltage_nominal_V']:.4g} V)"
        )
    return ("; " + ", ".join(parts)) if parts else ""


def diagnose_step_set(
    datasets: list[StepData],
    nominal: NominalDevice | None = None,
    *,
    names: list[str] | None = None,
    recommend: bool = True,
) -> SetDiagnosis:
    """Diagnose several step records of one device together (see the module docstring).

    **Arguments:** `datasets` validated `StepData` records of one device (small steps,
    stop-level steps, acceleration steps in any mix); `nominal` its nominal device (default
    the reference); `names` the records' names for the report; `recommend` whether a
    `cannot_tell` computes the next experiment (`next_experiments`).

    **Returns:** a `SetDiagnosis`. Float64 (x64 must be enabled; `ValueError` otherwise).
    """
    require_float64("the evidence compares log-likelihoods of ~1e4 to within ~1")
    nominal = NominalDevice.reference() if nominal is None else nominal
    names = names or [f"#{i + 1}" for i in range(len(datasets))]
    prepared = prepare_set(list(datasets), nominal)
    fits = fit_set(prepared, nominal)
    scores, ranking = _rank(fits, prepared, nominal)
    notes = [
        f"{name}: {note}"
        for name, p in zip(names, prepared.preps, strict=True)
        for note in p["notes"]
    ]
    if not any(r["all_at_floor"] for r in ranking):
        first = min(r["worst_excess_over_floor"] for r in ranking)
        prepared, fits = release_lag_states(prepared, nominal, fits)
        scores, ranking = _rank(fits, prepared, nominal)
        notes.append(
            "with every record's initial lag states on their first-order rule no candidate "
            f"brought every record to its floor (best worst record {first:.2f} floors); "
            "refitted with them free (second stage, `release_lag_states`)"
        )
    return _diagnose_prepared(prepared, nominal, fits, scores, ranking, names, notes, recommend)


def _rank(fits, prepared: PreparedSet, nominal: NominalDevice):
    """Each candidate's score (`_score`) and ranking entry: evidence against the nominal
    (Schwarz: ln n per lag parameter), records at their floor, shared values."""
    scores = {c: _score(fits[c], prepared, nominal) for c in CANDIDATES}
    n_total = scores["nominal"]["n"]
    ranking = []
    for c in CANDIDATES:
        evidence = 2 * (scores[c]["log_likelihood"] - scores["nominal"]["log_likelihood"])
        if c != "nominal":
            evidence -= math.log(n_total)
        ranking.append(
            {
                "effect": c,
                "evidence": float(evidence) if c != "nominal" else 0.0,
                "all_at_floor": all(r["at_floor"] for r in scores[c]["records"]),
                "worst_excess_over_floor": max(
                    r["excess_over_floor"] for r in scores[c]["records"]
                ),
                "converged": fits[c]["converged"],
                "shared": shared_values(fits[c], prepared, nominal, c),
            }
        )
    return scores, ranking


def _verdict(ranking):
    by = {r["effect"]: r for r in ranking}
    lags = sorted((r for r in ranking if r["effect"] != "nominal"), key=lambda r: -r["evidence"])
    good = [r for r in lags if r["evidence"] >= SIGNIFICANCE and r["all_at_floor"]]
    tied: list = []
    if by["nominal"]["all_at_floor"] and not any(r["evidence"] >= SIGNIFICANCE for r in lags):
        verdict = "none"
        reason = (
            "the nominal device, refitted within its prior, leaves every record at its noise "
            "floor and neither lag is significant"
        )
    elif good and (len(good) == 1 or good[0]["evidence"] - good[1]["evidence"] >= INDISTINCT):
        verdict = good[0]["effect"]
        other = lags[1]
        reason = (
            f"{verdict} brings every record to its floor (evidence {good[0]['evidence']:.1f} "
            f"against the nominal, {good[0]['evidence'] - other['evidence']:.1f} against "
            f"{other['effect']})"
        )
    elif len(good) == 2:
        verdict = "cannot_tell"
        tied = [good[0]["effect"], good[1]["effect"]]
        reason = (
            f"both lags bring every record to its floor; their evidence differs by "
            f"{good[0]['evidence'] - good[1]['evidence']:.1f} (< {INDISTINCT:g}): these "
            "records cannot separate a lag inside the loop from one on the output"
        )
    else:
        verdict = "unexplained"
        worst = min(ranking, key=lambda r: r["worst_excess_over_floor"])
        reason = (
            "no candidate brings every record to its floor; the best "
            f"({worst['effect']}) leaves {worst['worst_excess_over_floor']:.2f} floors of "
            "excess in its worst record (an effect outside the joint model: run the "
            "single-record diagnosis of each record)"
        )
    return verdict, tied, reason


def _diagnose_prepared(prepared, nominal, fits, scores, ranking, names, notes, recommend):
    verdict, tied, reason = _verdict(ranking)
    by = {r["effect"]: r for r in ranking}
    chosen = verdict if verdict in CANDIDATES else (tied[0] if tied else "nominal")
    records = []
    for r, (name, p) in enumerate(zip(names, prepared.preps, strict=True)):
        entry = {"name": name, "on_stops": p["on_stops"], "has_accel": p["has_accel"]}
        entry.update(scores[chosen]["records"][r])
        records.append(entry)
    traces = {
        "records": [
            {
                "name": name,
                "t": np.asarray(p["view"].t),
                "u_out": prepared.data[r, : p["n"]],
                "sigma": p["sigma"],
                "predictions": {c: fits[c]["prediction"][r, : p["n"]] for c in CANDIDATES},
            }
            for r, (name, p) in enumerate(zip(names, prepared.preps, strict=True))
        ],
        "chosen": chosen,
    }
    result = SetDiagnosis(
        verdict=verdict,
        tied=tied,
        reason=reason,
        ranking=ranking,
        records=records,
        shared=by[chosen]["shared"],
        notes=notes,
        traces=traces,
    )
    if verdict == "cannot_tell" and recommend:
        result.next_experiment = next_experiments(prepared, nominal, fits, tied)
        if result.next_experiment:
            best = result.next_experiment[0]
            result.reason += (
                f"; to separate {tied[0]} from {tied[1]}, {best['description']} (expected "
                f"2 ln B ≈ {best['expected_2lnB']:.0f})"
            )
    return result


# --------------------------------------------------------------------------------------
# The next experiment
# --------------------------------------------------------------------------------------


def experiment_menu(nominal: NominalDevice, sample_rate: float, noise_V: float) -> list[dict]:
    """Experiments a user can run on the device, each as a record design (t, u_test, a_in)
    at `sample_rate`, 8 ms long, in equal segments (`levels_V`, `accel_levels_g`):
    stop-level test steps (±1.3 × the nominal stop voltage
    over the test gain), a larger small step, an acceleration step of ±1 g, and the small
    step sampled 4× faster."""
    params = nominal.params
    k_test = float(closed_loop_test_gain(params))
    v_stop = nominal_stop_voltage(params)
    u_stop = round(1.3 * v_stop / k_test, 1)
    menu = []

    def design(rate, levels, *, accel=None, description, duration=8e-3):
        n = int(round(duration * rate))
        t = np.arange(n) / rate
        edges = np.linspace(0, n, len(levels) + 1).astype(int)[1:-1]
        index = np.searchsorted(edges, np.arange(n), side="right")
        u = np.asarray(levels, float)[index]
        a = None if accel is None else np.asarray(accel, float)[index]
        return {
            "description": description,
            "record": StepData(t=t, u_test=u, u_out=np.zeros(n), a_in=a),
            "noise_V": noise_V,
            "levels_V": [float(x) for x in levels],
            "accel_levels_g": None if accel is None else [float(x) for x in accel],
        }

    menu.append(
        design(
            sample_rate,
            [0.0, u_stop, -u_stop, u_stop, 0.0],
            description=f"record +{u_stop:g} V and −{u_stop:g} V test steps onto the stops",
        )
    )
    menu.append(
        design(
            sample_rate,
            [0.0, 0.0, 0.0, 0.0, 0.0],
            accel=[0.0, 1.0, -1.0, 1.0, 0.0],
            description="record ±1 g acceleration steps along the input axis (tilt or "
            "centrifuge), test voltage off",
        )
    )
    menu.append(
        design(
            sample_rate,
            [0.0, 2.0, -2.0, 2.0, 0.0],
            description="record another ±2 V small-step sequence",
        )
    )
    menu.append(
        design(
            4 * sample_rate,
            [0.0, 2.0, -2.0, 2.0, 0.0],
            description=f"record the ±2 V steps at {4 * sample_rate / 1e6:g} MHz",
        )
    )
    return menu


# One program per design shape; run eagerly, the simulation's hundreds of small operations
# were each compiled on their own (about 5 s of a cold lag-tie diagnosis).
_record_prediction_compiled = eqx.filter_jit(_record_prediction)


def _simulate_design(fit, prepared: PreparedSet, nominal, candidate, design) -> StepData:
    """The design's record as the fitted `candidate` predicts it (noise-free): the set's
    shared values, polarity +1, no offset, at rest at the start."""
    record = design["record"]
    probe = prepare_set([_with_output(record, nominal)], nominal)
    probe.preps[0]["sigma"] = design["noise_V"]
    ctx = jax.tree_util.tree_map(lambda leaf: leaf[0], probe.ctx)
    shared = jnp.asarray(fit["x"][:N_SHARED])
    own = np.zeros(probe.layout.width)  # the design's changes at its samples' boundaries
    ctx = dataclasses.replace(ctx, polarity=jnp.asarray(1.0), accel_sign=jnp.asarray(1.0))
    n = probe.layout.n_padded
    out = _record_prediction_compiled(
        shared,
        jnp.asarray(own),
        jnp.asarray(CANDIDATES.index(candidate)),
        nominal.params,
        jnp.asarray(prior_sigma_of(nominal)),
        ctx,
        n,
        jnp.asarray(prepared.stop_voltage),
        probe.layout.stops[0],
    )
    m = probe.preps[0]["block"]
    blocks = np.asarray(out)[: probe.preps[0]["n"]]
    y = np.repeat(blocks, m)
    y = np.concatenate([y, np.full(record.t.size - y.size, y[-1])])
    return StepData(t=record.t, u_test=record.u_test, u_out=y, a_in=record.a_in)


def _with_output(record: StepData, nominal) -> StepData:
    """A design record with a placeholder response (its linear settled levels plus a
    ramp, so that `prepare` finds a non-constant output)."""
    k = float(closed_loop_test_gain(nominal.params))
    y = k * np.asarray(record.u_test) + 1e-6 * np.arange(record.t.size)
    if record.a_in is not None:
        y = y + k * float(accel_moment(nominal.params)) * np.asarray(record.a_in)
    return StepData(t=record.t, u_test=record.u_test, u_out=y, a_in=record.a_in)


def expected_evidence(
    prepared: PreparedSet, nominal, fits, truth: str, rival: str, design
) -> float:
    """Expected 2 ln B of `truth` over `rival` once `design` is added to the set: the fitted
    `truth` simulated noise-free on every record (the set's and the design's), `rival`
    refitted to all of them; its misfit Σ r²/σ² (σ each record's floor; the design's its
    `noise_V` per sample over √(samples per block)). Both models have the same number of
    parameters, so no penalty enters."""
    truth_fit = fits[truth]
    new = prepare_set([_simulate_design(truth_fit, prepared, nominal, truth, design)], nominal)
    preps = []
    for r, p in enumerate(prepared.preps):
        q = dict(p)
        u_out = np.zeros_like(p["u_out"])
        u_out[: p["n"]] = truth_fit["prediction"][r, : p["n"]]
        q["u_out"] = u_out
        preps.append(q)
    added = dict(new.preps[0])
    added["sigma"] = design["noise_V"] / math.sqrt(added["block"])
    combined = stack(preps + [added], prepared.stop_voltage, prepared.layout.lag_states)
    start = _transfer_start(fits[rival]["x"], prepared, combined)
    fit = fit_set(combined, nominal, candidates=[rival], starts={rival: start})[rival]
    chi2 = 0.0
    for r, p in enumerate(combined.preps):
        n = p["n"]
        error = combined.data[r, :n] - fit["prediction"][r, :n]
        chi2 += float(np.sum(error**2)) / p["sigma"] ** 2
    return chi2


def _transfer_start(x, old: PreparedSet, new: PreparedSet) -> np.ndarray:
    """Fitted parameters of `old` as a start for `new` (the same records first, perhaps more
    of them, more change slots or free lag states): each record's own values carried over
    section by section, the rest at zero (a new record's changes at the sample boundaries,
    as simulated; lag states on their first-order rule)."""
    shared = x[:N_SHARED]
    own_old = x[N_SHARED:].reshape(len(old.preps), old.layout.width)
    own = np.zeros((len(new.preps), new.layout.width))
    k = len(old.preps)
    j = min(old.layout.j_padded, new.layout.j_padded)
    own[:k, : _R_TIMING + j] = own_old[:, : _R_TIMING + j]
    if old.layout.lag_states and new.layout.lag_states:
        own[:k, -N_LAG_STATES:] = own_old[:, -N_LAG_STATES:]
    return np.concatenate([shared, own.ravel()])


def release_lag_states(prepared: PreparedSet, nominal: NominalDevice, fits: dict):
    """The second stage: every candidate refitted with each record's initial lag states free
    (N(0, 1) in the record's scale), from its first-stage solution. A record that starts in
    a transient soon after a stop contact or an earlier level, with a long lag, departs from
    the first-order start rule of `initial_state`; the first stage then leaves it above its
    floor. The second stage nests the first and starts at its solution, so no candidate's
    penalised cost can rise (a single record's misfit can). Returns the widened set and its
    fits."""
    wide = stack(prepared.preps, prepared.stop_voltage, lag_states=True)
    starts = {c: _transfer_start(fits[c]["x"], prepared, wide) for c in fits}
    return wide, fit_set(wide, nominal, candidates=list(fits), starts=starts)


def next_experiments(prepared: PreparedSet, nominal, fits, tied) -> list[dict]:
    """The menu's experiments ranked by the expected 2 ln B that separates the tied pair
    (the smaller of the two directions)."""
    rate = 1.0 / prepared.preps[0]["dt_sample"]
    noise = max(p["floor"]["sigma_per_sample_V"] for p in prepared.preps)
    out = []
    for design in experiment_menu(nominal, rate, noise):
        one = expected_evidence(prepared, nominal, fits, tied[0], tied[1], design)
        two = expected_evidence(prepared, nominal, fits, tied[1], tied[0], design)
        out.append(
            {
                "description": design["description"],
                "expected_2lnB": float(min(one, two)),
                f"expected_2lnB_if_{tied[0]}": float(one),
                f"expected_2lnB_if_{tied[1]}": float(two),
                "levels_V": design["levels_V"],
                "accel_levels_g": design["accel_levels_g"],
                "sample_rate_Hz": float(1 / design["record"].sample_period),
                "duration_s": float(design["record"].t[-1] + design["record"].sample_period),
            }
        )
    out.sort(key=lambda e: -e["expected_2lnB"])
    return out


def set_figure(result: SetDiagnosis):
    """One row per record: the measured block means with the chosen model (left), and each
    candidate's residual in units of the record's noise floor (right)."""
    import matplotlib

    if matplotlib.get_backend().lower() not in ("agg", "pdf", "svg", "cairo"):
        matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = result.traces["records"]
    fig, axes = plt.subplots(len(rows), 2, figsize=(13, 2.6 * len(rows) + 0.8), squeeze=False)
    chosen = result.traces["chosen"]
    for (left, right), row in zip(axes, rows, strict=True):
        t = 1e3 * (row["t"] - row["t"][0])
        left.plot(t, row["u_out"], lw=0.8, color="0.3", label="measured (block means)")
        left.plot(t, row["predictions"][chosen], lw=0.8, color="C3", ls="--", label=chosen)
        left.set_ylabel("U_out [V]")
        left.set_title(str(row["name"]), fontsize=9, loc="left")
        left.legend(fontsize=7, loc="best")
        for k, (name, prediction) in enumerate(row["predictions"].items()):
            residual = (row["u_out"] - prediction) / row["sigma"]
            right.plot(t, residual, lw=0.6, color=f"C{k}", label=name)
        right.axhspan(-1, 1, color="0.85", zorder=0)
        right.set_ylabel("residual / floor")
        right.set_yscale("symlog", linthresh=3)
        right.legend(fontsize=7, loc="best")
    for ax in axes[-1]:
        ax.set_xlabel("time [ms]")
    title = f"joint step diagnosis: {result.verdict}"
    if result.tied:
        title += f" ({result.tied[0]} or {result.tied[1]})"
    fig.suptitle(title + "; residual band ±1 noise floor", fontsize=10)
    fig.tight_layout()
    return fig
