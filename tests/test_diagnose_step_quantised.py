"""A step record whose output ADC is coarse against its noise: each plateau keeps a
quantisation bias of its own (`record.quantisation_bias`), which the nominal model's white
output noise does not describe. Its levels are then fitted as errors in variables, as a
measured input's are (`record.COARSE_BIAS`). The records come from the independent truth
simulator (studies/step_truth.py), drawn as the stop-contact harness draws its clean ones."""

import sys
from pathlib import Path

import jax
import numpy as np
import pytest

from accel_jax._data import NominalDevice
from accel_jax.diagnose import diagnose_many
from accel_jax.diagnose.step import record
from accel_jax.diagnose.step.effects import step_effects

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "studies"))
import contact_harness  # noqa: E402
import step_truth  # noqa: E402

NOMINAL = NominalDevice.reference(**contact_harness.NOMINAL_LAGS)


def _clean(index: int, **changes):
    """The stop-contact harness's clean record `none_<index>` (seed 2029), its world
    changed by `changes` (truth fields) before it is simulated."""
    truth, rng, _ = contact_harness.draw("none", 2029, index)
    t, u, y, _ = step_truth.make({**truth, **changes}, rng)
    from accel_jax import StepData

    return truth, StepData(t, u, y)


@pytest.fixture(autouse=True)
def _x64():
    with jax.enable_x64(True):
        yield


def test_levels_are_errors_in_variables_only_where_the_output_is_not_dithered():
    # Record 6: a 14-bit ADC (1.22 mV) over 0.21 mV of white noise (q = 5.9 σ).
    truth, data = _clean(6)
    assert truth["adc_step_V"] / truth["noise_V"] > 5
    rec = record.prepare(data, NOMINAL, step_effects())
    assert rec.ctx.level_sigma is not None
    changes = len(truth["change_times_s"])
    sigmas = np.asarray(rec.ctx.level_sigma)
    assert np.all(sigmas[:changes] > 0) and np.all(sigmas[changes:] == 0)
    assert np.ptp(sigmas[:changes]) == 0  # one bias for every plateau
    assert np.all(np.asarray(rec.ctx.drift_step) == 0)  # no input channel to drift
    assert sum("coarse against its noise" in note for note in rec.notes) == 1
    # The same world with noise that dithers the ADC (σ ≈ q), and a fine ADC (16 bits
    # against the same 0.21 mV): the levels stay exact.
    for changes_ in ({"noise_V": 1.2e-3}, {"adc_step_V": 20.0 / 2**18}):
        _, other = _clean(6, **changes_)
        plain = record.prepare(other, NOMINAL, step_effects())
        assert plain.ctx.level_sigma is None and not plain.notes, changes_


def test_only_a_measured_channels_delay_is_held_on_its_late_side():
    """`record.prepare`: a measured input's common delay has the prior σ
    `model.DELAY_LATE_SIGMA` on its late side and `DELAY_PRIOR_SIGMA` on the other; the
    changes' own shifts keep one σ, and an exact column has no late-side σ at all."""
    from accel_jax import StepData
    from accel_jax.diagnose.step.model import DELAY_LATE_SIGMA, DELAY_PRIOR_SIGMA, TIMING_PRIOR

    _, data = _clean(3)
    exact = record.prepare(data, NOMINAL, step_effects())
    assert exact.ctx.timing_map is None and exact.ctx.timing_sigma_late is None
    column, _ = step_truth.measure_input(
        np.asarray(data.u_test), 1.0 / float(data.t[1] - data.t[0]), np.random.default_rng(7)
    )
    rec = record.prepare(StepData(data.t, column, data.u_out), NOMINAL, step_effects())
    late, sigma = np.asarray(rec.ctx.timing_sigma_late), np.asarray(rec.ctx.timing_sigma)
    changes = rec.change_index.size
    assert late[-1] == DELAY_LATE_SIGMA and sigma[-1] == DELAY_PRIOR_SIGMA
    assert np.all(late[:changes] == TIMING_PRIOR[1]) and np.all(sigma[:changes] == TIMING_PRIOR[1])


@pytest.mark.slow
def test_a_clean_record_quantised_coarsely_is_none_not_coloured_noise():
    # Before the levels were errors in variables this record read `colored_noise`: the
    # nominal's held-out residual carried each plateau's quantisation bias (Ljung–Box
    # p = 4.8e-132), and the coloured output noise took it.
    _, data = _clean(6)
    result = diagnose_many([data], NOMINAL, recommend=False)[0]
    assert result.verdict == "none", result.summary()
    assert "and white" in result.reason, result.reason
    # The record says why its levels are nuisances (a clean input has no level errors).
    assert any("coarse against its noise" in note for note in result.notes), result.notes
