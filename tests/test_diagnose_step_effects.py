"""The step effects' physical values from their fitted parameters
(`accel_jax.diagnose.step.effects`, `AbstractStepEffect.physical`), on a record's scales
made by hand."""

import numpy as np
import pytest

from accel_jax.diagnose.step.effects import DisturbanceDrift
from accel_jax.diagnose.step.state import RecordHost


def _host(**changes):
    fields = dict(
        lag_unit=1e-6, gain=1e3, mid=0.0, half=1.0, scale=0.1, dt=1e-6, duration=0.012,
        torquer_gain=2e-3, accel_per_g=0.5, timing_late=np.zeros(3),
        nominal_torquer_time_constant=1e-5, nominal_filter_time_constant=1e-5, top=1.0,
        bottom=-1.0, block_samples=1, k_test=0.9964,
    )
    return RecordHost(**{**fields, **changes})


@pytest.mark.parametrize("test_gain", [0.9964 * 1.02, -0.9964 * 0.98])
def test_a_drift_s_output_is_its_moment_through_the_loop_not_the_test_winding(test_gain):
    # The drift of M/k_dm over the record, 1e-2 z V, reaches the output as k_test times it
    # (the settled output of an external moment), whatever the test winding's fitted gain
    # and polarity (which act on the test input only).
    context = _host().candidate(innovation_variance=1e-8, test_gain=test_gain)
    values = DisturbanceDrift().physical(np.array([3.0]), context)
    change = 3e-2  # V of M/k_dm over the record
    assert values["moment_rate_Nm_per_s"] == pytest.approx(change * 2e-3 / 0.012)
    assert values["output_drift_V_per_s"] == pytest.approx(change * 0.9964 / 0.012)
