"""Clocked test sequences of hundreds of changes (a PRBS or random telegraph): their bit
clock found from the change indices, their measured levels grouped into the generator's
distinct levels, and the step diagnosis of such a record (clean and measured input) giving
its step-sequence twin's verdict. Records from the independent truth simulator
(studies/step_truth.py, written without the diagnosis code). Float64 (conftest)."""

import sys
from pathlib import Path

import numpy as np
import pytest

from accel_jax._data import DataError, NominalDevice, StepData
from accel_jax.diagnose import diagnose_many
from accel_jax.diagnose.step.inputs import CLOCK_TOLERANCE, clock_grid, level_groups

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "studies"))
import step_truth  # noqa: E402

NOMINAL = dict(torquer_time_constant=0.0, filter_time_constant=0.0)


def _prbs_column(seed, rate=1e6, duration=0.03, changes=220):
    rng = np.random.default_rng(seed)
    levels, times = step_truth.prbs_levels(
        rng, n_changes=changes, duration_s=duration, low_V=-2.0, high_V=2.0, min_bit_s=2e-5
    )
    t = np.arange(int(duration * rate)) / rate
    return t, np.asarray(levels)[np.searchsorted(times, t, side="right")], times


def test_the_bit_clock_of_a_sampled_prbs_is_found():
    for seed in range(5):
        t, column, times = _prbs_column(seed, rate=float(1e6 / (1 + seed / 3)))
        index = np.flatnonzero(np.diff(column)) + 1
        clock = clock_grid(index)
        assert clock is not None, seed
        rate = 1 / (t[1] - t[0])
        true_bit = np.min(np.diff(times)) * rate  # (the shortest run is one bit)
        assert abs(clock.period - true_bit) < 0.01 * true_bit, (clock.period, true_bit)
        assert np.max(np.abs(clock.residual)) <= CLOCK_TOLERANCE
        # The grid against the exact change times: the sampled column shows each change up
        # to one sample late, so the grid sits 0–1 sample after them.
        late = clock.phase + clock.period * clock.bits - np.asarray(times) * rate
        assert -0.2 < np.mean(late) < 1.2, np.mean(late)


@pytest.mark.parametrize("bit", [3.0, 3.3, 3.5, 4.5, 7.25])
def test_the_clock_of_bits_a_few_samples_long_is_found(bit):
    """Bits of a few samples, whole or not (runs of up to 7 bits): a start from the median
    of the short gaps once miscounted the long runs, and a fitted 3.0 came out below 3."""
    rng = np.random.default_rng(int(bit * 10))
    for _ in range(50):
        runs = np.minimum(rng.geometric(0.5, size=221), 7)
        times = (rng.uniform() + np.cumsum(runs)[:-1]) * bit
        clock = clock_grid(np.ceil(times).astype(int))
        assert clock is not None and abs(clock.period - bit) < 0.01, bit


def test_changes_on_no_common_clock_are_not_clocked():
    rng = np.random.default_rng(0)
    index = np.cumsum(rng.uniform(20, 90, 200)).astype(int)
    assert clock_grid(index) is None
    assert clock_grid([10, 20]) is None  # too few to tell


def test_measured_plateaus_group_into_the_generators_levels():
    rng = np.random.default_rng(1)
    truth = np.where(np.arange(41) % 2 == 0, 1.5, -0.5)
    sigmas = rng.uniform(1e-4, 3e-4, truth.size)
    levels = truth + sigmas * rng.normal(size=truth.size)
    group, means, errors = level_groups(levels, sigmas)
    assert means.size == 2 and np.all(group[::2] == group[0]) and group[1] != group[0]
    assert np.allclose(np.sort(means), [-0.5, 1.5], atol=5 * errors.max())
    assert np.all(errors < sigmas.min())  # the plateaus of a level averaged together


def test_close_levels_do_not_chain_into_one_group():
    """Levels 8 standard errors apart each join the one before in sorted order; against
    the group's mean, the ladder splits."""
    levels = np.arange(6) * 8e-4
    group, means, _ = level_groups(levels, np.full(6, 1e-4))
    assert means.size >= 3 and np.all(np.diff(group) >= 0)


def test_a_measured_record_joins_a_set_beside_a_clean_one():
    """The joint fit's padding takes a measured record's context (one delay parameter more
    than its changes, the timing and level maps) beside a clean record's."""
    from accel_jax.diagnose.step import joint as step_joint

    rng = np.random.default_rng(8)
    truth = step_truth.draw_truth(rng, "none")
    t, u, y, _ = step_truth.make(truth, rng)
    measured, _ = step_truth.measure_input(u, truth["rate"], rng)
    prepared = step_joint.prepare_set(
        [StepData(t, u, y), StepData(t, measured, y)], NominalDevice.reference(**NOMINAL)
    )
    assert len(prepared.preps) == 2


def test_many_changes_off_any_clock_are_refused_in_one_line():
    rng = np.random.default_rng(2)
    n = 20000
    edges = np.cumsum(rng.uniform(30, 120, 250)).astype(int)
    edges = edges[edges < n]
    u = np.where(np.searchsorted(edges, np.arange(n), side="right") % 2 == 0, 1.0, -1.0)
    t = np.arange(n) * 1e-6
    y = 0.9 * u + 1e-3 * rng.normal(size=n)
    with pytest.raises(DataError, match="not on one bit clock") as error:
        diagnose_many([StepData(t, u, y)], NominalDevice.reference(**NOMINAL))
    assert "\n" not in str(error.value)


@pytest.mark.slow
@pytest.mark.worker_of("step_cases")  # the step-sequence twin's layout is the fixture's
def test_a_prbs_record_is_diagnosed_like_its_step_sequence_twin():
    """One truth (a device with a torquer lag, the truth's conventions) driven by its small
    steps and by a 220-change PRBS; the PRBS's input also measured (delay, anti-alias,
    noise, ADC, relay spikes). The same verdict from all three."""
    rng = np.random.default_rng(4)
    truth = step_truth.draw_truth(rng, "torquer_lag")
    t, u, y, _ = step_truth.make(truth, rng)
    step_twin = StepData(t, u, y)
    prbs = dict(truth)
    levels, times = step_truth.prbs_levels(
        rng, n_changes=220, duration_s=step_truth.DURATION * 2.5, low_V=-truth["u_max_V"],
        high_V=truth["u_max_V"], min_bit_s=2e-5,
    )
    prbs["levels_V"], prbs["change_times_s"] = levels, times
    duration = step_truth.DURATION
    try:
        step_truth.DURATION = duration * 2.5  # (make reads the record's length from it)
        tp, up, yp, _ = step_truth.make(prbs, rng)
    finally:
        step_truth.DURATION = duration
    measured, _ = step_truth.measure_input(up, prbs["rate"], rng)
    nominal = NominalDevice.reference(**NOMINAL)
    results = diagnose_many([step_twin], nominal, recommend=False)
    # (with the next experiment asked for: a clocked lag tie says why there is none)
    results += diagnose_many([StepData(tp, up, yp), StepData(tp, measured, yp)], nominal)
    verdicts = [(r.verdict, sorted(r.tied)) for r in results]
    assert verdicts[1] == verdicts[0] and verdicts[2] == verdicts[0], verdicts
    assert verdicts[0][0] != "none"
    for r in results[1:]:
        assert any(n.startswith("u_test: 220 changes on one bit clock") for n in r.notes)
        assert any(n.startswith("no next experiment designed") for n in r.notes)
    # The clean twin's nominal fit (the wrong model) strains one nuisance only: the
    # output's lateness behind the input's column, the torquer lag's own signature
    # (`nuisance.LATE_OUTPUT_SIGMA`); the clock's rate and the gain stay within 3σ.
    test = results[1].refit["nuisance_test"]
    assert not test["strained"] or test["largest"] == "input_delay", test
    assert all(abs(v) < 3 for k, v in test["standardised"].items() if k != "input_delay"), test
    # The measured twin's nominal fit (the wrong model: the truth has a torquer lag) may
    # strain one nuisance only: the input channel's drift, which the PRBS's 221 plateaus of
    # two levels pin to ±71 µV over the record (the truth's channel drifts by −13 µV), so it
    # can no longer absorb the lag's misfit; the verdict is the step twin's (above).
    test = results[2].refit["nuisance_test"]
    assert not test["strained"] or test["largest"] == "input_channel_drift", test
    assert any("2 distinct levels" in n for n in results[2].notes)


def test_mapped_timing_parameters_keep_a_gradient_beyond_their_limit():
    """The clock's (or a measured channel's delay's) parameters are limited smoothly: a fit
    that overshoots its limit in a first step can come back (a hard clip has no gradient
    there; a measured record's delay once stayed at the clip with every level strained)."""
    from types import SimpleNamespace

    import jax
    import jax.numpy as jnp

    from accel_jax.diagnose.step.fit import timing_terms

    ctx = SimpleNamespace(
        timing_map=jnp.array([[1.0, 1.0], [0.0, 1.0]]),
        timing_offset=jnp.array([0.25, -0.5]),
        timing_mean=jnp.array([-0.5, 0.0]),
        timing_sigma=jnp.array([1.0, 4.0]),
        timing_limit=jnp.array([4.0, 8.0]),
        timing_sigma_late=None,
    )
    shift, prior = timing_terms(jnp.array([-0.5, 1.0]), ctx)
    assert jnp.allclose(prior, jnp.array([0.0, 0.25]))
    assert abs(float(shift[1]) - (-0.5 + 8 * np.tanh(1 / 8))) < 1e-12
    beyond = jax.jacfwd(lambda p: timing_terms(p, ctx)[0])(jnp.array([6.0, 12.0]))
    assert np.all(np.asarray(beyond)[ctx.timing_map > 0] > 0.01)


def test_a_measured_channels_delay_is_held_on_its_late_side_by_its_prior():
    """A measured input channel only adds delay (its column shows a change late): its delay
    parameter's prior is `DELAY_PRIOR_SIGMA` wide where it moves the changes earlier and
    `DELAY_LATE_SIGMA` where it moves them later, so that the nominal fit cannot take up a
    lag in the loop as a late output for little; a prior, not a limit, so the gradient
    stays; the changes' own shifts keep their symmetric prior, and the limits are as
    before."""
    from types import SimpleNamespace

    import jax
    import jax.numpy as jnp

    from accel_jax.diagnose.step.fit import timing_terms
    from accel_jax.diagnose.step.model import (
        DELAY_LATE_SIGMA,
        DELAY_LIMIT,
        DELAY_PRIOR_SIGMA,
        TIMING_LIMIT,
    )

    ctx = SimpleNamespace(
        timing_map=jnp.array([[1.0, 1.0], [0.0, 1.0]]),
        timing_offset=jnp.zeros(2),
        timing_mean=jnp.array([-0.5, 0.0]),
        timing_sigma=jnp.array([1.0, DELAY_PRIOR_SIGMA]),
        timing_limit=jnp.array([TIMING_LIMIT, DELAY_LIMIT]),
        timing_sigma_late=jnp.array([1.0, DELAY_LATE_SIGMA]),
    )
    for p in (3.0, -3.0):
        shift, prior = timing_terms(jnp.array([0.5, p]), ctx)
        assert float(shift[1]) == pytest.approx(DELAY_LIMIT * np.tanh(p / DELAY_LIMIT))
        sigma = DELAY_LATE_SIGMA if p > 0 else DELAY_PRIOR_SIGMA
        assert np.allclose(np.asarray(prior), [1.0, p / sigma])  # the change's own: 1σ

    def penalty(p):
        return 0.5 * jnp.sum(timing_terms(jnp.array([-0.5, p]), ctx)[1] ** 2)

    # Continuous, with its gradient, through the mean; steep on the late side only.
    assert float(jax.grad(penalty)(0.0)) == 0.0
    assert float(penalty(1e-9)) == pytest.approx(0.0, abs=1e-12)
    assert float(jax.grad(penalty)(2.0)) == pytest.approx(2.0 / DELAY_LATE_SIGMA**2)
    assert float(jax.grad(penalty)(-2.0)) == pytest.approx(-2.0 / DELAY_PRIOR_SIGMA**2)
    # Without `timing_sigma_late` (an exact column's clock), one σ on both sides.
    ctx.timing_sigma_late = None
    assert np.allclose(
        np.asarray(timing_terms(jnp.array([0.5, 3.0]), ctx)[1]), [1.0, 3.0 / DELAY_PRIOR_SIGMA]
    )
