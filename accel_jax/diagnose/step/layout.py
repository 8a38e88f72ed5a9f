"""Where each parameter lies in the step diagnosis's fit vectors, named once here: a
record's w (`fit`: `W`) and a set's x (`joint`: the shared part `Shared`, then each
record's own part `Own`). The fits see flat vectors (one Jacobian, one linear solve);
every reader names what it takes by these indices and slices.
"""

from __future__ import annotations

SLOT = 4
"""Parameters of the effect slot of w: as many as the step effect with the most has
(`stop_contact`: two clearances, a stiffness and a damping ratio)."""

N_LAG_STATES = 2
"""A set's free initial lag states per record (the joint fit's second stage)."""


class W:
    """A record's fit vector w (`fit.unpack`), all O(1): the refit z of J, μ, c, k_dm
    (`REFIT`), the external moment (`MOMENT`), the test winding's gain z (`GAIN`), the
    initial displacement and velocity (`DV`, `DW`), the effect slot (`EFFECT`), the
    timing parameters (`timing(n)`, n = `fit.n_timing`: one per change, or a clock's
    shift and rate) and, for a measured input, the level errors (`levels(n)`), the last of
    them the input channel's drift (`DRIFT`). Each name is an index or a slice of w."""

    REFIT = slice(0, 4)
    MOMENT = 4
    GAIN = 5
    DV = 6
    DW = 7
    BEFORE_EFFECT = slice(0, 8)
    """The device's z and the record's own nuisances: everything before the slot."""
    EFFECT = slice(8, 8 + SLOT)
    FIXED = 8 + SLOT
    """How many parameters come before the timing ones (the index of the first)."""
    INPUT = slice(FIXED, None)
    """The input's nuisances: the timing parameters and the level errors."""
    FROM_EFFECT = slice(8, None)
    """The slot and the input's nuisances: what the held-out refit may move."""
    DRIFT = -1

    @staticmethod
    def effect(k: int) -> slice:
        """The first `k` parameters of the slot (an effect's own)."""
        return slice(8, 8 + k)

    @staticmethod
    def timing(n: int) -> slice:
        """The `n` timing parameters."""
        return slice(W.FIXED, W.FIXED + n)

    @staticmethod
    def levels(n: int) -> slice:
        """The level errors and the drift, after `n` timing parameters."""
        return slice(W.FIXED + n, None)


class Shared:
    """The shared part of a set's x (`joint`), first in x: the refit z of J, μ, c, k_dm
    (`REFIT`), the lag's departure z (`LAG`), and the z of the stop voltage (`STOP`), of
    the test winding's gain (`GAIN`) and of the pendulosity (`ACCEL`); `SIZE` of them."""

    REFIT = slice(0, 4)
    LAG = 4
    STOP = 5
    GAIN = 6
    ACCEL = 7
    SIZE = 8
    SCALES = slice(5, 8)
    """The stop voltage's, test gain's and pendulosity's z (each under N(0, 1))."""
    GAINS = slice(6, 8)
    """The test gain's and pendulosity's z (each held within `fit.REFIT_BOUND`)."""


class Own:
    """Each record's own part of a set's x (`joint_set.SetLayout.width` long, after the shared
    part): the external moment (`MOMENT`), the initial displacement and velocity (`DV`,
    `DW`), the output offset (`OFFSET`), the change times (`timing(j)`, j the set's change
    slots) and, in the second stage, the initial lag states (`lag_states(j)`,
    `N_LAG_STATES`)."""

    MOMENT = 0
    DV = 1
    DW = 2
    OFFSET = 3
    TIMING = 4
    """The index of the first change time (how many parameters come before them)."""

    @staticmethod
    def timing(j: int) -> slice:
        """The `j` change times."""
        return slice(Own.TIMING, Own.TIMING + j)

    @staticmethod
    def through_timing(j: int) -> slice:
        """Everything up to and with the `j` change times (all but the lag states)."""
        return slice(0, Own.TIMING + j)

    @staticmethod
    def lag_states(j: int) -> slice:
        """The initial lag states after `j` change times (empty in the first stage)."""
        return slice(Own.TIMING + j, None)
