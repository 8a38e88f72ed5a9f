"""`_simulate.contact.contact_record`, the loop with compliant (spring-damper) stops: the
linear record when the stops are out of reach, the inelastic clamp of `stop_record` in the
stiff, damped limit, convergence in the parts of a step, forward-mode derivatives against
finite differences, block means, and a stop on one side only."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import accel_jax as aj
from accel_jax._simulate.contact import contact_record
from accel_jax._simulate.sequence import SequenceInputs, linear_record, stop_record


RATE = 1e6
DT = 1 / RATE
LEVELS = np.array([0.5, 2.0, 0.0, -2.0, 2.0, 0.0])
SEGMENT = 1000
N = SEGMENT * LEVELS.size
INDEX = np.arange(1, LEVELS.size) * SEGMENT + np.array([3, -7, 0, 5, 1])
IDEAL = aj.ServoParams.reference(torquer_time_constant=0.0, filter_time_constant=0.0)
STOP = 1.8
"""The stops [V of deflection]: the ±2 V levels press the pendulum onto them."""


def _sequence():
    shifts = np.random.default_rng(1).uniform(-1, 1, INDEX.size)
    changes = (jnp.asarray(INDEX), jnp.asarray(np.diff(LEVELS)), jnp.asarray(shifts))
    return SequenceInputs(LEVELS[0], 1.0, 0.0, 0.0, 0.0, 0.0, *changes)


def _contact(high, low, stiffness, damping, **kw):
    return np.asarray(contact_record(IDEAL, DT, N, _sequence(), high, low, stiffness, damping, **kw))


def test_out_of_reach_stops_give_the_linear_record():
    linear = np.asarray(linear_record(IDEAL, DT, N, _sequence(), duration=DT * (N - 1)))
    np.testing.assert_allclose(_contact(1e6, -1e6, 100.0, 0.5), linear, rtol=0, atol=1e-12)


def test_a_stiff_damped_contact_approaches_the_inelastic_stop():
    # Stiffer and stiffer contacts (critically over-damped, so that they do not bounce)
    # close on the clamp that loses the velocity at the contact and holds the pendulum.
    clamp = np.asarray(stop_record(IDEAL, DT, N, _sequence(), STOP, -STOP))
    gaps = [
        np.max(np.abs(_contact(STOP, -STOP, k, 10.0, substeps=64) - clamp)) for k in (1e5, 1e7)
    ]
    assert gaps[1] < 0.5 * gaps[0]
    assert gaps[1] < 5e-5 * STOP
    # A soft contact lets the pendulum well past the stop.
    soft = _contact(STOP, -STOP, 10.0, 0.5)
    assert np.max(soft) > 1.1 * STOP


@pytest.mark.parametrize(("stiffness", "damping", "atol"), [(300.0, 0.3, 1e-9), (3000.0, 0.05, 2e-4)])
def test_the_parts_of_a_step_converge(stiffness, damping, atol):
    # A contact of moderate stiffness is taken exactly part by part; a stiff, lightly
    # damped one chatters on the stop (ever shorter bounces, several within one part)
    # and converges more slowly: 8 parts are within 2e-4 V of 64 (below the records' noise).
    coarse = _contact(STOP, -STOP, stiffness, damping)
    fine = _contact(STOP, -STOP, stiffness, damping, substeps=64)
    assert np.max(np.abs(coarse)) < 1.05 * STOP < np.max(np.abs(coarse)) + 0.3
    np.testing.assert_allclose(coarse, fine, rtol=0, atol=atol)


def test_forward_derivatives_match_finite_differences():
    def loss(p):
        record = contact_record(IDEAL, DT, N, _sequence(), p[0], -p[0], p[1], p[2])
        return jnp.sum(record**2)

    p = jnp.array([STOP, 300.0, 0.3])
    derivative = jax.jacfwd(loss)(p)
    for i, rel in enumerate([1e-6, 1e-3, 1e-5]):
        step = jnp.zeros(3).at[i].set(rel * p[i])
        fd = (loss(p + step) - loss(p - step)) / (2 * rel * p[i])
        np.testing.assert_allclose(derivative[i], fd, rtol=1e-5)


def test_block_means_and_a_stop_on_one_side_only():
    one_sided = _contact(STOP, -1e6, 300.0, 0.3)
    # m = 1 steps sample by sample; m ≥ WHOLE_BLOCK_MIN takes free blocks whole (m traced,
    # as the diagnosis passes it, under one `max_block`).
    blocks = 300
    blocked = jax.jit(
        lambda m: contact_record(
            IDEAL, DT, blocks, _sequence(), STOP, -1e6, 300.0, 0.3, block=m, max_block=32,
            duration=DT * (N - 1),
        )
    )
    for m in (4, 20):
        means = one_sided[: blocks * m].reshape(-1, m).mean(1)
        np.testing.assert_allclose(np.asarray(blocked(m)), means, rtol=0, atol=1e-12)
    # The lower side is free: the −2 V level's overshoot passes −STOP as far as the linear
    # record's, while the upper stop holds the +2 V levels near STOP.
    assert np.max(one_sided) < 1.05 * STOP
    assert np.min(one_sided) < -1.1 * STOP


@pytest.mark.parametrize("block", [1, 20])
def test_a_step_or_block_held_on_a_stop_is_the_part_by_part_flow(block):
    # A sample step (and a block of 20) that starts in a contact and stays in it is one
    # exact step of that contact's flow (`whole_holds`): the record that takes every such
    # step part by part, the switches looked for in each part, is the same to round-off —
    # on a soft contact, a chattering one, and a stop on one side only.
    for stiffness, damping, low in ((10.0, 0.5, -STOP), (3000.0, 0.05, -STOP), (300.0, 0.3, -1e6)):
        records = [
            np.asarray(
                contact_record(
                    IDEAL, DT, N // block, _sequence(), STOP, low, stiffness, damping,
                    block=block, max_block=32, whole_holds=whole,
                )
            )
            for whole in (True, False)
        ]
        assert np.max(records[0]) > STOP  # pressed into the stop
        np.testing.assert_allclose(records[0], records[1], rtol=0, atol=1e-11)
