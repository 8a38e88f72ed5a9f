"""accel_jax: a JAX differentiable model of servo (pendulum compensating) accelerometers.

The public API (models, algorithms, results) is re-exported here; modules starting with
an underscore are private; file writing, provenance and the study plumbing are under
`accel_jax.report`. The library never changes JAX's configuration: enable float64 yourself
(`jax.config.update("jax_enable_x64", True)`) where a computation needs it — the studies
do. The one process-level setting made on import is the XLA:CPU deadlock workaround below
(`ACCEL_JAX_XLA_WORKAROUND=off` opts out). The code's map: docs/architecture.md.
"""

import os as _os

# Whether the user chose XLA's C++ log level before JAX (imported below) sets its default:
# the command line keeps XLA's log lines off the terminal only when they did not
# (`accel_jax._runtime.quiet_xla_logs`). Reading it changes nothing.
_USER_SET_XLA_LOG_LEVEL = "TF_CPP_MIN_LOG_LEVEL" in _os.environ
del _os

# The one process-level setting made on import: jaxlib 0.10.2's XLA:CPU scheduler deadlock
# workaround, added to XLA_FLAGS before JAX starts its backend unless the user set the
# option or opted out (ACCEL_JAX_XLA_WORKAROUND=off). It changes no result; see _runtime.py.
from ._runtime import apply_at_import as _apply_at_import

_XLA_WORKAROUND = _apply_at_import()
del _apply_at_import

from ._data import DataError as DataError
from ._data import Dataset as Dataset
from ._data import NoiseData as NoiseData
from ._data import NominalDevice as NominalDevice
from ._data import StepData as StepData
from ._data import VibrationData as VibrationData
from ._data import infer_kind as infer_kind
from ._data import parse_csv as parse_csv
from ._data import parse_params_toml as parse_params_toml
from ._data import read_csv as read_csv
from ._data import read_params_toml as read_params_toml
from ._data import write_csv as write_csv
from ._identify import (
    AperiodicEstimate as AperiodicEstimate,
)
from ._identify import (
    IdentificationResult as IdentificationResult,
)
from ._identify import (
    OscillatoryEstimate as OscillatoryEstimate,
)
from ._identify import (
    StepFit as StepFit,
)
from ._identify import (
    fit_step_response as fit_step_response,
)
from ._identify import (
    identify_aperiodic as identify_aperiodic,
)
from ._identify import (
    identify_oscillatory as identify_oscillatory,
)
from ._identify import (
    identify_step_record as identify_step_record,
)
from ._identify import (
    identify_step_records as identify_step_records,
)
from ._identify import (
    inflection_time_ratio as inflection_time_ratio,
)
from ._identify import (
    monte_carlo_oscillatory as monte_carlo_oscillatory,
)
from ._identify import (
    pickoff_gain_from_stops as pickoff_gain_from_stops,
)
from ._identify import (
    scale_factor_from_fit as scale_factor_from_fit,
)
from ._kalman import EARTH_RADIUS as EARTH_RADIUS
from ._kalman import ConsistencyTrial as ConsistencyTrial
from ._kalman import FilterOutput as FilterOutput
from ._kalman import INSChannel as INSChannel
from ._kalman import LinearGaussianModel as LinearGaussianModel
from ._kalman import SmootherOutput as SmootherOutput
from ._kalman import ins_consistency_trial as ins_consistency_trial
from ._kalman import ins_initial_covariance as ins_initial_covariance
from ._kalman import kalman_filter as kalman_filter
from ._kalman import normalised_estimation_error_squared as normalised_estimation_error_squared
from ._kalman import normalised_innovation_squared as normalised_innovation_squared
from ._kalman import rts_smoother as rts_smoother
from ._kalman import scale_noise_coefficients as scale_noise_coefficients
from ._kalman import simulate_linear_gaussian as simulate_linear_gaussian
from ._ml_estimate import AbstractDisturbance as AbstractDisturbance
from ._ml_estimate import CompensatedEstimate as CompensatedEstimate
from ._ml_estimate import ExponentialDisturbance as ExponentialDisturbance
from ._ml_estimate import GaussMarkovDisturbance as GaussMarkovDisturbance
from ._ml_estimate import HarmonicDisturbance as HarmonicDisturbance
from ._ml_estimate import MLEstimate as MLEstimate
from ._ml_estimate import NonlinearFit as NonlinearFit
from ._ml_estimate import WhiteDisturbance as WhiteDisturbance
from ._ml_estimate import column_sum_estimate as column_sum_estimate
from ._ml_estimate import compensate_linearisation as compensate_linearisation
from ._ml_estimate import error_covariance as error_covariance
from ._ml_estimate import fit_sensing_element as fit_sensing_element
from ._ml_estimate import linearisation_error as linearisation_error
from ._ml_estimate import linearisation_residual as linearisation_residual
from ._ml_estimate import ml_estimate as ml_estimate
from ._ml_estimate import state_basis as state_basis
from ._noise import AbstractNoiseModel as AbstractNoiseModel
from ._noise import AccelNoiseTerms as AccelNoiseTerms
from ._noise import AllanCoefficients as AllanCoefficients
from ._noise import AllanDeviation as AllanDeviation
from ._noise import AllanTerms as AllanTerms
from ._noise import ExponentialCosine as ExponentialCosine
from ._noise import GaussMarkov as GaussMarkov
from ._noise import NoiseFit as NoiseFit
from ._noise import NoiseFitResult as NoiseFitResult
from ._noise import NoiseSum as NoiseSum
from ._noise import PaperExpCosineFit as PaperExpCosineFit
from ._noise import PaperGaussMarkovFit as PaperGaussMarkovFit
from ._noise import RandomWalk as RandomWalk
from ._noise import SensorNoiseSelection as SensorNoiseSelection
from ._noise import StructureSelection as StructureSelection
from ._noise import WhiteNoise as WhiteNoise
from ._noise import allan_coefficients as allan_coefficients
from ._noise import allan_deviation as allan_deviation
from ._noise import allan_deviation_intervals as allan_deviation_intervals
from ._noise import allan_variance_of_model as allan_variance_of_model
from ._noise import analyse_static_record as analyse_static_record
from ._noise import analysis_to_json as analysis_to_json
from ._noise import autocorrelation as autocorrelation
from ._noise import density_to_discrete as density_to_discrete
from ._noise import density_to_one_sided_asd as density_to_one_sided_asd
from ._noise import density_to_vrw as density_to_vrw
from ._noise import detect_non_gaussian as detect_non_gaussian
from ._noise import detect_quantization as detect_quantization
from ._noise import detect_saturation as detect_saturation
from ._noise import detect_spectral_change as detect_spectral_change
from ._noise import discrete_to_density as discrete_to_density
from ._noise import discrete_to_gauss_markov as discrete_to_gauss_markov
from ._noise import discrete_to_random_walk as discrete_to_random_walk
from ._noise import fit_allan_terms as fit_allan_terms
from ._noise import fit_autocorrelation_least_squares as fit_autocorrelation_least_squares
from ._noise import fit_exp_cosine_paper as fit_exp_cosine_paper
from ._noise import fit_gauss_markov_paper as fit_gauss_markov_paper
from ._noise import fit_maximum_likelihood as fit_maximum_likelihood
from ._noise import gauss_markov_to_discrete as gauss_markov_to_discrete
from ._noise import initial_model as initial_model
from ._noise import kalibr_yaml as kalibr_yaml
from ._noise import ljung_box as ljung_box
from ._noise import micro_g_to_si as micro_g_to_si
from ._noise import model_parameters as model_parameters
from ._noise import noise_innovations as noise_innovations
from ._noise import noise_log_likelihood as noise_log_likelihood
from ._noise import one_sided_asd_to_density as one_sided_asd_to_density
from ._noise import random_walk_to_discrete as random_walk_to_discrete
from ._noise import select_noise_model as select_noise_model
from ._noise import select_sensor_noise as select_sensor_noise
from ._noise import si_to_micro_g as si_to_micro_g
from ._noise import simulate_noise as simulate_noise
from ._noise import to_gnss_ins_sim as to_gnss_ins_sim
from ._noise import to_ieee as to_ieee
from ._noise import to_kalibr as to_kalibr
from ._noise import unit_to_si as unit_to_si
from ._noise import vrw_to_density as vrw_to_density
from ._params import (
    APERIODIC_DAMPING as APERIODIC_DAMPING,
)
from ._params import (
    PAPER_GAMMA as PAPER_GAMMA,
)
from ._params import (
    REFERENCE_VALUES as REFERENCE_VALUES,
)
from ._params import (
    ServoParams as ServoParams,
)
from ._pendulum import SensingElement as SensingElement
from ._pendulum import SensingElementSolution as SensingElementSolution
from ._pendulum import amplitude_frequency as amplitude_frequency
from ._pendulum import cubic_approximation as cubic_approximation
from ._pendulum import initial_state as initial_state
from ._pendulum import linear_solution as linear_solution
from ._pendulum import record_mask as record_mask
from ._pendulum import sample_sensing_element as sample_sensing_element
from ._pendulum import sample_times as sample_times
from ._pendulum import solve_sensing_element as solve_sensing_element
from ._servo import (
    aperiodic_time_constants as aperiodic_time_constants,
)
from ._servo import (
    closed_loop_test_gain as closed_loop_test_gain,
)
from ._servo import (
    damping_for_ratio as damping_for_ratio,
)
from ._servo import (
    damping_ratio as damping_ratio,
)
from ._servo import (
    dominant_pole_scale_factor as dominant_pole_scale_factor,
)
from ._servo import (
    feedback_stiffness as feedback_stiffness,
)
from ._servo import (
    loop_stiffness as loop_stiffness,
)
from ._servo import (
    natural_frequency as natural_frequency,
)
from ._servo import (
    relative_error_percent as relative_error_percent,
)
from ._servo import (
    scale_factor as scale_factor,
)
from ._servo import (
    scale_factor_from_time_constant as scale_factor_from_time_constant,
)
from ._servo import (
    shape_factor as shape_factor,
)
from ._servo import (
    time_constant as time_constant,
)
from ._servo import (
    transfer_function as transfer_function,
)
from ._servo import (
    transfer_function_test_signal as transfer_function_test_signal,
)
from ._simulate import (
    discretise as discretise,
)
from ._simulate import (
    equilibrium_state as equilibrium_state,
)
from ._simulate import (
    fast_step_response as fast_step_response,
)
from ._simulate import (
    second_order_step as second_order_step,
)
from ._simulate import (
    simulate_linear as simulate_linear,
)
from ._simulate import (
    simulate_nonlinear as simulate_nonlinear,
)
from ._simulate import (
    state_space as state_space,
)
from ._simulate import (
    step_response as step_response,
)
from ._static import COEFFICIENT_UNITS as COEFFICIENT_UNITS
from ._static import COEFFICIENTS as COEFFICIENTS
from ._static import MILLI_G as MILLI_G
from ._static import PASSPORTS as PASSPORTS
from ._static import PPM as PPM
from ._static import PPM_UNITS as PPM_UNITS
from ._static import STANDARD_GRAVITY as STANDARD_GRAVITY
from ._static import StaticTransferFunction as StaticTransferFunction
from ._static import basic_error as basic_error
from ._static import g_to_si as g_to_si
from ._static import indicated_acceleration as indicated_acceleration
from ._static import si_to_g as si_to_g
from ._static import to_ppm as to_ppm
from ._sweep import device_count as device_count
from ._sweep import sweep as sweep
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

__version__ = "0.1.0"


# Moved in 0.2 (CHANGELOG.md): the identify command's text and figure are presentation,
# now under `accel_jax.report` (read lazily here, so that importing the package does not
# import its presentation layer).
from ._deprecated import moved_names as _moved_names

__getattr__ = _moved_names(
    __name__,
    {
        "identification_summary": "accel_jax.report",
        "identification_figure": "accel_jax.report",
    },
)
del _moved_names
