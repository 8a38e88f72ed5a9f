"""One noise model (issue 43): the noise spectra are defined once, in
`accel_jax._noise.models`, and every path that evaluates one gets it from there.

- The models' spectra are those of their autocovariances and state-space forms (and the
  low-pass's gain that of scipy's bilinear Butterworth design).
- The sensor analysis' Whittle spectrum (`_noise.spectral.spectrum`), for each component
  alone and all together at random parameters, equals the models' spectrum of the
  differenced record; `spectral.component_models` gives those models.
- The noise diagnosis' Whittle spectrum (`diagnose.noise.fit.spectrum`), for each
  candidate at random parameters, equals the models'.
- The diagnosis' hand-unrolled Kalman filter (`noise_fit.filter_terms`) gives the
  log-likelihood terms of `accel_jax._kalman.kalman_filter` on the models' state space,
  and takes its transition from `ExponentialCosine.discrete_state_space` (finite, with
  finite derivatives, at the nominal candidate's ρ = 0).
- The deterministic terms of the mean (`accel_jax._noise.mean_models`: `PeriodicLine`,
  `StartupTransient`) are the formulas the sensor-noise selection used, and every path
  that fits, evaluates or reports a line or a transient goes through them.

All in float64 (tests/conftest.py), to round-off.
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import signal

from accel_jax._kalman import LinearGaussianModel, kalman_filter
from accel_jax._noise import _DIFFUSE, spectral
from accel_jax._noise.models import (
    ButterworthLowPass,
    ExponentialCosine,
    Flicker,
    GaussMarkov,
    HighFrequencyNoise,
    NoiseSum,
    RandomWalk,
    WhiteNoise,
    differencing_gain,
)
from accel_jax.diagnose.noise import fit as noise_fit

DT = 0.01
DRAWS = 6
# The folded grid of the debiasing correction includes ω = 0 and π.
OMEGA = jnp.asarray(np.linspace(0.0, math.pi, 257))
RTOL = 1e-12


def _close(actual, expected, rtol=RTOL):
    np.testing.assert_allclose(np.asarray(actual), np.asarray(expected), rtol=rtol, atol=0.0)


# --------------------------------------------------------------------------------------
# The models' spectra against their autocovariances and state-space forms
# --------------------------------------------------------------------------------------


def _stationary_models(rng):
    sigma = math.exp(rng.uniform(-2, 1))
    return [
        WhiteNoise(sigma),
        GaussMarkov(sigma, DT * math.exp(rng.uniform(0, 3))),
        ExponentialCosine(sigma, math.exp(rng.uniform(-1, 2)), rng.uniform(5.0, 250.0)),
    ]


@pytest.mark.parametrize("seed", range(DRAWS))
def test_spectra_are_those_of_the_autocovariance_and_the_state_space(seed):
    rng = np.random.default_rng(seed)
    size = 1 << 14  # aliasing ρ^size: nothing at float64
    grid = jnp.asarray(2 * np.pi * np.arange(size) / size)
    lags = np.arange(24)
    for model in _stationary_models(rng):
        f = np.asarray(model.spectrum(grid, DT))
        from_spectrum = np.real(np.fft.ifft(f))[lags]
        scale = float(model.autocovariance(0.0))
        np.testing.assert_allclose(
            from_spectrum, np.asarray(model.autocovariance(lags * DT)), atol=1e-12 * scale
        )
        # R_k = H F^k P0 Hᵀ (+ r at k = 0) of the state-space form.
        F, _, H, P0, r = (np.asarray(a) for a in model.state_space(DT))
        state = [
            float((H @ np.linalg.matrix_power(F, k) @ P0 @ H.T)[0, 0]) + (float(r) if k == 0 else 0)
            for k in lags
        ]
        np.testing.assert_allclose(from_spectrum, state, atol=1e-12 * scale)
    # The random walk: its difference is white of variance qΔ, the state-space increment.
    walk = RandomWalk(math.exp(rng.uniform(-8, -2)))
    _, Q, _, _, _ = walk.state_space(DT)
    _close(walk.difference_spectrum(OMEGA, DT), np.full(OMEGA.shape, float(Q[0, 0])))
    inner = OMEGA[1:]
    _close(walk.spectrum(inner, DT) * differencing_gain(inner), walk.difference_spectrum(inner, DT))
    # Flicker: B²/|ω| per sample, the IEEE 952 PSD B²/(2π f) at f = ω/(2πΔ), times 1/Δ.
    flicker = Flicker(math.exp(rng.uniform(-3, 0)))
    b2 = float(flicker.coefficient) ** 2
    frequency = np.asarray(inner) / (2 * np.pi * DT)
    _close(flicker.spectrum(inner, DT), b2 / (2 * np.pi * frequency) / DT)
    assert float(flicker.spectrum(jnp.zeros(1), DT)[0]) == 0.0


@pytest.mark.parametrize("seed", range(DRAWS))
def test_low_pass_gain_is_the_bilinear_butterworth(seed):
    rng = np.random.default_rng(100 + seed)
    corner = rng.uniform(0.02, 0.98) / (2 * DT)  # below the Nyquist frequency
    sos = signal.butter(2, corner * 2 * DT, output="sos")
    w, h = signal.sosfreqz(sos, worN=np.asarray(OMEGA[:-1]))
    gain = ButterworthLowPass(corner).gain(jnp.asarray(w), DT)
    np.testing.assert_allclose(np.asarray(gain), np.abs(h) ** 2, rtol=1e-9, atol=1e-15)


# --------------------------------------------------------------------------------------
# The sensor analysis' Whittle spectrum (`_noise.spectral`)
# --------------------------------------------------------------------------------------


def _spectral_draw(rng):
    return np.array(
        [
            rng.uniform(-2, 2),  # ln σ_w²
            rng.uniform(-2, 2),  # ln σ_g²
            rng.uniform(0, 5),  # ln τ_c/Δ
            rng.uniform(-2, 2),  # ln σ_e²
            rng.uniform(-5, -1),  # ln αΔ (before the quality bound)
            rng.uniform(-3, 1),  # ln θ
            rng.uniform(-9, -2),  # ln qΔ
            rng.uniform(-5, 0),  # ln B²
            rng.uniform(-3, 3),  # logit(f_b/f_N)
            rng.uniform(-6, 0),  # ln p_f (the white noise after the filter)
            rng.uniform(-2, 2),  # ln σ_h² (the high-frequency noise)
            rng.uniform(-3, 3),  # logit(f_h/f_N)
        ]
    )


def _expected_parameters(z):
    """The models' parameters of z, as `spectral`'s N_PARAMS docstring defines them."""
    theta = math.exp(z[5])
    return {
        "white": math.exp(z[0]),
        "gauss_markov": (math.exp(z[1]), DT * math.exp(z[2])),
        "exp_cosine": (
            math.exp(z[3]),
            (math.exp(z[4]) + theta / spectral.MAX_QUALITY) / DT,
            theta / DT,
        ),
        "random_walk": math.exp(z[6]) / DT,
        "flicker": math.exp(z[7]),
        "bandlimit": 1 / (1 + math.exp(-z[8])) / (2 * DT),
        "filter_floor": math.exp(z[9]),
        "high_frequency_noise": (math.exp(z[10]), 1 / (1 + math.exp(-z[11])) / (2 * DT)),
    }


def _model_difference_spectrum(noise, low_pass, floor):
    """λ(H Σ f_stationary + p) + H qΔ from the models alone."""
    components = noise.components if isinstance(noise, NoiseSum) else (noise,)
    gain = 1.0 if low_pass is None else low_pass.gain(OMEGA, DT)
    coloured = sum(c.spectrum(OMEGA, DT) for c in components if not isinstance(c, RandomWalk))
    walk = sum(c.difference_spectrum(OMEGA, DT) for c in components if isinstance(c, RandomWalk))
    return differencing_gain(OMEGA) * (gain * coloured + floor) + gain * walk


STRUCTURES = [(name,) for name in spectral.COMPONENTS] + [tuple(spectral.COMPONENTS)]


@pytest.mark.parametrize("names", STRUCTURES, ids="+".join)
def test_spectral_whittle_spectrum_is_the_models(names):
    rng = np.random.default_rng(len(names) * 7 + spectral.COMPONENTS.index(names[0]))
    mask = spectral._mask(names)
    for _ in range(DRAWS):
        z = _spectral_draw(rng)
        floor = rng.uniform(0, 0.1)
        noise, low_pass, after = spectral.component_models(z, mask, DT)
        expected = _expected_parameters(z)
        components = noise.components if isinstance(noise, NoiseSum) else (noise,)
        for c in components:
            if isinstance(c, WhiteNoise):
                _close(c.sigma**2, expected["white"])
            elif isinstance(c, GaussMarkov):
                _close(c.sigma**2, expected["gauss_markov"][0])
                _close(c.correlation_time, expected["gauss_markov"][1])
            elif isinstance(c, ExponentialCosine):
                e = expected["exp_cosine"]
                _close(jnp.stack([c.sigma**2, c.decay_rate, c.angular_frequency]), e)
            elif isinstance(c, RandomWalk):
                _close(c.intensity, expected["random_walk"])
            elif isinstance(c, HighFrequencyNoise):
                _close(c.sigma**2, expected["high_frequency_noise"][0])
                _close(c.corner_frequency, expected["high_frequency_noise"][1])
            else:
                assert isinstance(c, Flicker)
                _close(c.coefficient**2, expected["flicker"])
        names_on = {c.name for c in components} - {"white"}
        assert names_on == set(names) - {"bandlimit", "filter_floor"}
        assert (low_pass is not None) == ("bandlimit" in names)
        if low_pass is not None:
            _close(low_pass.corner_frequency, expected["bandlimit"])
        assert (after is not None) == ("filter_floor" in names)
        after_variance = 0.0
        if after is not None:
            _close(after.sigma**2, expected["filter_floor"])
            after_variance = after.sigma**2
        path = spectral.spectrum(jnp.asarray(z), jnp.asarray(mask), OMEGA, floor)
        _close(path, _model_difference_spectrum(noise, low_pass, floor + after_variance))


def test_a_component_the_mask_leaves_off_is_not_evaluated():
    """A slot the mask leaves off enters neither the Whittle likelihood's value nor its
    gradient, even where its parameters would overflow: the component is not evaluated
    (`spectral._if_on`; a `jnp.where` over an evaluated inf gave a NaN gradient). Under
    `vmap` over masks, the spectrum of each mask is the one computed alone."""
    rng = np.random.default_rng(11)
    z = _spectral_draw(rng)
    overflowing = z.copy()
    overflowing[[1, 3, 7, 10]] = 800.0  # e^800 = inf: every coloured component's variance
    walk = np.cumsum(rng.standard_normal(4_000)) * 0.01
    gram = spectral.periodogram(walk + rng.standard_normal(4_000))
    floor = jnp.asarray(1e-6)
    for names in [(), ("random_walk",), ("bandlimit", "filter_floor")]:
        mask = jnp.asarray(spectral._mask(names))
        value, gradient = jax.value_and_grad(spectral.whittle)(
            jnp.asarray(overflowing), mask, gram, floor
        )
        reference = spectral.whittle(jnp.asarray(z), mask, gram, floor)
        assert np.isfinite(float(value)) and np.all(np.isfinite(np.asarray(gradient)))
        _close(value, reference)
        off = ~np.asarray(spectral._free(mask))
        assert np.all(np.asarray(gradient)[off] == 0.0)
    masks = jnp.asarray([spectral._mask(s) for s in STRUCTURES])
    together = jax.vmap(lambda m: spectral.spectrum(jnp.asarray(z), m, OMEGA, 0.01))(masks)
    for mask, row in zip(masks, together, strict=True):
        _close(row, spectral.spectrum(jnp.asarray(z), mask, OMEGA, 0.01))


# --------------------------------------------------------------------------------------
# The noise diagnosis' Whittle spectrum and Kalman filter (`diagnose.noise.fit`)
# --------------------------------------------------------------------------------------

CANDIDATES = {0: "white", 1: "gauss_markov", 2: "exp_cosine", 3: "random_walk"}


def test_diagnosis_candidates_are_in_this_order():
    assert [e.name for e in noise_fit._effects()] == list(CANDIDATES.values())[1:]


def _diagnosis_draw(rng):
    # [ln σ_w, amplitude, decay/time scale, √θ] (noise_effects' slot layout)
    return np.array(
        [rng.uniform(-1, 1), rng.uniform(0.2, 2.0), rng.uniform(-4, -0.5), rng.uniform(0.2, 1.5)]
    )


def _diagnosis_models(z, candidate):
    """White + the candidate's process as `models`' modules, from noise_effects' mapping:
    σ_w = e^{z₀}; GM σ = |z₁|, τ_c = Δ e^{−z₂}; exp-cos σ = |z₁|, α = e^{z₂}/Δ, β = z₃²/Δ;
    walk √(qΔ) = |z₁|."""
    white = WhiteNoise(math.exp(z[0]))
    name = CANDIDATES[candidate]
    if name == "white":
        return (white,)
    if name == "gauss_markov":
        return white, GaussMarkov(abs(z[1]), DT * math.exp(-z[2]))
    if name == "exp_cosine":
        return white, ExponentialCosine(abs(z[1]), math.exp(z[2]) / DT, z[3] ** 2 / DT)
    return white, RandomWalk(z[1] ** 2 / DT)


@pytest.mark.parametrize("candidate", list(CANDIDATES), ids=list(CANDIDATES.values()))
def test_diagnosis_whittle_spectrum_is_the_models(candidate):
    rng = np.random.default_rng(200 + candidate)
    for _ in range(DRAWS):
        z = _diagnosis_draw(rng)
        models = _diagnosis_models(z, candidate)
        expected = sum(m.difference_spectrum(OMEGA, DT) for m in models)
        _close(noise_fit.spectrum(jnp.asarray(z), candidate, OMEGA), expected)


def _generic_terms(models, walk, record, diffuse):
    """`_kalman.kalman_filter`'s log-likelihood terms for white + block + a level of
    increment variance `walk` qΔ per sample (0: a constant level), its start diffuse."""
    level = RandomWalk(1.0)
    level = eqx.tree_at(lambda m: m.intensity, level, jnp.asarray(walk / DT))
    model = NoiseSum((*models, level))
    f, q, h, p0, r = model.state_space(DT)
    p0 = jnp.where(p0 < 0, diffuse, p0)
    lgm = LinearGaussianModel(f, q, h, jnp.reshape(r, (1, 1)))
    out = kalman_filter(lgm, record, jnp.zeros(f.shape[0]), p0)
    return out.log_likelihoods


@pytest.mark.parametrize("candidate", list(CANDIDATES), ids=list(CANDIDATES.values()))
def test_diagnosis_filter_is_the_generic_kalman_filter(candidate):
    rng = np.random.default_rng(300 + candidate)
    n = 240
    for _ in range(3):
        z = _diagnosis_draw(rng)
        x = rng.normal(size=n).cumsum() * 0.05 + rng.normal(size=n)
        record = jnp.asarray(x - x.mean())
        diffuse = _DIFFUSE * float(jnp.mean(record**2))
        white, parts = noise_fit._components(jnp.asarray(z), candidate)
        _, _, terms = noise_fit.filter_terms(white, parts, record, diffuse)
        models = _diagnosis_models(z, candidate)
        last = models[-1]
        walk = float(last.intensity) * DT if isinstance(last, RandomWalk) else 0.0
        block = tuple(m for m in models if not isinstance(m, RandomWalk))
        reference = _generic_terms(block, walk, record, diffuse)
        # The first term carries the diffuse prior (S ≈ 1e6 var): equal to its round-off.
        np.testing.assert_allclose(np.asarray(terms[1:]), np.asarray(reference[1:]), rtol=1e-9)
        np.testing.assert_allclose(float(terms[0]), float(reference[0]), rtol=1e-9)


def test_exp_cosine_discrete_state_space_is_its_state_space():
    """`ExponentialCosine.discrete_state_space` of the per-sample parameters is the model's
    `state_space(Δ)` (to the bit given 1 − ρ² as −expm1(−2αΔ), to 1e-12 with its own
    1 − ρ²), and F is ρ Rot(θ)."""
    rng = np.random.default_rng(310)
    for _ in range(DRAWS):
        model = _stationary_models(rng)[2]
        assert isinstance(model, ExponentialCosine)
        alpha, beta = float(model.decay_rate), float(model.angular_frequency)
        rho, theta = math.exp(-alpha * DT), beta * DT
        variance = model.sigma**2
        expected = model.state_space(DT)
        exact = ExponentialCosine.discrete_state_space(
            variance, jnp.exp(-model.decay_rate * DT), model.angular_frequency * DT,
            -jnp.expm1(-2 * model.decay_rate * DT),
        )  # fmt: skip
        for got, want in zip(exact, expected, strict=True):
            np.testing.assert_array_equal(np.asarray(got), np.asarray(want))
        plain = ExponentialCosine.discrete_state_space(variance, rho, theta)
        for got, want in zip(plain, expected, strict=True):
            np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-12, atol=0)
        rotation = [[math.cos(theta), -math.sin(theta)], [math.sin(theta), math.cos(theta)]]
        _close(plain[0], rho * np.array(rotation))


def test_diagnosis_filter_builds_its_transition_from_the_model(monkeypatch):
    """`filter_terms` takes the block's transition and noise from
    `ExponentialCosine.discrete_state_space` (a spy sees the call with the candidate's v, ρ,
    θ), and the likelihood, its gradient and its Hessian stay finite at the nominal
    candidate, where ρ = 0 and v = 0 (no log of ρ on the way)."""
    import jax

    seen = []
    real = ExponentialCosine.discrete_state_space

    def spy(*args):
        seen.append(args)
        return real(*args)

    monkeypatch.setattr(ExponentialCosine, "discrete_state_space", staticmethod(spy))
    rng = np.random.default_rng(320)
    x = rng.normal(size=200).cumsum() * 0.05 + rng.normal(size=200)
    record = jnp.asarray(x - x.mean())
    diffuse = _DIFFUSE * float(jnp.mean(record**2))
    z = jnp.asarray(_diagnosis_draw(rng))
    white, parts = noise_fit._components(z, 2)
    noise_fit.filter_terms(white, parts, record, diffuse)
    assert len(seen) == 1
    for got, want in zip(seen[0], (parts.variance, parts.decay, parts.rotation), strict=True):
        np.testing.assert_array_equal(np.asarray(got), np.asarray(want))
    weight = jnp.asarray((np.arange(200) > 0).astype(float))
    args = (record, weight, 0, diffuse)
    white, parts = noise_fit._components(z, 0)
    assert float(parts.decay) == 0.0 and float(parts.variance) == 0.0
    value = noise_fit._negative_log_likelihood(z, args)
    gradient = jax.grad(noise_fit._negative_log_likelihood)(z, args)
    hessian = jax.hessian(noise_fit._negative_log_likelihood)(z, args)
    for a in (value, gradient, hessian):
        assert np.all(np.isfinite(np.asarray(a)))


# --------------------------------------------------------------------------------------
# The diagnosis figure's fitted-model PSD (a fourth copy of the formulas, in
# report/figures/diagnosis.py): checked against the models' one-sided PSD
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("candidate", list(CANDIDATES), ids=list(CANDIDATES.values()))
def test_diagnosis_figure_psd_is_the_models(candidate):
    from accel_jax.report.figures.diagnosis import _model_psd

    rng = np.random.default_rng(400 + candidate)
    frequency = np.linspace(0.5, 0.5 / DT, 200)  # up to the Nyquist frequency, f > 0
    for _ in range(DRAWS):
        models = _diagnosis_models(_diagnosis_draw(rng), candidate)
        white = models[0]
        assert isinstance(white, WhiteNoise)
        values = {"white_sigma_g": float(white.sigma)}
        if len(models) > 1:
            m = models[1]
            if isinstance(m, GaussMarkov):
                values |= {
                    "sigma_g": float(m.sigma),
                    "correlation_time_s": float(m.correlation_time),
                }
            elif isinstance(m, ExponentialCosine):
                values |= {
                    "sigma_g": float(m.sigma),
                    "decay_rate_per_s": float(m.decay_rate),
                    "angular_frequency_rad_per_s": float(m.angular_frequency),
                }
            else:
                assert isinstance(m, RandomWalk)
                values |= {"intensity_g2_per_s": float(m.intensity)}
        document = {"parameters": {k: {"value": v} for k, v in values.items()}}
        figure = _model_psd(document, frequency, DT)
        assert figure is not None
        expected = sum(np.asarray(m.one_sided_psd(frequency, DT)) for m in models)
        np.testing.assert_allclose(figure, expected, rtol=1e-11)


# --------------------------------------------------------------------------------------
# The spectra from precomputed sines (`Frequencies`) against their textbook forms
# --------------------------------------------------------------------------------------


def test_spectra_from_half_angle_sines_equal_the_cosine_forms_and_are_exact_near_zero():
    """Every `discrete_spectrum` is written with sin(ω/2) and cos(ω/2) (`Frequencies`, built
    once per fit): at random parameters it equals the textbook form with cos ω, cos(ω ∓ θ)
    and tan(ω/2) to round-off, given ω or its `Frequencies`. Where the textbook
    denominator 1 − 2ρ cos ω + ρ² cancels (ρ → 1, ω → 0) the half-angle form keeps full
    precision: checked against the value in 40-digit decimal arithmetic, where the cosine
    form is off by more than 10⁻⁵."""
    from decimal import Decimal, getcontext

    from accel_jax._noise.models import Frequencies

    rng = np.random.default_rng(7)
    omega = np.concatenate([np.linspace(-math.pi, math.pi, 401), rng.uniform(-3, 3, 100)])
    trig = Frequencies.of(jnp.asarray(omega))
    for _ in range(DRAWS):
        variance, rho, theta = math.exp(rng.normal()), rng.uniform(0.0, 0.999), rng.uniform(0, 3)
        corner = rng.uniform(0.05, math.pi / 2)

        def poisson(u, rho=rho):
            return (1 - rho**2) / (1 - 2 * rho * np.cos(u) + rho**2)

        size = np.minimum(np.abs(omega), math.pi * (1 - 1e-12))
        textbook = {
            "gm": variance * poisson(omega),
            "ec": variance / 2 * (poisson(omega - theta) + poisson(omega + theta)),
            "lowpass": 1 / (1 + (np.tan(size / 2) / math.tan(corner)) ** 4),
            "difference": 2 - 2 * np.cos(omega),
        }
        for given in (jnp.asarray(omega), trig):
            _close(GaussMarkov.discrete_spectrum(given, variance, rho), textbook["gm"])
            _close(
                ExponentialCosine.discrete_spectrum(given, variance, rho, theta), textbook["ec"]
            )
            _close(ButterworthLowPass.discrete_gain(given, corner), textbook["lowpass"])
            np.testing.assert_allclose(
                np.asarray(differencing_gain(given)), textbook["difference"], rtol=1e-12,
                atol=1e-15,
            )
    # Near the cancellation: ρ = 1 − 10⁻⁶, ω = 10⁻⁷.
    getcontext().prec = 40
    rho, w = 1 - 1e-6, 1e-7
    d_rho, d_w = Decimal(rho), Decimal(w) / 2
    half = d_w - d_w**3 / 6 + d_w**5 / 120  # sin(ω/2), error < 10⁻⁴⁷
    exact = (1 - d_rho**2) / ((1 - d_rho) ** 2 + 4 * d_rho * half**2)
    got = float(GaussMarkov.discrete_spectrum(jnp.asarray(w), 1.0, rho))
    assert got == pytest.approx(float(exact), rel=1e-13)
    assert abs(poisson(w, rho) / float(exact) - 1) > 1e-5


# --------------------------------------------------------------------------------------
# The deterministic terms of the mean (`_noise.mean_models`): periodic lines and the
# start-up transient, and every path that fits, evaluates or reports one
# --------------------------------------------------------------------------------------


def _line_draws(rng):
    t = np.arange(int(rng.integers(200, 4000))) * DT
    return t, rng.uniform(0.05, 0.5 / DT), rng.normal(0, 1e-3), rng.normal(0, 1e-3)


@pytest.mark.parametrize("seed", range(DRAWS))
def test_periodic_line_is_the_formula_the_selection_used(seed):
    """`PeriodicLine.signal` is the old `_line_signal` (c cos 2πft + s sin 2πft, w formed
    as 2π·f·t) and `basis` the old `_line_design`'s columns, to the bit on the host and to
    1e-12 of the amplitude traced; `to_dict` the old report {"frequency_Hz", "amplitude"
    = math.hypot(c, s)}; the power A²/2 the mean square over whole periods, split between
    ±f in `line_spectrum`."""
    import jax

    from accel_jax._noise.mean_models import PeriodicLine

    rng = np.random.default_rng(500 + seed)
    t, f, c, s = _line_draws(rng)
    line = PeriodicLine(f, c, s)
    w = 2 * np.pi * f * t
    old = c * np.cos(w) + s * np.sin(w)
    np.testing.assert_array_equal(line.signal(t), old)
    cos, sin = PeriodicLine.basis(t, f)
    np.testing.assert_array_equal(cos, np.cos(2 * np.pi * f * t))
    np.testing.assert_array_equal(sin, np.sin(2 * np.pi * f * t))
    amplitude = math.hypot(c, s)
    traced = jax.jit(lambda line, t: line.signal(t))(line, jnp.asarray(t))
    np.testing.assert_allclose(np.asarray(traced), old, rtol=0, atol=1e-12 * amplitude)
    assert line.to_dict() == {"frequency_Hz": f, "amplitude": amplitude}
    assert list(line.to_dict()) == ["frequency_Hz", "amplitude"]
    periods = np.arange(4096) / 4096 * 3 / f  # three whole periods
    _close(line.power, float(np.mean(line.signal(periods) ** 2)))
    frequencies, powers = line.line_spectrum()
    np.testing.assert_array_equal(frequencies, [-f, f])
    _close(np.sum(powers), amplitude**2 / 2)


@pytest.mark.parametrize("seed", range(DRAWS))
def test_startup_transient_is_the_formula_the_selection_used(seed):
    """`StartupTransient.signal` is the old `_transient_signal` a e^{−(t − t₀)/τ} on a
    record's times (t₀ = 0), to the bit on the host and to 1e-12 traced; one of unit
    amplitude over a τ grid is the old transient test's template; `to_dict` the old report
    {"time_constant_s", "amplitude"}, in that order."""
    import jax

    from accel_jax._noise.mean_models import StartupTransient

    rng = np.random.default_rng(600 + seed)
    t = np.arange(int(rng.integers(200, 4000))) * DT
    a, tau = rng.normal(0, 1e-2), math.exp(rng.uniform(-3, 1))
    transient = StartupTransient(a, tau)
    old = a * np.exp(-(t - t[0]) / tau)
    np.testing.assert_array_equal(transient.signal(t), old)
    traced = jax.jit(lambda m, t: m.signal(t))(transient, jnp.asarray(t))
    np.testing.assert_allclose(np.asarray(traced), old, rtol=0, atol=1e-12 * abs(a))
    taus = np.geomspace(2 * DT, t.size * DT / 4, 24)
    np.testing.assert_array_equal(
        StartupTransient(1.0, taus).signal(t[:, None]), np.exp(-t[:, None] / taus[None, :])
    )
    assert list(transient.to_dict().items()) == [("time_constant_s", tau), ("amplitude", a)]
    with pytest.raises(ValueError, match="time_constant"):
        StartupTransient(a, -tau)


def test_selection_fits_evaluates_and_reports_lines_and_transients_through_the_components(
    monkeypatch,
):
    """Every path of the sensor-noise selection that fits, evaluates or reports a line or a
    transient goes through `mean_models`: `_fit_line` returns a `PeriodicLine` built on its
    `basis`; `_Record.residual` takes out `signal`s; `_transient_test` builds its templates
    with `StartupTransient.signal` and returns one; `_physical` reports `to_dict`s; the
    open-world periodic predictor (`openworld.predictability`) regresses on `basis`."""
    from accel_jax._noise import sensor_model
    from accel_jax._noise.mean_models import PeriodicLine, StartupTransient
    from accel_jax.diagnose import openworld

    rng = np.random.default_rng(700)
    n = 3000
    t = np.arange(n) * DT
    x = 1e-3 * rng.normal(size=n) + 2e-3 * np.cos(2 * np.pi * 3.3 * t + 0.4) + 0.2
    x += 5e-3 * np.exp(-t / 0.3)
    calls = []
    spied = ((PeriodicLine, "basis"), (PeriodicLine, "signal"), (StartupTransient, "signal"))
    for cls, name in spied:
        real = cls.__dict__[name]
        function = real.__func__ if isinstance(real, staticmethod) else real

        def spy(*args, function=function, label=f"{cls.__name__}.{name}"):
            calls.append(label)
            return function(*args)

        monkeypatch.setattr(cls, name, staticmethod(spy) if isinstance(real, staticmethod) else spy)

    rec = sensor_model._Record(x, DT)
    line = sensor_model._fit_line(x[: rec.split], rec.t[: rec.split], 3.3, 0.05)
    assert isinstance(line, PeriodicLine) and calls == ["PeriodicLine.basis"]
    assert float(line.frequency) == pytest.approx(3.3, rel=1e-3)
    white = sensor_model._evaluate(rec, 1e-12, (), (), None)
    calls.clear()
    found = sensor_model._transient_test(rec.residual((line,), None)[: rec.split], DT, white, 1e-12)
    assert calls == ["PeriodicLine.signal", "PeriodicLine.basis", "StartupTransient.signal"]
    transient = found["transient"]
    assert isinstance(transient, StartupTransient)
    assert float(transient.amplitude) == pytest.approx(5e-3, rel=0.3)
    calls.clear()
    residual = rec.residual((line,), transient)
    assert calls[0] == "PeriodicLine.signal" and calls[-1] == "StartupTransient.signal"
    expected = x - np.mean(x[: rec.split]) - line.signal(rec.t) - transient.signal(rec.t)
    np.testing.assert_array_equal(residual, expected)
    model = dataclasses.replace(white, lines=(line,), transient=transient)
    reported = sensor_model._physical(model, DT, 1e-12)
    assert reported["sinusoid"] == [line.to_dict()]
    assert reported["startup_transient"] == transient.to_dict()
    calls.clear()
    openworld.predictability(x - x.mean(), 2000, DT, np.zeros(0, int), np.zeros(0), 10)
    # the line search (`_training_line`) fits each candidate frequency, then the predictor
    # regresses on the chosen one: every sinusoid it builds is `basis`, none of its own
    assert len(calls) > 1 and set(calls) == {"PeriodicLine.basis"}


@pytest.mark.parametrize(
    "names",
    [
        ("bandlimit_bessel3", "filter_floor", "gauss_markov"),
        ("bandlimit_taps5", "filter_floor"),
        ("bandlimit_order1", "exp_cosine", "random_walk"),
    ],
    ids="+".join,
)
def test_other_low_pass_shapes_are_the_models(names):
    """A Bessel low-pass and a moving average in the low-pass slot (`chain_filters`): the
    sensor analysis's spectrum is the difference spectrum built from the modules that
    `component_models` gives (`BesselLowPass`, `MovingAverage`, `ButterworthLowPass`)."""
    from accel_jax._noise.chain_filters import BesselLowPass, MovingAverage

    rng = np.random.default_rng(7)
    mask = spectral._mask(names)
    kinds = {"bandlimit_bessel3": BesselLowPass, "bandlimit_taps5": MovingAverage}
    for _ in range(DRAWS):
        z = _spectral_draw(rng)
        floor = rng.uniform(0, 0.1)
        noise, low_pass, after = spectral.component_models(z, mask, DT)
        assert isinstance(low_pass, kinds.get(names[0], ButterworthLowPass))
        if isinstance(low_pass, MovingAverage):
            assert low_pass.taps == 5
        else:
            assert low_pass.order == {"bandlimit_bessel3": 3, "bandlimit_order1": 1}[names[0]]
            _close(low_pass.corner_frequency, 1 / (1 + math.exp(-z[8])) / (2 * DT))
        after_variance = 0.0 if after is None else after.sigma**2
        path = spectral.spectrum(jnp.asarray(z), jnp.asarray(mask), OMEGA, floor)
        _close(path, _model_difference_spectrum(noise, low_pass, floor + after_variance))
