"""The time-domain arbiter between a wandering level and a returning bias with a start-up
transient (`accel_jax._noise.sensor_arbiter`): its likelihood against the dense Gaussian
one, and the tie it reports where the selection dropped a warm-up beside a slow bias."""

import dataclasses
import math
import sys
from pathlib import Path

import jax
import numpy as np
import pytest
from scipy import linalg

import accel_jax as aj
from accel_jax._noise import sensor_arbiter, spectral
from accel_jax._noise.sensor_model import (
    _differenced_autocovariance,
    _Model,
    _transient_grid,
    _transient_templates,
)

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "studies"))
import noise_truth  # noqa: E402


@pytest.fixture(autouse=True)
def _x64():
    with jax.enable_x64(True):
        yield


def _model(names, **values):
    z = np.zeros(spectral.N_PARAMS)
    z[0] = math.log(values.get("white", 1.0) ** 2)
    if "gauss_markov" in names:
        sigma, tau_over_dt = values["gauss_markov"]
        z[1], z[2] = math.log(sigma**2), math.log(tau_over_dt)
    if "random_walk" in names:
        z[6] = math.log(values["random_walk"])
    return _Model(tuple(names), (), None, z, 0.0, 0.0, np.zeros(0), True)


@pytest.mark.parametrize("names", [("gauss_markov",), ("random_walk",)])
def test_the_arbiters_likelihood_is_the_dense_gaussian_one(names):
    """2 ln L of the differenced block means, the level's drift profiled (the
    Durbin–Levinson recursion), and with a transient's best 2 ln Λ added, equal the same
    quantities from the dense covariance (a Cholesky factor of the Toeplitz matrix)."""
    rng = np.random.default_rng(3)
    dt, n = 0.01, 12_000
    model = _model(names, white=1.0, gauss_markov=(0.8, 300.0), random_walk=2e-3)
    r = np.cumsum(rng.normal(size=n)) * 0.05 + rng.normal(size=n)
    r += 3 * np.exp(-np.arange(n) / 900)
    y, m = sensor_arbiter._block_differences(r)
    assert m == math.ceil(n / (sensor_arbiter.ARBITER_BLOCKS + 1)) and y.size <= 512
    templates = _transient_templates(y.size, m, dt, _transient_grid(n, dt, m))
    floor = 1e-9

    gamma = _differenced_autocovariance(model, floor, y.size, m)
    factor = linalg.cho_factor(linalg.toeplitz(gamma))
    columns = np.column_stack([y, np.ones(y.size), templates])
    gram = columns.T @ linalg.cho_solve(factor, columns)
    logdet = 2 * np.sum(np.log(np.diag(factor[0])))
    plain = -(gram[0, 0] - gram[0, 1] ** 2 / gram[1, 1] + logdet)
    cross = gram[2:, 0] - gram[2:, 1] * gram[1, 0] / gram[1, 1]
    energy = np.diag(gram)[2:] - gram[2:, 1] ** 2 / gram[1, 1]

    got = sensor_arbiter._two_log_likelihood(y, m, model, floor, None)
    assert got == pytest.approx(plain, rel=1e-9, abs=1e-6)
    with_transient = sensor_arbiter._two_log_likelihood(y, m, model, floor, templates)
    best = plain + np.max(cross**2 / energy)
    assert with_transient == pytest.approx(best, rel=1e-9, abs=1e-6)


def test_a_dropped_warm_up_beside_a_slow_bias_is_offered_as_the_walks_tie():
    """White noise (500 µg), a Gauss–Markov bias (150 µg, 10 s) and a 2 mg warm-up of τ
    20 s, 200 s at 200 Hz: too small a warm-up for the selection to keep beside the walk it
    names (the walk absorbs it); the arbiter offers "gauss_markov+startup_transient" as the
    walk's tie, weighed in the time domain, and the text says so. On three such records
    2 ln B of the walk over it was 4.3, −1.5 and −4.4; without the arbiter none of the
    three said anything of a warm-up or, on two, of a Gauss–Markov process."""
    from accel_jax.report.text.noise import _selection_lines

    n, dt = 40_000, 0.005
    truth = {"white": 5e-4, "gauss_markov": (1.5e-4, 10.0), "transient": (2e-3, 20.0)}
    truth["level"] = 1.0
    found = aj.noise.select_sensor_noise(
        noise_truth.record(np.random.default_rng(60), n, dt, truth), dt
    )
    weighed = [t for t in found.held_out.ties if t.get("judged_by") == "time_domain"]
    assert set(found.effects) == {"random_walk"}, found.effects
    assert [(t["effect"], t["alternative"]) for t in weighed] == [
        ("random_walk", "gauss_markov+startup_transient")
    ]
    assert weighed[0]["evidence"] < weighed[0]["bar"]
    lines = _selection_lines(found)
    said = ("weighed in the time domain", "prefers the second")
    assert any(any(s in line for s in said) for line in lines)
    # an alternative better by more than the bar is said to be preferred, not a tie
    held = dataclasses.replace(
        found.held_out, ties=[{**weighed[0], "evidence": -15.0}]
    )
    text = _selection_lines(dataclasses.replace(found, held_out=held))
    assert any("time-domain likelihood prefers the second" in line for line in text)


def test_a_warm_up_on_white_noise_needs_no_arbiter():
    """A warm-up the selection keeps (1 mg, τ 20 s, on 500 µg of white noise) is named
    alone, with no tie weighed in the time domain (the arbiter runs only where the backward
    check dropped a transient)."""
    n, dt = 40_000, 0.005
    truth = {"white": 5e-4, "transient": (1e-3, 20.0), "level": 1.0}
    found = aj.noise.select_sensor_noise(
        noise_truth.record(np.random.default_rng(80), n, dt, truth), dt
    )
    assert found.effects == ("startup_transient",)
    assert not any(t.get("judged_by") for t in found.held_out.ties)
