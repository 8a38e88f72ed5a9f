"""The step diagnosis's nuisances judged together: each fitted nuisance (the test
winding's gain, the change times about their mean, a clock's rate, a measured input's
levels and drift) in σ of its prior, a family-wise test over them, and what a strained
set of nuisances says about the record."""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import numpy as np

from ..._deprecated import LegacyItems
from ..._io import field_dict
from .model import DELAY_LIMIT, GAIN_SIGMA, n_timing, timing_terms
from .layout import W
from .state import StepFit, StepRecord


LATE_OUTPUT_SIGMA = 0.5
"""Scale [samples] of the output's lateness behind the test input's column, judged with the
nuisances (`nuisance_test`'s `input_delay`): a column shows a change up to one sample
after it happened (the fitted delay then lies in [0, 1] samples, centre 0.5), and a
measured input's channel only adds delay (its filters and converter come after the
drive). An output later than that is a lag the model lacks (a torquer lag, an output
filter) or a delay between the column and the drive: a free delay absorbs either (seen on
blind lag records, measured and clean: `none` with the fitted delay at −1.6 to −5
samples), so a record needing one is not `none`. Earlier outputs are not judged."""

COLUMN_PHASE = 1.0
"""How far [samples] an exact `u_test` column can show a change after it happened (the
sampling phase): the lag a record whose input channel adds no delay cannot tell from it."""

NUISANCE_ALPHA = 0.01
"""Family-wise level of the joint test of a fit's nuisances (`nuisance_test`): on records
whose nuisances are what their priors say, it trips in at most this share (Bonferroni over
the standardised shifts, each at most N(0, 1) under its prior: fitted shifts are shrunk)."""


NUISANCE_METHOD = (
    "Bonferroni over the standardised nuisance shifts (gain, the output's lateness behind the "
    "input, change times about their mean, measured input levels)"
)


@dataclasses.dataclass(frozen=True)
class NuisanceTest(LegacyItems):
    """A fit's nuisances judged together (`nuisance_test`).

    - `standardised`: each nuisance's shift in σ of its prior, by name (`test_winding_gain`,
        `input_delay`, `change_time_j` or `input_clock_rate`, a measured input's
        `input_level_j` or `input_level_group_j` and `input_channel_drift`);
    - `largest`, `largest_sigma`: the one furthest from its prior and its shift; `count`
        how many were judged;
    - `family_p_value`: Bonferroni's p of the largest; `alpha` the level
        (`NUISANCE_ALPHA`); `strained` whether p < alpha;
    - `input_delay_samples`: the mean change-time shift (positive when the output moves
        first); `known_input_delay_samples` the delay the record gives (None if not);
        `sample_period_s` [s] one sample;
    - `hidden_lag_samples`, `hidden_lag_s` [s]: the largest loop lag the fitted delay can
        take up (`hidden_lag_samples`).

    `to_dict()` is what the refit reports (`refit["nuisance_test"]`). It was a plain dict;
    `test["strained"]` still reads for one release, with a `DeprecationWarning`.
    """

    standardised: dict[str, float]
    largest: str
    largest_sigma: float
    count: int
    family_p_value: float
    alpha: float
    strained: bool
    input_delay_samples: float
    known_input_delay_samples: float | None
    sample_period_s: float
    hidden_lag_samples: float
    hidden_lag_s: float
    method: str = NUISANCE_METHOD

    def to_dict(self) -> dict:
        """The fields in order (`standardised` a copy): the dict `nuisance_test` returned."""
        return field_dict(self)

    def _legacy(self) -> dict:
        return self.to_dict()


def nuisance_test(fit: StepFit, rec: StepRecord) -> NuisanceTest:
    """Every fitted nuisance of `fit` with its shift in σ of its prior, judged together.

    Standardised: the test winding's gain (log-normal, `GAIN_SIGMA`); each change time
    about the record's mean change time (the mean is the delay between the input and
    output channels and the sampling phase, reported apart; N(0, 1) in samples); for a
    measured input, each level's error in its standard errors. Shown without a prior:
    the output offset (external moment) and the initial state, free in every model.
    The delay between the input's column and the output (the mean change-time shift,
    `input_delay_samples`, positive when the output moves first) is judged on its late
    side only, beyond a delay the record gives (`StepData.input_delay`, k samples):
    `input_delay` = min(0, delay − k − 0.5) / `LATE_OUTPUT_SIGMA`.
    The test: the largest |z| against Bonferroni over the K standardised shifts, p =
    min(1, K · 2Φ(−max|z|)); `strained` when p < `NUISANCE_ALPHA`.

    `hidden_lag_samples` (and `hidden_lag_s`): the largest lag of the loop (a torquer lag,
    an output filter, a delay in the drive) the fitted delay can take up, whatever the
    verdict. The output appears `input_delay_samples` = d − L ahead of the column, d the
    column's own delay behind the drive and L the loop's lag, so L = d − that, at most
    d_max − that: d_max = `COLUMN_PHASE` beyond the given delay where the column is exact
    or its delay given, beyond `DELAY_LIMIT` (the fit's bound on the channel's delay) for a
    measured input whose delay is not given. A `none` rules out no lag below it; it is not
    an upper bound on what the record hides (a lag the device parameters or the initial
    state take up is not counted), and it is the fitted delay's value, without its error."""
    from scipy import stats

    w = np.asarray(fit.w)
    ctx = rec.ctx
    n_changes = int(rec.change_index.size)
    n_t = n_timing(ctx)
    timing = change_shifts(w, ctx)[:n_changes]
    delay = float(np.mean(timing)) if n_changes else 0.0
    known = rec.input_delay_known or 0.0  # (samples; the output's lateness is beyond it)
    shifts = [("test_winding_gain", float(fit.z_gain))]
    if n_changes:
        shifts.append(("input_delay", min(0.0, -delay - known - 0.5) / LATE_OUTPUT_SIGMA))
    if rec.clock is not None:  # the clock's rate (its shift is the delay)
        shifts.append(("input_clock_rate", float(w[W.timing(n_t)][1])))
    elif n_changes > 1:
        shifts += [(f"change_time_{j + 1}", float(x - delay)) for j, x in enumerate(timing)]
    if ctx.level_sigma is not None:
        if rec.level_groups is not None:
            count = rec.level_groups.means.size
            levels = w[W.levels(n_t)][:count]
            shifts += [(f"input_level_group_{g + 1}", float(e)) for g, e in enumerate(levels)]
        else:
            levels = w[W.levels(n_t)][:n_changes]
            shifts += [(f"input_level_{j + 2}", float(e)) for j, e in enumerate(levels)]
        shifts.append(("input_channel_drift", float(w[W.DRIFT])))
    hidden = hidden_lag_samples(-delay, measured=rec.input_measured, known=rec.input_delay_known)
    z = np.abs(np.asarray([v for _, v in shifts]))
    worst = int(np.argmax(z))
    p_value = min(1.0, len(shifts) * 2 * float(stats.norm.sf(z[worst])))
    return NuisanceTest(
        standardised={name: value for name, value in shifts},
        largest=shifts[worst][0],
        largest_sigma=shifts[worst][1],
        count=len(shifts),
        family_p_value=p_value,
        alpha=NUISANCE_ALPHA,
        strained=bool(p_value < NUISANCE_ALPHA),
        input_delay_samples=-delay,
        known_input_delay_samples=rec.input_delay_known,
        sample_period_s=float(rec.dt_sample),
        hidden_lag_samples=hidden,
        hidden_lag_s=hidden * float(rec.dt_sample),
    )


def hidden_lag_samples(
    input_delay_samples: float, *, measured: bool, known: float | None = None
) -> float:
    """The largest loop lag [samples] a fitted delay (`input_delay_samples`, positive when
    the output moves first) can take up (`nuisance_test`'s `hidden_lag_samples`): the
    column's largest own delay — `COLUMN_PHASE` beyond `known` (or zero), or beyond
    `DELAY_LIMIT` for a `measured` input whose delay is not given — less that lead."""
    channel = (known or 0.0) + COLUMN_PHASE
    if measured and known is None:
        channel = DELAY_LIMIT + COLUMN_PHASE
    return max(0.0, channel - input_delay_samples)


def change_shifts(w, ctx) -> np.ndarray:
    """Each change's fitted shift [samples] from where `u_test` shows it, as the fit uses
    it (`fit.timing_terms`), from a fit's parameters w."""
    timing = jnp.asarray(np.asarray(w)[W.timing(n_timing(ctx))])
    return np.asarray(timing_terms(timing, ctx)[0])


def strained_sentence(test: NuisanceTest, fit) -> str:
    """What a failed joint nuisance test says, with the effects that make such a record."""
    name, value = test.largest, test.largest_sigma
    where = f"(family-wise p = {test.family_p_value:.2g} over {test.count} nuisances)"
    if name == "test_winding_gain":
        gain = math.exp(GAIN_SIGMA * value)
        return (
            f"the test winding's gain came out {gain:.3g} of nominal ({value:+.1f}σ) {where}: "
            "a winding fault, or a device resting on a stop when the record starts (the "
            "first change then moves the output less than the gain says: stop contact), or "
            "a different device"
        )
    if name == "input_delay":
        late = -test.input_delay_samples + (test.known_input_delay_samples or 0.0)
        micro = late * test.sample_period_s * 1e6
        return (
            f"the output follows the test input's changes {late:.1f} samples ({micro:.3g} µs) "
            f"later than its column shows ({value:+.1f}σ of the sampling phase) {where}: a "
            "lag the model lacks (a torquer lag or an output filter, which a free delay "
            "absorbs) or a delay between the column and the drive (a driver or converter "
            "delay, the test winding's L/R, a slower output channel); the record cannot tell "
            "them apart"
        )
    if name.startswith("change_time"):
        return (
            f"change {name.rsplit('_', 1)[1]} of the test input came {value:+.1f} samples off "
            f"the others' timing {where}: the input switched at another time than its column "
            "shows (a relay's delay or bounce), or a lag the model lacks"
        )
    if name == "input_clock_rate":
        return (
            f"the test sequence's clock rate came out {value:+.1f}σ off the grid read from its "
            f"changes {where}: the generator's clock and the recorder's differ in rate, or a "
            "lag the model lacks"
        )
    if name == "input_channel_drift":
        return (
            f"the input channel's drift came out {value:+.1f}σ of what its plateaus allow "
            f"{where}: the test input's level moved during the record, or a slow drift "
            "of the output the model lacks (disturbance drift)"
        )
    if name.startswith("input_level_group"):
        return (
            f"level {name.rsplit('_', 1)[1]} of the clocked test sequence differs from what "
            f"its channel recorded by {value:+.1f} standard errors {where}: a gain or offset "
            "error of the input channel, or an output that is not linear in the input"
        )
    return (
        f"level {name.rsplit('_', 1)[1]} of the test input differs from what its channel "
        f"recorded by {value:+.1f}σ (its standard error and the output ADC's plateau bias, "
        f"`quantisation_bias`) {where}: a gain or offset error of the "
        "input channel, or an output that is not linear in the input at that level"
    )
