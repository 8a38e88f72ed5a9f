"""The predictability test's null from a noise candidate's own fitted noise
(`accel_jax.diagnose.step.noise_null`): its realisations have the fitted model's variance
and correlation (checked against `block_noise`'s closed form and against the moment
model's stationary variance), and a deterministic misfit (a sinusoid far above the noise,
a step-locked template) stays deterministic while a realisation of the noise itself does
not."""

from types import SimpleNamespace

import jax.numpy as jnp
import numpy as np
import pytest

import accel_jax as aj
from accel_jax._servo import time_constant
from accel_jax.diagnose import openworld
from accel_jax.diagnose.step.effects import ColoredNoise, MomentNoise, block_noise
from accel_jax.diagnose.step.innovations import moment_noise_model
from accel_jax.diagnose.step.noise_null import (
    CalibratedPredictability,
    calibrated,
    noise_draws,
)

BASE = aj.NominalDevice.reference(torquer_time_constant=0.0, filter_time_constant=0.0).params
M = 4
N = 600
DT = float(time_constant(BASE)) / 20
WHITE = 1e-3


def _record():
    held = np.zeros(N, bool)
    for start in range(200, N, 300):
        held[start : start + 100] = True
    return SimpleNamespace(
        n=N, block=M, dt_sample=DT, dt=DT * M, prior_sigma=np.full(4, 0.05), held=held,
        change_block=np.arange(100, N, 100), change_step=np.tile([1.0, -1.0], 3)[:5],
    )


def _fit(model, z):
    w = np.zeros(16)
    w[8:10] = z
    return SimpleNamespace(
        w=w, z=np.zeros(4), model=model, effect=model.name,
        params={"sigma_white_per_sample_V": WHITE},
    )


def test_output_noise_draws_have_the_block_means_autocovariance():
    ratio, phi_block = 16.0, 0.9
    fit = _fit(ColoredNoise(), [4.0, np.arctanh(phi_block)])
    draws = noise_draws(fit, _record(), BASE, 400)
    phi, theta, first, variance = (float(v) for v in block_noise(ratio, phi_block, M, M))
    gamma0 = first * variance * WHITE**2
    assert np.var(draws) == pytest.approx(gamma0, rel=0.08)
    lag1 = np.mean(draws[:, 1:] * draws[:, :-1])
    gamma1 = (1 - phi * theta) * (phi - theta) / (1 - phi**2) * variance * WHITE**2
    assert lag1 == pytest.approx(gamma1, rel=0.1)


def test_moment_noise_draws_have_the_stationary_variance():
    ratio, phi_block = 25.0, 0.8
    fit = _fit(MomentNoise(), [5.0, np.arctanh(phi_block)])
    draws = noise_draws(fit, _record(), BASE, 300)
    *_, block, _ = moment_noise_model(BASE, DT, M, M, ratio, phi_block)
    expected = (float(block) + 1 / M) * WHITE**2
    # Stationary from the first block (the start is drawn from P), not only at the end.
    assert np.var(draws[:, :20]) == pytest.approx(expected, rel=0.12)
    assert np.var(draws) == pytest.approx(expected, rel=0.08)


def test_a_sinusoid_stays_deterministic_and_the_noise_itself_does_not():
    rec = _record()
    fit = _fit(ColoredNoise(), [3.0, np.arctanh(0.95)])
    window = 20
    noise = noise_draws(fit, rec, BASE, 1, seed=7)[0]
    t = np.arange(N)
    line = 20 * WHITE * np.sin(2 * np.pi * t / 37.0)
    judged = []
    for residual in (line + noise, noise):
        plain = openworld.predictability(
            residual, rec.held, rec.dt, rec.change_block, rec.change_step, window
        )
        judged.append((plain, calibrated(plain, fit, rec, BASE, window, count=60)))
    (line_plain, line_null), (_, noise_null) = judged
    assert line_plain.deterministic and line_null.deterministic
    assert line_null.periodic > line_null.null_quantile["periodic"]
    assert not noise_null.deterministic
    # The calibrated test can only call a misfit deterministic less often.
    assert set(noise_null.null_quantile) == {"input_locked", "periodic", "trend"}
    # Typed (`CalibratedPredictability`, an `openworld.Predictability`); `to_dict()` is the
    # dict `calibrated` returned: the predictability's keys, then the null's.
    assert isinstance(noise_null, CalibratedPredictability)
    assert list(noise_null.to_dict()) == [
        *line_plain.to_dict(), "null_quantile", "null_draws", "null_model"
    ]
    assert noise_null.null_draws == 60 and noise_null.null_model == "colored_noise"
    with pytest.warns(DeprecationWarning, match="use result.null_quantile"):
        assert noise_null["null_quantile"] == noise_null.null_quantile
