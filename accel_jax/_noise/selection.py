"""Structure selection: `select_noise_model` fits every candidate sum of white, Gauss-Markov,
exponential-cosine and random-walk noise by maximum likelihood from `initial_model`'s start,
ranks the fits by BIC or AIC and tests each one's standardised innovations for whiteness
with `ljung_box`, returning a `StructureSelection`; `_fit_ml_jit` and `_innovations_jit` are
the compiled fit and filter it calls once per structure.
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike

from .fit import NoiseFit, fit_maximum_likelihood, innovations
from .models import (
    AbstractNoiseModel,
    ExponentialCosine,
    GaussMarkov,
    NoiseSum,
    RandomWalk,
    WhiteNoise,
    model_parameters,
)
from .record import NoiseFitResult, _sample_interval, _validate_record, autocorrelation
from .whiteness import ljung_box

DEFAULT_STRUCTURES: tuple[str, ...] = (
    "white",
    "gauss_markov",
    "exp_cosine",
    "random_walk",
    "white+gauss_markov",
    "white+random_walk",
    "gauss_markov+random_walk",
    "white+exp_cosine",
)
"""Candidate structures `select_noise_model` compares by default."""

_COMPONENTS = ("white", "gauss_markov", "exp_cosine", "random_walk")


def initial_model(structure: str, record: ArrayLike, sample_interval: float) -> AbstractNoiseModel:
    """A starting point for `fit_maximum_likelihood` of a structure ("white",
    "gauss_markov", "exp_cosine", "random_walk" or sums joined by "+"), from the record's
    variance, its increments and the paper's rules on its autocorrelation (lags up to N/8).
    Components of a sum share the variance equally. A host-side helper (NumPy on a concrete
    record), not jittable; `select_noise_model` calls it once per structure."""
    names = structure.split("+")
    unknown = [name for name in names if name not in _COMPONENTS]
    if unknown or len(set(names)) != len(names):
        raise ValueError(
            f"initial_model: unknown or repeated component(s) in {structure!r}; use "
            f"{_COMPONENTS} joined by '+'."
        )
    x = np.asarray(_validate_record("initial_model", record), dtype=float)
    dt = float(sample_interval)
    n = x.shape[0]
    max_lag = max(2, min(n // 8, 2000))
    R = np.asarray(autocorrelation(x, max_lag))
    share = float(R[0]) / len(names)
    r = R / R[0]
    positive = np.cumprod(r[1:] > 0).astype(bool)
    upto = max(1, int(np.sum(positive & (r[1:] > np.exp(-1)))))
    lags = np.arange(1, upto + 1) * dt
    alpha = -np.sum(np.log(np.clip(r[1 : upto + 1], 1e-12, None))) / np.sum(lags)
    tau = float(np.clip(1 / alpha if alpha > 0 else 10 * dt, dt, n * dt))
    first_zero = int(np.argmax(r[1:] <= 0)) + 1 if np.any(r[1:] <= 0) else max_lag
    beta = 0.5 * np.pi / (first_zero * dt)
    increments = np.var(np.diff(x)) / dt
    models = []
    for name in names:
        if name == "white":
            models.append(WhiteNoise(np.sqrt(share)))
        elif name == "gauss_markov":
            models.append(GaussMarkov(np.sqrt(share), tau))
        elif name == "exp_cosine":
            models.append(ExponentialCosine(np.sqrt(share), 1 / tau, beta))
        else:
            models.append(RandomWalk(max(increments / len(names), 1e-300) * 0.1))
    dtype = jnp.result_type(float)
    models = [jax.tree_util.tree_map(lambda v: jnp.asarray(v, dtype), m) for m in models]
    return models[0] if len(models) == 1 else NoiseSum(tuple(models))


class StructureSelection(eqx.Module):
    """Result of `select_noise_model`.

    **Fields:**

    - `chosen`: the structure with the smallest criterion (e.g. "white+gauss_markov").
    - `model`: its fitted model; `fit`: its `NoiseFit` (with confidence bounds).
    - `table`: one dict per structure, best first: structure, num_parameters,
        log_likelihood, aic, bic, delta (criterion − best), converged, ljung_box_p,
        parameters (name → value, with SI units in the name).
    - `fits`: structure → `NoiseFit`.
    - `residual_autocorrelation`: structure → ρ_1..ρ_L of its standardised innovations.
    - `criterion`: "bic" or "aic".
    """

    chosen: str = eqx.field(static=True)
    model: AbstractNoiseModel
    fit: NoiseFit
    table: list = eqx.field(static=True)
    fits: dict
    residual_autocorrelation: dict
    criterion: str = eqx.field(static=True)


def select_noise_model(
    record: ArrayLike,
    sample_interval: float,
    *,
    structures: Sequence[str] = DEFAULT_STRUCTURES,
    criterion: str = "bic",
    residual_lags: int = 20,
    max_steps: int = 256,
) -> StructureSelection:
    """Choose the noise structure of a record by maximum likelihood and an information
    criterion — the paper's structure identification, made quantitative.

    Every candidate structure is fitted by `fit_maximum_likelihood` from `initial_model`;
    the smallest BIC (default; or AIC) wins. Fits that ran out of optimiser steps are flagged
    (`converged` False) and still compete: that happens when a redundant parameter runs to
    a boundary, where the criterion's penalty already rules the structure out. The
    standardised innovations of each fit are tested for whiteness (Ljung-Box over
    `residual_lags` lags): a wrong structure leaves correlation in them — the paper's
    warning that a wrong model makes the filter diverge.

    **Arguments:**

    - `record`: x, shape (N,), e.g. a static accelerometer record [g]; N ≥ 4·residual_lags.
    - `sample_interval`: Δ [s].
    - `structures`: candidates, from "white", "gauss_markov", "exp_cosine", "random_walk"
        and their sums joined by "+".
    - `criterion`: "bic" or "aic".

    **Returns:** `StructureSelection`. Not jitted as a whole (one compiled fit per
    structure); float64 recommended (a float32 log-likelihood of 10⁴ samples is only good to
    ~0.1). Bad records (NaN, constant, too short) raise `ValueError`.
    """
    if criterion not in ("bic", "aic"):
        raise ValueError(
            f"select_noise_model: criterion must be 'bic' or 'aic', got {criterion!r}."
        )
    if not structures:
        raise ValueError("select_noise_model: no candidate structures given.")
    x = _validate_record("select_noise_model", record, max_lag=residual_lags)
    _sample_interval("select_noise_model", sample_interval)
    dt = float(sample_interval)
    fits, rhos, rows = {}, {}, []
    for structure in structures:
        init = initial_model(structure, x, dt)
        fit = _fit_ml_jit(init, x, dt, max_steps)
        standardised, _ = _innovations_jit(fit.model, x, dt)
        whiteness = ljung_box(standardised[1:], residual_lags, fit.num_parameters)
        fits[structure] = fit
        rhos[structure] = np.asarray(whiteness["autocorrelation"])
        rows.append(
            {
                "structure": structure,
                "num_parameters": fit.num_parameters,
                "log_likelihood": float(fit.objective),
                "aic": float(fit.aic),
                "bic": float(fit.bic),
                "converged": bool(fit.result == NoiseFitResult.successful),
                "ljung_box_Q": whiteness["statistic"],
                "ljung_box_p": whiteness["p_value"],
                "parameters": model_parameters(fit.model),
            }
        )
    # A fit that ran out of steps is usually a structure with a redundant parameter
    # running to a boundary (a Gauss-Markov τ → 0 on white data, β → 0 of an
    # exponential-cosine on Gauss-Markov data): its likelihood is then that of the simpler
    # structure and the criterion's penalty rules it out, so it still competes (flagged).
    usable = [row for row in rows if np.isfinite(row[criterion])]
    if not usable:
        raise ValueError(
            "select_noise_model: no candidate structure gave a finite likelihood; check the "
            "record's units and sampling."
        )
    best = min(usable, key=lambda row: row[criterion])
    for row in rows:
        row["delta"] = row[criterion] - best[criterion]
    rows.sort(key=lambda row: row[criterion] if np.isfinite(row[criterion]) else np.inf)
    chosen = best["structure"]
    return StructureSelection(
        chosen=chosen,
        model=fits[chosen].model,
        fit=fits[chosen],
        table=rows,
        fits=fits,
        residual_autocorrelation=rhos,
        criterion=criterion,
    )


@eqx.filter_jit
def _fit_ml_jit(init, x, dt, max_steps):
    return fit_maximum_likelihood(init, x, dt, max_steps=max_steps, throw=False)


@eqx.filter_jit
def _innovations_jit(model, x, dt):
    return innovations(model, x, dt)
