"""The noise diagnosis's view of a record (`prepare`, a `NoiseRecord`): the training part
(the first 1 − `HELD_OUT_FRACTION`), the level and scale the record is normalised by, and
every candidate's starts from `accel_jax._noise.initial_model`."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from ..._data import DataError, NoiseData
from ..._noise import initial_model
from .effects import _SLOT, STARTS, AbstractNoiseEffect
from .state import NoiseRecord, NoiseStarts

HELD_OUT_FRACTION = 1 / 3
"""The last third of the record is held out."""


def prepare(data: NoiseData, effects: Sequence[AbstractNoiseEffect]) -> NoiseRecord:
    """The record normalised by its training part's mean and standard deviation, with the
    starts of the nominal model and of each of `effects` (a `DataError` for a constant
    training part or one `initial_model` cannot start from)."""
    x = np.asarray(data.a_out, dtype=np.float64)
    n = x.size
    split = int(round((1 - HELD_OUT_FRACTION) * n))
    train = x[:split]
    if np.ptp(train) == 0:
        raise DataError(
            f"noise record: a_out is constant ({float(train[0])!r} g) over the training part "
            f"(first {split} samples); no noise to diagnose (a disconnected or saturated channel?)."
        )
    level = float(np.mean(train))
    scale = float(np.std(train))
    dt = float(data.sample_period)
    normalised = (x - level) / scale
    initial = {}
    for effect in effects:
        try:
            initial[effect.name] = initial_model(effect.structure, normalised[:split], dt)
        except ValueError as error:
            raise DataError(f"noise record: {error}") from None
    starts = NoiseStarts(initial_models=initial, dt=dt)
    guesses = np.zeros((1 + len(effects), STARTS, 1 + _SLOT))  # nominal: σ_w = s₀ (z = 0)
    for i, effect in enumerate(effects, start=1):
        guess = effect.initial_guess(starts)
        guesses[i, :, 0] = math.log(float(initial[effect.name].components[0].sigma))
        guesses[i, 0, 1 : 1 + effect.n_params] = guess
        guesses[i, 1:, 1 : 1 + effect.n_params] = effect.alternative_starts(guess)
    return NoiseRecord(
        normalised=normalised,
        split=split,
        level=level,
        scale=scale,
        dt=dt,
        duration=float(data.t[-1] - data.t[0]),
        guesses=guesses,
    )
