"""The step diagnosis's output-noise model (`accel_jax.diagnose.step.effects.block_noise`,
`innovations.innovation_terms`): white + Gauss–Markov noise sampled at the record's rate
and averaged over blocks of m samples, as an ARMA(1,1) on the block means. Checked against
the block means' autocovariance summed sample by sample (no formula of the module's)."""

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.signal import lfilter

from accel_jax.diagnose.step.effects import block_noise
from accel_jax.diagnose.step.innovations import innovation_terms


def _brute_autocovariance(ratio, r, m, lags):
    """γ_k of the block means of white (variance 1) + AR(1) (variance `ratio`, coefficient
    r per sample), by summing the samples' covariances over every pair in two blocks."""
    i = np.arange(m)
    out = []
    for k in range(lags):
        d = np.abs(k * m + i[None, :] - i[:, None])
        cov = ratio * r**d + (d == 0)
        out.append(cov.sum() / m**2)
    return np.array(out)


def _arma_autocovariance(phi, theta, variance, lags):
    g0 = variance * (1 + theta**2 - 2 * phi * theta) / (1 - phi**2)
    g1 = variance * (1 - phi * theta) * (phi - theta) / (1 - phi**2)
    return np.array([g0] + [g1 * phi ** (k - 1) for k in range(1, lags)])


@pytest.mark.parametrize(
    "ratio, tau_samples, m",
    [(100.0, 380.0, 10), (4.0, 3.0, 5), (0.25, 40.0, 16), (9.0, 40.0, 1), (400.0, 2.0, 7)],
)
def test_block_noise_is_the_block_means_autocovariance(ratio, tau_samples, m):
    r = np.exp(-1 / tau_samples)
    phi, theta, first, variance = (float(v) for v in block_noise(ratio, r**m, m, 16))
    assert phi == pytest.approx(r**m, rel=1e-12)
    assert abs(theta) < 1
    exact = _brute_autocovariance(ratio, r, m, 6)
    np.testing.assert_allclose(_arma_autocovariance(phi, theta, variance, 6), exact, rtol=1e-9)
    assert first * variance == pytest.approx(exact[0], rel=1e-12)  # V₀ σ_a² = γ₀


def test_the_averaging_gives_the_moving_average_part_the_other_sign():
    # Per sample, white + AR(1) has θ ≥ 0 (m = 1); averaged over blocks, a dominant
    # correlated part gives θ < 0, which white + AR(1) on the block means cannot take.
    r = np.exp(-1 / 380)
    assert float(block_noise(100.0, r, 1, 16)[1]) > 0
    assert float(block_noise(100.0, r**10, 10, 16)[1]) < 0


def test_white_noise_is_the_zero_model():
    phi, theta, first, variance = (float(v) for v in block_noise(0.0, 0.0, 10, 16))
    assert phi == 0 and theta == 0
    assert first == pytest.approx(1.0) and variance == pytest.approx(0.1)


def test_innovations_are_white_with_the_exact_model():
    # A long simulated record: the one-step errors with the true parameters have unit
    # variance (σ_a² as predicted) and no lag-1..5 correlation beyond 4 standard errors.
    rng = np.random.default_rng(3)
    ratio, r, m, nb = 100.0, np.exp(-1 / 380), 10, 40_000
    n = nb * m
    w = rng.normal(size=n) * np.sqrt(ratio * (1 - r**2))
    w[0] = rng.normal() * np.sqrt(ratio)
    x = rng.normal(size=n) + lfilter([1.0], [1.0, -r], w)
    y = x.reshape(nb, m).mean(1)
    phi, theta, first, variance = block_noise(ratio, r**m, m, 16)
    a, _ = innovation_terms(jnp.asarray(y), phi, theta, jnp.log(first))
    a = np.asarray(a) / np.sqrt(float(variance))
    assert np.mean(a[100:] ** 2) == pytest.approx(1.0, abs=4 * np.sqrt(2 / nb))
    for k in range(1, 6):
        rho = np.mean(a[100 + k :] * a[100:-k])
        assert abs(rho) < 4 / np.sqrt(nb), k


def test_a_training_mask_makes_the_held_out_blocks_gaps():
    """`innovation_terms` with a training mask: each training segment's one-step errors
    from its own start (a NumPy loop per segment: e/√V₀ first, then the ARMA(1,1)
    recursion), ln V₀ once per segment, 0 on the held-out blocks, whose errors change
    nothing; all-training is the plain recursion exactly."""
    rng = np.random.default_rng(11)
    phi, theta, first, _ = (float(v) for v in block_noise(30.0, 0.9, 10, 16))
    n = 300
    y = rng.standard_normal(n)
    train = np.ones(n)
    train[:7] = 0
    train[60:100] = 0
    train[101:130] = 0  # a one-block training segment between two gaps
    a, log_v = innovation_terms(jnp.asarray(y), phi, theta, np.log(first), jnp.asarray(train))
    expected = np.zeros(n)
    segments = 0
    for k in range(n):
        if not train[k]:
            continue
        if k == 0 or not train[k - 1]:
            expected[k] = y[k] / np.sqrt(first)
            segments += 1
        else:
            expected[k] = y[k] - phi * y[k - 1] + theta * expected[k - 1]
    np.testing.assert_allclose(np.asarray(a), expected, rtol=1e-10, atol=1e-12)
    assert segments == 3
    assert float(log_v) == pytest.approx(segments * np.log(first), rel=1e-12)
    other = y.copy()
    other[train == 0] = 1e4
    again, _ = innovation_terms(jnp.asarray(other), phi, theta, np.log(first), jnp.asarray(train))
    np.testing.assert_array_equal(np.asarray(again), np.asarray(a))
    plain, plain_v = innovation_terms(jnp.asarray(y), phi, theta, np.log(first))
    whole, whole_v = innovation_terms(
        jnp.asarray(y), phi, theta, np.log(first), jnp.ones(n)
    )
    np.testing.assert_array_equal(np.asarray(whole), np.asarray(plain))
    assert float(whole_v) == float(plain_v)


def test_the_stop_programs_white_shortcut_is_the_recursion_at_zero():
    # `fit._fit_record` skips the filter for the stops' programs (no noise model among
    # their candidates): ã = the training errors, 0 on the gaps, and ln V = 0. That is
    # what the recursion gives at the default effect's noise (φ = θ = ln V₀ = 0), bit for
    # bit, with and without a training mask.
    rng = np.random.default_rng(5)
    error = jnp.asarray(rng.normal(size=64))
    train = jnp.asarray((np.arange(64) // 8) % 3 != 1, dtype=jnp.float64)
    zero = jnp.zeros(())
    for mask in (train, jnp.ones(64)):
        a, log_v = innovation_terms(error, zero, zero, zero, mask)
        assert bool(jnp.all(a == jnp.where(mask > 0, error, 0.0))) and float(log_v) == 0.0
