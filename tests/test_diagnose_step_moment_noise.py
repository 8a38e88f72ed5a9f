"""The step diagnosis's model of a Gauss–Markov moment inside the loop
(`accel_jax.diagnose.step.innovations.moment_noise_model`, `moment_kalman`,
`moment_noise_terms`; the effect `moment_noise`): its Kalman filter over the block means
against the exact Gaussian likelihood of the block means written from a dense covariance
matrix (SciPy's matrix exponential and Lyapunov solver, the samples' autocovariance summed
pair by pair: none of the module's recursions)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg as sl

import accel_jax as aj
from accel_jax._servo import time_constant
from accel_jax._simulate.sequence import loop_system
from accel_jax.diagnose.step.effects import MomentNoise
from accel_jax.diagnose.step.innovations import (
    moment_kalman,
    moment_noise_model,
    moment_noise_terms,
)

LAGS = [(0.0, 0.0), (2e-4, 1e-4)]


def _params(lags):
    return aj.NominalDevice.reference(
        torquer_time_constant=lags[0], filter_time_constant=lags[1]
    ).params


def _dense_covariance(params, dt, m, n, ratio, phi_block):
    """The covariance of n block means: the loop's states and the moment (SciPy expm and
    continuous Lyapunov), each sample pair's covariance C Φ^|i−j| P Cᵀ summed into blocks,
    plus the white part's 1/m."""
    a6, _, c6 = (np.asarray(x) for x in loop_system(params, 1.0))
    a, c = a6[:5, :5].copy(), c6[:5]
    period = float(time_constant(params))
    for i in range(4):
        if np.all(a[i] == 0):  # an ideal lag's dummy state: undriven and unread
            a[i, i] = -1 / period
    beta = -np.log(phi_block) / (m * dt)
    a[4, 4] = -beta
    static = -c[:4] @ np.linalg.solve(a[:4, :4], a[:4, 4])
    q = np.zeros((5, 5))
    q[4, 4] = 2 * beta * ratio / static**2
    p = sl.solve_continuous_lyapunov(a, -q)
    phi = sl.expm(a * dt)
    count = n * m
    gamma = np.empty(count)
    power = np.eye(5)
    for d in range(count):
        gamma[d] = c @ power @ p @ c
        power = phi @ power
    i = np.arange(count)
    samples = gamma[np.abs(i[:, None] - i[None, :])]
    average = np.kron(np.eye(n), np.ones((1, m)) / m)
    return average @ samples @ average.T + np.eye(n) / m, gamma[0]


@pytest.mark.parametrize("lags", LAGS)
@pytest.mark.parametrize("m", [1, 4])
@pytest.mark.parametrize("ratio, phi_block", [(9.0, 0.9), (100.0, 0.3), (0.5, 0.99)])
def test_kalman_likelihood_is_the_dense_gaussian_likelihood(lags, m, ratio, phi_block):
    params = _params(lags)
    dt = float(time_constant(params)) / 20
    n = 50
    cov, _ = _dense_covariance(params, dt, m, n, ratio, phi_block)
    e = np.random.default_rng(m).standard_normal(n) * np.sqrt(np.diag(cov))
    chol = np.linalg.cholesky(cov)
    z = np.linalg.solve(chol, e)
    exact = -0.5 * z @ z - np.sum(np.log(np.diag(chol)))
    a, s = (np.asarray(v) for v in moment_kalman(jnp.asarray(e), params, dt, m, 8, ratio, phi_block))
    kalman = -0.5 * np.sum(a**2 / s) - 0.5 * np.sum(np.log(s))
    assert kalman == pytest.approx(exact, abs=1e-9 * abs(exact))
    # The stationary variances the effect reports: a block mean's (less the white part's)
    # and one sample's.
    *_, block, sample = moment_noise_model(params, dt, m, 8, ratio, phi_block)
    assert float(block) == pytest.approx(cov[0, 0] - 1 / m, rel=1e-9)
    assert float(sample) == pytest.approx(_dense_covariance(params, dt, m, 1, ratio, phi_block)[1], rel=1e-9)


def test_the_profiled_likelihood_is_the_filter_s():
    """−½[n ln(Σã²/n) + ln V] of `moment_noise_terms` is the Kalman likelihood with the
    scale profiled out, whatever the normalising S_∞."""
    params = _params(LAGS[1])
    dt, m = float(time_constant(params)) / 20, 4
    e = jnp.asarray(np.random.default_rng(3).standard_normal(40))
    a, s = (np.asarray(v) for v in moment_kalman(e, params, dt, m, 8, 25.0, 0.8))
    scaled, log_v = moment_noise_terms(e, params, dt, m, 8, 25.0, 0.8, jnp.ones(40))
    n = 40
    scale = np.mean(a**2 / s)  # the profiled σ²
    direct = -0.5 * (n * np.log(scale) + np.sum(np.log(s)) + n)
    profiled = -0.5 * (n * np.log(np.mean(np.asarray(scaled) ** 2)) + float(log_v) + n)
    assert profiled == pytest.approx(direct, abs=1e-10)


def test_held_out_blocks_are_gaps_in_the_training_likelihood():
    """With `observed` (the training mask), the held-out blocks are gaps: the profiled
    likelihood of `moment_noise_terms` is the dense Gaussian likelihood of the training
    blocks alone (their sub-matrix of the exact covariance), and the held-out errors,
    whatever they are, change nothing."""
    params = _params(LAGS[1])
    dt, m, n, ratio, phi_block = float(time_constant(params)) / 20, 4, 40, 25.0, 0.8
    cov, _ = _dense_covariance(params, dt, m, n, ratio, phi_block)
    train = np.ones(n)
    train[10:16] = train[27:31] = 0
    seen = train > 0
    e = np.random.default_rng(5).standard_normal(n) * np.sqrt(np.diag(cov))
    scaled, log_v = moment_noise_terms(
        jnp.asarray(e), params, dt, m, 8, ratio, phi_block, jnp.asarray(train), jnp.asarray(train)
    )
    scaled = np.asarray(scaled)
    k = int(seen.sum())
    profiled = -0.5 * (k * np.log(np.sum(scaled**2) / k) + float(log_v) + k)
    # The dense likelihood of the training blocks with the scale profiled out.
    sub = cov[np.ix_(seen, seen)]
    chol = np.linalg.cholesky(sub)
    z = np.linalg.solve(chol, e[seen])
    scale = z @ z / k
    exact = -0.5 * (k * np.log(scale) + 2 * np.sum(np.log(np.diag(chol))) + k)
    assert profiled == pytest.approx(exact, abs=1e-9 * abs(exact))
    assert np.all(scaled[~seen] == 0)
    other = e.copy()
    other[~seen] = 1e3 * np.random.default_rng(6).standard_normal(int((~seen).sum()))
    again, log_again = moment_noise_terms(
        jnp.asarray(other), params, dt, m, 8, ratio, phi_block, jnp.asarray(train),
        jnp.asarray(train),
    )
    np.testing.assert_array_equal(np.asarray(again), scaled)
    assert float(log_again) == float(log_v)


def test_no_moment_is_white_noise_exactly():
    params = _params(LAGS[0])
    e = jnp.asarray(np.random.default_rng(4).standard_normal(30))
    scaled, log_v = moment_noise_terms(e, params, 1e-5, 5, 8, 0.0, 0.7, jnp.ones(30))
    np.testing.assert_allclose(np.asarray(scaled), np.asarray(e), rtol=1e-12)
    assert float(log_v) == pytest.approx(0.0, abs=1e-12)


def test_forward_derivatives_match_finite_differences():
    """The fit differentiates the filter forward (`jax.jacfwd`) through the loop's device,
    the moment's size and its coefficient."""
    params = _params(LAGS[1])
    dt, m = float(time_constant(params)) / 20, 4
    e = jnp.asarray(np.random.default_rng(5).standard_normal(30))

    def loss(x):
        p = aj.ServoParams(**{**params.__dict__, "moment_of_inertia": params.moment_of_inertia * jnp.exp(x[2])})
        scaled, log_v = moment_noise_terms(e, p, dt, m, 8, x[0], x[1], jnp.ones(30))
        return jnp.sum(scaled**2) + log_v

    x = jnp.array([16.0, 0.85, 0.02])
    grad = np.asarray(jax.jacfwd(loss)(x))
    for k, h in enumerate((1e-4, 1e-6, 1e-6)):
        step = jnp.zeros(3).at[k].set(h)
        fd = (float(loss(x + step)) - float(loss(x - step))) / (2 * h)
        assert grad[k] == pytest.approx(fd, rel=1e-5, abs=1e-8)


def test_the_effect_is_the_nominal_model_at_zero():
    effect = MomentNoise()
    ratio, phi = effect.moment_noise(jnp.zeros(2), None)
    assert float(ratio) == 0.0 and float(phi) == 0.0
    ratio, phi = effect.moment_noise(jnp.array([-2.0, 1.0]), None)
    assert float(ratio) == 0.0  # a negative size is none


def _one_pass(error, params, dt, m, ratio, phi_block, observed):
    """`moment_kalman` as one pass of the package's `kalman_filter` over the errors (what
    it computed before its covariances and its means were split into two passes)."""
    from accel_jax._kalman import LinearGaussianModel, kalman_filter

    power, total, p0, _, _ = moment_noise_model(params, dt, m, 8, ratio, phi_block)
    lead = power[:, :5]
    model = LinearGaussianModel(
        transition=jnp.zeros((6, 6)).at[:, :5].set(lead),
        process_covariance=total,
        observation=jnp.zeros((1, 6)).at[0, 5].set(1.0),
        observation_covariance=jnp.reshape(1.0 / m, (1, 1)),
    )
    prior = lead @ p0 @ lead.T + total
    seen = None if observed is None else observed > 0
    out = kalman_filter(model, error, jnp.zeros(6), prior, observed=seen)
    return out.innovations[:, 0], out.innovation_covariances[:, 0, 0]


def test_two_passes_are_the_one_pass_filter_with_its_derivatives():
    """`moment_kalman` runs the filter's covariances and its means as two passes and gives
    the covariance pass a derivative of its own (taken only in the model's parameters that
    move): the same innovations and variances to the bit as the one-pass filter, with gaps
    or none, and the same forward Jacobian and gradient in parameters of every kind — the
    device's, the moment's, the errors' (which the covariances do not see) — to round-off."""
    import equinox as eqx

    params = _params(LAGS[1])
    dt, m, n = float(time_constant(params)) / 20, 4, 30
    rng = np.random.default_rng(5)
    e0 = jnp.asarray(rng.standard_normal(n))
    gaps = jnp.asarray(rng.uniform(size=n) > 0.25, float)

    def args(w, observed=gaps):
        device = eqx.tree_at(
            lambda p: p.moment_of_inertia, params, params.moment_of_inertia * jnp.exp(w[0])
        )
        error = e0 * (1 + w[2]) + w[3] * jnp.linspace(0, 1, n)
        return error, device, dt, m, 25.0 * jnp.exp(w[1]), 0.8 + 0.1 * w[4], observed

    def split(w, observed=gaps):
        error, device, dt_, m_, ratio, phi, seen = args(w, observed)
        return moment_kalman(error, device, dt_, m_, 8, ratio, phi, seen)

    def whole(w, observed=gaps):
        return _one_pass(*args(w, observed))

    w = jnp.array([0.2, -0.3, 0.05, 0.4, 0.1, 0.0, 0.0])  # the last two move nothing
    for observed in (None, gaps):
        for mine, theirs in zip(split(w, observed), whole(w, observed), strict=True):
            assert float(jnp.max(jnp.abs(mine - theirs))) <= 1e-13 * float(
                jnp.max(jnp.abs(theirs))
            )

    def both(w):
        return jax.jacfwd(split)(w), jax.jacfwd(whole)(w)

    (a_mine, s_mine), (a_theirs, s_theirs) = jax.jit(both)(w)
    # Reverse mode, compiled (the one-pass filter has none under jit: the matrix
    # exponential's squarings are a loop whose count is known only when its input is; the
    # two passes differentiate it forward only), against the chain rule on the one-pass
    # filter's forward Jacobian: d Σ a²/s = Σ (2a/s) da − (a²/s²) ds.
    g_mine = jax.jit(jax.grad(lambda w: jnp.sum(split(w)[0] ** 2 / split(w)[1])))(w)
    a, v = whole(w)
    g_theirs = (2 * a / v) @ a_theirs - (a**2 / v**2) @ s_theirs
    for mine, theirs in ((a_mine, a_theirs), (s_mine, s_theirs), (g_mine, g_theirs)):
        assert float(jnp.max(jnp.abs(mine - theirs))) <= 1e-12 * float(jnp.max(jnp.abs(theirs)))
    assert float(jnp.min(jnp.max(jnp.abs(a_theirs[:, :5]), axis=0))) > 0  # each moves it
    # Differentiated in the errors alone, the covariance pass has no moving parameter.
    error, device, *_ = args(w)
    jac = jax.jacfwd(lambda e: moment_kalman(e, device, dt, m, 8, 25.0, 0.8, gaps)[0])(error)
    ref = jax.jacfwd(lambda e: _one_pass(e, device, dt, m, 25.0, 0.8, gaps)[0])(error)
    assert float(jnp.max(jnp.abs(jac - ref))) <= 1e-12 * float(jnp.max(jnp.abs(ref)))
