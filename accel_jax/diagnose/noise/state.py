"""The noise diagnosis's typed state of one record (host side, NumPy): what `record.prepare`
reads from a record (`NoiseRecord`) and what an effect's start reads (`NoiseStarts`).

Each is a frozen dataclass: a stage that changes one makes a new one with
`dataclasses.replace`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import numpy as np


@dataclasses.dataclass(frozen=True)
class NoiseStarts:
    """What an effect's start reads (`AbstractNoiseEffect.initial_guess`).

    **Fields:** `initial_models` the `accel_jax._noise.initial_model` of white noise plus
    each effect (a `NoiseSum` whose second component is the effect's process), by effect
    name, fitted to the normalised training record; `dt` [s] the sample interval.
    """

    initial_models: Mapping[str, Any]
    dt: float


@dataclasses.dataclass(frozen=True, eq=False)
class NoiseRecord:
    """One static record as the noise fit sees it (`record.prepare`).

    **Fields:** `normalised` the record (a_out − `level`) / `scale`, all of it; `split` the
    number of training samples (the first 1 − `HELD_OUT_FRACTION` of the record); `level`
    [g] and `scale` [g] the training part's mean and standard deviation s₀; `dt` [s] the
    sample interval; `duration` [s] t[-1] − t[0]; `guesses` every candidate's starts,
    shape (1 + effects, `STARTS`, 1 + `_SLOT`): [ln σ_w, effect slot] in the fit's scaled
    parameters (the nominal's all zero: σ_w = s₀).
    """

    normalised: np.ndarray
    split: int
    level: float
    scale: float
    dt: float
    duration: float
    guesses: np.ndarray
