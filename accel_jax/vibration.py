"""Vibration error of a navigation accelerometer, its shaker test and in-flight
compensation, coefficient fitting from vibration tables, and the tolerance limits on the
static transfer-function coefficients (docs/models.md §3).

The vibration error is the mean indicated acceleration under vibration minus the indicated
acceleration without it, δ_V = E[a_F(a + v)] − a_F(a), for the static transfer function
(`accel_jax.StaticTransferFunction`, in g). Precision: vibration errors are ppm-level
differences of O(1 g) numbers: evaluate in float64; the functions keep the caller's dtype
and do not change JAX's settings.

    import accel_jax.vibration as av
    env = av.VibrationEnvironment(sine_amplitude=[2.0, 0.0, 0.0], sine_frequency=30.0)
"""

# The public names of this namespace (the modules that define them are private).
from ._tolerance import AKS05_RANGES_PPM as AKS05_RANGES_PPM
from ._tolerance import PAPER_SHARES as PAPER_SHARES
from ._tolerance import TOLERANCED as TOLERANCED
from ._tolerance import ToleranceScenario as ToleranceScenario
from ._tolerance import cyclone4 as cyclone4
from ._tolerance import error_contributions as error_contributions
from ._tolerance import gradient_limits as gradient_limits
from ._tolerance import paper_limits as paper_limits
from ._tolerance import sample_batch as sample_batch
from ._tolerance import sensitivities as sensitivities
from ._tolerance import sensitivity_profile as sensitivity_profile
from ._tolerance import tactical_missile as tactical_missile
from ._tolerance import tolerance_table as tolerance_table
from ._tolerance import unit_vibration_error as unit_vibration_error
from ._tolerance import within_rms_region as within_rms_region
from ._vibration import ASYMMETRY_RANDOM_FACTOR as ASYMMETRY_RANDOM_FACTOR
from ._vibration import ASYMMETRY_SINE_FACTOR as ASYMMETRY_SINE_FACTOR
from ._vibration import FIT_PARAMETERS as FIT_PARAMETERS
from ._vibration import TABLE_COLUMNS as TABLE_COLUMNS
from ._vibration import BandSpectrum as BandSpectrum
from ._vibration import CoefficientFit as CoefficientFit
from ._vibration import CompensationSteps as CompensationSteps
from ._vibration import Identifiability as Identifiability
from ._vibration import ShakerEstimate as ShakerEstimate
from ._vibration import VibrationEnvironment as VibrationEnvironment
from ._vibration import compensate_in_flight as compensate_in_flight
from ._vibration import design_matrix as design_matrix
from ._vibration import fit_coefficients as fit_coefficients
from ._vibration import greedy_test_plan as greedy_test_plan
from ._vibration import identifiability as identifiability
from ._vibration import mean_abs_gauss as mean_abs_gauss
from ._vibration import mean_abs_input as mean_abs_input
from ._vibration import mean_abs_sine as mean_abs_sine
from ._vibration import mean_indicated_acceleration as mean_indicated_acceleration
from ._vibration import paper_deterministic_error as paper_deterministic_error
from ._vibration import paper_random_error as paper_random_error
from ._vibration import paper_vibration_error as paper_vibration_error
from ._vibration import predict_table as predict_table
from ._vibration import random_rms as random_rms
from ._vibration import read_band_spectrum as read_band_spectrum
from ._vibration import read_vibration_table as read_vibration_table
from ._vibration import shaker_vibration_error as shaker_vibration_error
from ._vibration import synthesize_vibration as synthesize_vibration
from ._vibration import time_domain_vibration_error as time_domain_vibration_error
from ._vibration import validate_vibration_table as validate_vibration_table
from ._vibration import vibration_error as vibration_error
from ._vibration import write_vibration_table as write_vibration_table
