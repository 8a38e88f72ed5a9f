"""The step diagnosis's fit vectors (accel_jax/diagnose/step/layout.py): the named indices
and slices of a record's w and a set's x cover each vector once, in the order the fits
read them."""

import numpy as np

from accel_jax.diagnose.step.joint import SetLayout
from accel_jax.diagnose.step.layout import N_LAG_STATES, SLOT, Own, Shared, W


def _owners(size, parts):
    """For each entry of a vector of `size`, the names of the parts that take it."""
    owners = [[] for _ in range(size)]
    for name, where in parts.items():
        for i in np.arange(size)[where].ravel():
            owners[i].append(name)
    return owners


def test_a_record_s_w_is_named_once_per_entry():
    n_timing, n_levels = 5, 6
    size = W.FIXED + n_timing + n_levels
    parts = {
        "refit": W.REFIT,
        "moment": W.MOMENT,
        "gain": W.GAIN,
        "dv": W.DV,
        "dw": W.DW,
        "effect": W.EFFECT,
        "timing": W.timing(n_timing),
        "levels": W.levels(n_timing),
    }
    assert all(len(o) == 1 for o in _owners(size, parts))
    w = np.arange(size)
    assert w[W.EFFECT].size == SLOT and list(w[W.effect(1)]) == [W.FIXED - SLOT]
    assert np.array_equal(w[W.BEFORE_EFFECT], np.arange(W.EFFECT.start))
    assert np.array_equal(w[W.FROM_EFFECT], np.concatenate([w[W.EFFECT], w[W.INPUT]]))
    assert np.array_equal(
        w[W.INPUT], np.concatenate([w[W.timing(n_timing)], w[W.levels(n_timing)]])
    )
    assert w[W.DRIFT] == w[W.levels(n_timing)][-1]


def test_a_set_s_x_is_named_once_per_entry():
    j = 8
    width = SetLayout(n_padded=256, j_padded=j, stops=(False,), lag_states=True).width
    shared = {
        "refit": Shared.REFIT,
        "lag": Shared.LAG,
        "stop": Shared.STOP,
        "gain": Shared.GAIN,
        "accel": Shared.ACCEL,
    }
    assert all(len(o) == 1 for o in _owners(Shared.SIZE, shared))
    x = np.arange(Shared.SIZE)
    assert list(x[Shared.SCALES]) == [Shared.STOP, Shared.GAIN, Shared.ACCEL]
    assert list(x[Shared.GAINS]) == [Shared.GAIN, Shared.ACCEL]
    own = {
        "moment": Own.MOMENT,
        "dv": Own.DV,
        "dw": Own.DW,
        "offset": Own.OFFSET,
        "timing": Own.timing(j),
        "lag_states": Own.lag_states(j),
    }
    assert all(len(o) == 1 for o in _owners(width, own))
    assert np.arange(width)[Own.lag_states(j)].size == N_LAG_STATES
    assert np.arange(width)[Own.through_timing(j)].size == width - N_LAG_STATES
