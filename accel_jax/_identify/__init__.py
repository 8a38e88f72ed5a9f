"""In-flight identification of the scale factor from the test-signal step response.

docs/models.md §1 (Mironov, Fominov & Maletin): a constant test voltage U_test applied to an extra
torquer winding gives the second-order step response of W_test = K_test/(T²p² + 2ξTp + 1).

- Oscillatory case (ξ < 1, section 3.1): crossings of the steady-state line give the period,
  eq. (8); the overshoot/undershoot ratio gives ξ, eq. (9); T = √(1 − ξ²)/ω, eq. (10).
- Aperiodic case (ξ > 1, section 3.2): the tangent at the maximum slope gives T1 = T3 + T4
  and the tangent estimate T2 = √(T3 T4), eqs. (13)-(15); T2 is refined by solving
  t_inflection(T1, T2) = T0 (step 8) with a root finder; lag correction eq. (16).
- k_dp k_y from the outputs on the mechanical stops, eq. (11); K̂_a = γ T² k_dp k_y, eq. (7).
- Beyond the paper: a least-squares fit of the whole record to the second-order model, or to
  the third-order model with the torquer lag T_dm, with parameter covariance.

Every estimator takes one record `(ts, u_out)` of fixed length, is jit-compiled, and is
vmappable over records (`jax.vmap(lambda u: identify_oscillatory(ts, u, ...))(batch)`):
crossings and extrema are found with masks, cumulative sums and argmax, never with
data-dependent shapes. Expected failures (too few crossings, no root, …) are reported as an
`IdentificationResult` code; `throw=True` turns a failure into a runtime error with the
code's message, `throw=False` returns finite placeholder numbers for masking in sweeps.
Precision follows the dtype of the record; times, volts and gains are SI.

Modules: `record` (shared record handling, result codes), `oscillatory`, `aperiodic`,
`stops`, `fit` (least squares; its models are `_simulate.modal`'s), `monte_carlo` (the
fused simulate-and-identify kernel), `step_record` (a `StepData` record identified with
the method chosen for it, and several records of one device, for the CLI's `identify`).
"""

from .aperiodic import AperiodicEstimate as AperiodicEstimate
from .aperiodic import _savgol_kernels as _savgol_kernels
from .aperiodic import identify_aperiodic as identify_aperiodic
from .aperiodic import inflection_time_ratio as inflection_time_ratio
from .fit import StepFit as StepFit
from .fit import fit_step_response as fit_step_response
from .fit import scale_factor_from_fit as scale_factor_from_fit
from .monte_carlo import default_chunk_size as default_chunk_size
from .monte_carlo import monte_carlo_oscillatory as monte_carlo_oscillatory
from .oscillatory import OscillatoryEstimate as OscillatoryEstimate
from .oscillatory import _weighted_moments as _weighted_moments
from .oscillatory import identify_oscillatory as identify_oscillatory
from .record import IdentificationResult as IdentificationResult
from .step_record import identify_step_record as identify_step_record
from .step_record import identify_step_records as identify_step_records
from .stops import pickoff_gain_from_stops as pickoff_gain_from_stops
