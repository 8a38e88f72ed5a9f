"""`HeldOutCheck`: the final sensor-noise model's held-out check and the record screens'
findings, as `SensorNoiseSelection.held_out` (`accel_jax.noise.select_sensor_noise`)."""

from __future__ import annotations

import dataclasses

from .._deprecated import LegacyItems


@dataclasses.dataclass(frozen=True)
class HeldOutCheck(LegacyItems):
    """The final model's held-out deviance test and what the screens found in its residual
    (`SensorNoiseSelection.held_out`).

    **Fields:**

    - `excess_deviance`: the held-out Whittle deviance (the last third of the record) in
        excess of its expectation under the final model.
    - `z`: that excess in standard errors; above `UNEXPLAINED_Z` the record is unexplained.
    - `bins`: the held-out periodogram bins it sums.
    - `removed`: the effects the backward check took out, `{"effect", "evidence"}` (their
        2 ln B then).
    - `exchanged`: the low-frequency effects the exchange replaced, `{"effect", "by",
        "evidence"}`; their steps then name the substitute, with `replaced` the effect
        whose evidence they show.
    - `ties`: each named low-frequency effect another fits as well, within the bar,
        `{"effect", "alternative", "evidence", "bar"}` (2 ln B of the effect over the
        alternative); with `"judged_by": "time_domain"`, an alternative of another
        low-frequency effect and a start-up transient, weighed in the time domain after
        the selection dropped a transient (`sensor_arbiter`; its 2 ln B may lie below
        −bar too: that likelihood then prefers what the spectral steps did not take).
    - `bursts`: impulsive events, `{"start_s", "end_s", "peak"}`.
    - `non_gaussian`: the residual's skewness and excess kurtosis and their z
        (`_non_gaussian`; `significant` makes the record unexplained).
    - `spectral_change`: the residual's spectrum compared between the record's halves, the
        band that changes most and its p (`_spectral_change`; `significant` makes the
        record unexplained).
    - `drift`: the level's linear drift, `{"slope_per_s", "t"}`.
    - `drifting`: whether that drift is one no named effect makes.
    - `level_shift_test`: the last level-shift test (`_level_shift`; None for a record too
        short to test).
    - `more_level_shifts`: True when one more shift stood than `MAX_LEVEL_SHIFTS` (absent
        from `to_dict` when False).
    - `step_or_walk`: the test of a step of the level in a named random walk's place
        (`_shift_in_place_of_walk`; None where no step stood against the model without
        the walk).
    - `step_or_walk_tested`: whether that test ran (it runs when a random walk is named
        and no shift was taken out); `to_dict` has `step_or_walk` only then.
    - `level_shifts`: the steps of the level found and taken out (time, size, their z,
        the held-out z and effects with the step still in).
    - `saturation`: the rails the record's values pile up on (`detect_saturation`).
    - `white_floor`: the fitted white σ against the σ the record's low band supports, the
        process that carries the band, and `collapsed` where the band is flat and the
        white σ lies far below it — a fit failure, flagged (`sensor_refine._white_floor`;
        None where the model has no stationary coloured process or a wandering level).
    - `low_pass_ties`: the other low-pass shapes that fit within the evidence bar of the
        named `bandlimit`'s, `{"shape", "order", "evidence"}` (and `"taps"` or `"ratio"`;
        `evidence` 2 ln B of the named over it): the record cannot tell them apart.

    `to_dict()` is the dict of the JSON's `held_out`; `held_out["z"]` and the other keys
    of the dict this replaced still work for one release, with a `DeprecationWarning`.
    """

    excess_deviance: float
    z: float
    bins: int
    removed: list[dict]
    exchanged: list[dict]
    ties: list[dict]
    bursts: list[dict]
    non_gaussian: dict
    spectral_change: dict
    drift: dict
    drifting: bool
    level_shift_test: dict | None = None
    more_level_shifts: bool = False
    step_or_walk: dict | None = None
    step_or_walk_tested: bool = False
    level_shifts: list[dict] = dataclasses.field(default_factory=list)
    saturation: list[dict] = dataclasses.field(default_factory=list)
    white_floor: dict | None = None
    low_pass_ties: list[dict] = dataclasses.field(default_factory=list)

    def to_dict(self) -> dict:
        """The JSON-ready dict: every field in its order, but `more_level_shifts` only when
        True and `step_or_walk` only when its test ran (`step_or_walk_tested` never)."""
        out = {
            "excess_deviance": self.excess_deviance,
            "z": self.z,
            "bins": self.bins,
            "removed": self.removed,
            "exchanged": self.exchanged,
            "ties": self.ties,
            "bursts": self.bursts,
            "non_gaussian": self.non_gaussian,
            "spectral_change": self.spectral_change,
            "drift": self.drift,
            "drifting": self.drifting,
            "level_shift_test": self.level_shift_test,
        }
        if self.more_level_shifts:
            out["more_level_shifts"] = True
        if self.step_or_walk_tested:
            out["step_or_walk"] = self.step_or_walk
        out["level_shifts"] = self.level_shifts
        out["saturation"] = self.saturation
        out["white_floor"] = self.white_floor
        out["low_pass_ties"] = self.low_pass_ties
        return out

    def _legacy(self) -> dict:
        return self.to_dict()
