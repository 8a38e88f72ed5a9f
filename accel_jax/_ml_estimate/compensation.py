"""Compensation of the linearisation error of the ML estimate (docs/models.md §2)."""

from __future__ import annotations

import equinox as eqx
from jaxtyping import ArrayLike

from .._pendulum import SensingElement
from .disturbances import Scalar, ScalarLike, SeriesLike
from .estimate import MLEstimate, linearisation_error, ml_estimate


class CompensatedEstimate(eqx.Module):
    """Result of the paper's compensation algorithm (steps 1-5).

    **Fields:**

    - `constant_angle`: α̂_P − Δ_αP [rad], the compensated estimate (step 5).
    - `correction`: Δ_αP [rad] (step 4), evaluated at Â, φ̂ from the ML estimate.
    - `estimate`: the uncompensated `MLEstimate` (step 3).
    """

    constant_angle: Scalar
    correction: Scalar
    estimate: MLEstimate


def compensate_linearisation(
    ts: SeriesLike,
    samples: SeriesLike,
    *,
    angular_frequency: ScalarLike,
    element: SensingElement,
    covariance: ArrayLike,
    mask: SeriesLike | None = None,
) -> CompensatedEstimate:
    """The compensation algorithm (patent UA 86005), steps 1-5.

    1) R⁻¹, ω, Δω = ω − ω_d, δ, K are given a priori (`covariance`, `angular_frequency`,
    `element`, `ts`); 2) the samples; 3) Ẑ by eqs. (8)-(9); 4) Δ_αP by eqs. (16)-(18) at
    Â = sqrt(α̂_C² + α̂_S²), φ̂ = atan2(α̂_S, α̂_C); 5) α̂_P ← α̂_P − Δ_αP.

    **Arguments:** as `ml_estimate`, plus `element` (ω0 [rad/s], ξ [1/s]).

    **Returns:** a `CompensatedEstimate` (angles in rad).
    """
    estimate = ml_estimate(ts, samples, angular_frequency, covariance, mask=mask)
    delta = linearisation_error(
        ts,
        estimate.amplitude,
        estimate.phase,
        angular_frequency=angular_frequency,
        element=element,
        covariance=covariance,
        mask=mask,
    )
    return CompensatedEstimate(
        constant_angle=estimate.constant_angle - delta[0],
        correction=delta[0],
        estimate=estimate,
    )


# --- the nonlinear fit ------------------------------------------------------------------------
