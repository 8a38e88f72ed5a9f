"""Maximum-likelihood state estimate of the sensing element, its linearisation error and
the paper's compensation (docs/models.md §2, Bezvesilna & Podchashinskyi, eqs. 2-18).

Pickoff samples α*_i = α(t_i) + δ_α(t_i), t_i = i·δ, i = 1..K. The linear model (2)

    α(t) = α_P + α_C sin ωt + α_S cos ωt,   Z = (α_P, α_C, α_S),   α_C = A cos φ, α_S = A sin φ

is linear in Z, so the maximum-likelihood estimate with Gaussian errors of covariance
R = σ² I + R_SE is the generalised least-squares solution

    Ẑ = (Aᵀ R⁻¹ A)⁻¹ Aᵀ R⁻¹ α*          (8)-(9): linear in the samples,
    Ψ = (Aᵀ R⁻¹ A)⁻¹                      (10): its error covariance,

with A = [1, sin ωt_i, cos ωt_i] (7). Note: the paper writes the normal matrix (8) with
column-summed weights w_i = Σ_j w_ji, which equals Aᵀ R⁻¹ A only for a diagonal R; this
module uses Aᵀ R⁻¹ A itself (the likelihood equation (3) exactly); `column_sum_estimate`
is the paper's printed form, for comparison.

The linearisation error. For a record of the refined (cubic / sine) motion, first order in
A³, ξt and the frequency error, the samples differ from the linear model by (derived here
from eq. 11; it fixes the signs printed in eq. 17, see `linearisation_error`)

    d_i = (A³/192) sin 3(ωt_i + φ) + A (ω_z − ω) t_i cos(ωt_i + φ) − A ξ t_i sin(ωt_i + φ),

ω_z = ω_d (1 − A²/16) the frequency of the motion and ω the estimator's frequency; the linear
estimator's error is Δ = (Aᵀ R⁻¹ A)⁻¹ Aᵀ R⁻¹ d (eqs. 12-16), Δ_αP its first component (18).
The compensation (patent UA 86005, steps 1-5) evaluates Δ at Â = |(α̂_C, α̂_S)|,
φ̂ = atan2(α̂_S, α̂_C) and subtracts Δ_αP.

Beyond the paper: `fit_sensing_element`, a weighted nonlinear least-squares fit (optimistix
Levenberg–Marquardt through a diffrax solve of the exact sine equation) of α_P and the
initial state, the reference estimator.

Covariances: every estimator takes `covariance`, either shape (K,) — the variances of
independent errors (a diagonal R, solved in O(K)) — or shape (K, K), a full R (Cholesky).
An optional `mask` of shape (K,) (1 = use, 0 = ignore) restricts the estimate to a subset
of the samples with a fixed array shape, so that one compiled function runs over records of
different length K (see `accel_jax._pendulum.record_mask`). Linear solves use lineax.
Precision follows the inputs; the study and tests use float64 (the biases are 1e-10…1e-5 rad).

Modules: `disturbances` (white, Gauss–Markov, harmonic and exponential disturbances, the
error covariance), `estimate` (the GLS estimate, the paper's column-sum estimate
`column_sum_estimate`, and the linearisation error), `compensation`,
`fit` (the exact-sine fit).
"""

from .compensation import CompensatedEstimate as CompensatedEstimate
from .compensation import compensate_linearisation as compensate_linearisation
from .disturbances import AbstractDisturbance as AbstractDisturbance
from .disturbances import ExponentialDisturbance as ExponentialDisturbance
from .disturbances import GaussMarkovDisturbance as GaussMarkovDisturbance
from .disturbances import HarmonicDisturbance as HarmonicDisturbance
from .disturbances import WhiteDisturbance as WhiteDisturbance
from .disturbances import error_covariance as error_covariance
from .estimate import MLEstimate as MLEstimate
from .estimate import column_sum_estimate as column_sum_estimate
from .estimate import linearisation_error as linearisation_error
from .estimate import linearisation_residual as linearisation_residual
from .estimate import ml_estimate as ml_estimate
from .estimate import state_basis as state_basis
from .fit import NonlinearFit as NonlinearFit
from .fit import fit_sensing_element as fit_sensing_element
