"""The predictability test of a noise candidate, calibrated by its own fitted noise: how much
of the held-out residual each predictor (`openworld.predictability`: a template locked to
the input changes, a sinusoid, a trend, fitted on the training part) removes from
realisations of the candidate's fitted noise model alone, on the record's blocks and
held-out mask. A strong, slow noise is partly predictable by chance (a line fitted to the
training part continues a slow wander; a template averages a few large excursions): the
fixed `openworld.PREDICTABLE` fraction then called Gauss–Markov moment noise 7 times in 30
"deterministic" on the blind coloured-noise records. A misfit is deterministic for a noise
candidate when a predictor removes at least `PREDICTABLE` of the held-out residual *and*
more than it removes from the candidate's own noise in `NULL_QUANTILE` of `NULL_DRAWS`
realisations.

Realisations (host side, NumPy, float64): the output noise (`effects.ColoredNoise`) as its
block means' ARMA(1,1) (`effects.block_noise`) after a burn-in; the moment noise
(`effects.MomentNoise`) by its block-level state-space model
(`innovations.moment_noise_model`) from the stationary state. Each is scaled by the fit's
white noise per sample (`sigma_white_per_sample_V`).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.signal import lfilter

from .. import openworld
from .effects import block_noise
from .model import refitted_device
from .innovations import moment_noise_model
from .layout import W
from .state import StepFit, StepRecord

NULL_DRAWS = 100
"""Realisations of a noise candidate's fitted noise for the null of its predictability."""

NULL_QUANTILE = 0.99
"""A predictor's removal counts as deterministic above this quantile of its null."""

TESTS = openworld.PREDICTORS

MAX_BURN = 20_000
"""The longest burn-in (blocks) of an output-noise realisation."""


@dataclasses.dataclass(frozen=True)
class CalibratedPredictability(openworld.Predictability):
    """A residual's `openworld.Predictability` judged against a noise candidate's own fitted
    noise (`calibrated`): its fields, with `deterministic` re-judged, and

    - `null_quantile`: {predictor (`TESTS`): the `NULL_QUANTILE` of the fraction it removes
        from realisations of the fitted noise alone (dimensionless)};
    - `null_draws`: how many realisations;
    - `null_model`: the noise candidate whose noise was drawn.

    `to_dict()` is the dict `calibrated` returned (the three after the predictability's);
    its string-keyed access still reads for one release, with a `DeprecationWarning`.
    """

    null_quantile: dict[str, float] = dataclasses.field(default_factory=dict)
    null_draws: int = 0
    null_model: str = ""


def _sqrt_psd(matrix: np.ndarray) -> np.ndarray:
    values, vectors = np.linalg.eigh(0.5 * (matrix + matrix.T))
    return vectors * np.sqrt(np.clip(values, 0.0, None))


def noise_draws(fit: StepFit, rec: StepRecord, base, count: int, seed: int = 0) -> np.ndarray:
    """`count` realisations (count, rec.n) [V] of `fit`'s fitted noise on the record's blocks
    (`fit.model` a noise effect: `colored_noise` or `moment_noise`)."""
    model = fit.model
    if model is None or not model.stochastic:
        raise ValueError(f"{fit.effect} is not a noise candidate")
    rng = np.random.default_rng(seed)
    n, m = rec.n, rec.block
    z = np.asarray(fit.w)[W.effect(model.n_params)]
    white = float(fit.params["sigma_white_per_sample_V"])
    ratio, phi_block = max(float(z[0]), 0.0) ** 2, float(np.tanh(float(z[1])))
    if model.loop_noise:
        import jax.numpy as jnp

        device = refitted_device(base, jnp.asarray(fit.z), jnp.asarray(rec.prior_sigma))
        power, total, p, _, _ = (
            np.asarray(v)
            for v in moment_noise_model(device, rec.dt_sample, m, max(m, 1), ratio, phi_block)
        )
        lead = power[:, :5]
        root_total, root_p = _sqrt_psd(total), _sqrt_psd(p)
        state = rng.standard_normal((count, 5)) @ root_p.T
        out = np.empty((count, n))
        for k in range(n):
            joint = state @ lead.T + rng.standard_normal((count, 6)) @ root_total.T
            out[:, k] = joint[:, 5] + rng.standard_normal(count) / np.sqrt(m)
            state = joint[:, :5]
        return white * out
    phi, theta, _, variance = (float(v) for v in block_noise(ratio, phi_block, m, max(m, 1)))
    burn = int(min(MAX_BURN, 10.0 / max(1.0 - abs(phi), 1e-12)))
    a = rng.standard_normal((count, n + burn)) * np.sqrt(variance)
    filtered = np.asarray(lfilter([1.0, -theta], [1.0, -phi], a, axis=1))
    return white * filtered[:, burn:]


def calibrated(
    predictable: openworld.Predictability,
    fit: StepFit,
    rec: StepRecord,
    base,
    window: int,
    count: int = NULL_DRAWS,
) -> CalibratedPredictability:
    """`predictable` (the nominal residual's `openworld.predictability`) judged against
    `fit`'s own noise, a `CalibratedPredictability`: `null_quantile` {test: the
    NULL_QUANTILE of what the test removes from the fitted noise alone}, `null_draws`, and
    `deterministic` re-judged (a test removes at least `openworld.PREDICTABLE` and more than
    its null quantile)."""
    draws = noise_draws(fit, rec, base, count)
    removed = {test: [] for test in TESTS}
    for draw in draws:
        out = openworld.predictability(
            draw, rec.held, rec.dt, rec.change_block, rec.change_step, window
        )
        for test in TESTS:
            removed[test].append(out.removed(test))
    quantile = {test: float(np.quantile(removed[test], NULL_QUANTILE)) for test in TESTS}
    deterministic = any(
        predictable.removed(test) >= openworld.PREDICTABLE
        and predictable.removed(test) > quantile[test]
        for test in TESTS
    )
    plain = dataclasses.fields(openworld.Predictability)
    fields = {f.name: getattr(predictable, f.name) for f in plain}
    fields.update(deterministic=bool(deterministic))
    return CalibratedPredictability(
        **fields, null_quantile=quantile, null_draws=count, null_model=fit.effect
    )
