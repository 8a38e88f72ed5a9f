"""accel_jax: a JAX differentiable model of servo (pendulum compensating) accelerometers.

The device models, the simulation, the scale-factor identification and the sensing-element
estimation are re-exported here; three namespaces group the rest — `accel_jax.noise`
(noise models, their identification, Allan deviation, exports), `accel_jax.vibration`
(vibration error, compensation, coefficient fitting, tolerance limits) and
`accel_jax.kalman` (the Kalman filter and the INS test bed) — beside `accel_jax.diagnose`
(the sim-to-real diagnosis) and `accel_jax.report` (text, figures, file writing,
provenance, the study plumbing). Modules starting with an underscore are private.

The library never changes JAX's configuration: enable float64 yourself
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

from . import kalman as kalman
from . import noise as noise
from . import vibration as vibration
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
from ._data import with_input_delay as with_input_delay
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
from ._identify.step_result import StepIdentification as StepIdentification
from ._identify.step_result import StopRecordGain as StopRecordGain
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

__version__ = "0.1.0"


# Moved in 0.2 (CHANGELOG.md): the identify command's text and figure are presentation,
# now under `accel_jax.report` (read lazily here, so that importing the package does not
# import its presentation layer); the noise, vibration/tolerance and Kalman names are
# grouped under `accel_jax.noise`, `accel_jax.vibration` and `accel_jax.kalman`.
from ._deprecated import moved_names as _moved_names

__getattr__ = _moved_names(
    __name__,
    {
        "identification_summary": "accel_jax.report",
        "identification_figure": "accel_jax.report",
        "AbstractNoiseModel": "accel_jax.noise",
        "AccelNoiseTerms": "accel_jax.noise",
        "AllanCoefficients": "accel_jax.noise",
        "AllanDeviation": "accel_jax.noise",
        "AllanTerms": "accel_jax.noise",
        "ExponentialCosine": "accel_jax.noise",
        "GaussMarkov": "accel_jax.noise",
        "NoiseFit": "accel_jax.noise",
        "NoiseFitResult": "accel_jax.noise",
        "NoiseSum": "accel_jax.noise",
        "PaperExpCosineFit": "accel_jax.noise",
        "PaperGaussMarkovFit": "accel_jax.noise",
        "RandomWalk": "accel_jax.noise",
        "SensorNoiseSelection": "accel_jax.noise",
        "StructureSelection": "accel_jax.noise",
        "WhiteNoise": "accel_jax.noise",
        "allan_coefficients": "accel_jax.noise",
        "allan_deviation": "accel_jax.noise",
        "allan_deviation_intervals": "accel_jax.noise",
        "allan_variance_of_model": "accel_jax.noise",
        "analyse_static_record": "accel_jax.noise",
        "analysis_to_json": "accel_jax.noise",
        "autocorrelation": "accel_jax.noise",
        "density_to_discrete": "accel_jax.noise",
        "density_to_one_sided_asd": "accel_jax.noise",
        "density_to_vrw": "accel_jax.noise",
        "detect_non_gaussian": "accel_jax.noise",
        "detect_quantization": "accel_jax.noise",
        "detect_saturation": "accel_jax.noise",
        "detect_spectral_change": "accel_jax.noise",
        "discrete_to_density": "accel_jax.noise",
        "discrete_to_gauss_markov": "accel_jax.noise",
        "discrete_to_random_walk": "accel_jax.noise",
        "fit_allan_terms": "accel_jax.noise",
        "fit_autocorrelation_least_squares": "accel_jax.noise",
        "fit_exp_cosine_paper": "accel_jax.noise",
        "fit_gauss_markov_paper": "accel_jax.noise",
        "fit_maximum_likelihood": "accel_jax.noise",
        "gauss_markov_to_discrete": "accel_jax.noise",
        "initial_model": "accel_jax.noise",
        "kalibr_yaml": "accel_jax.noise",
        "ljung_box": "accel_jax.noise",
        "micro_g_to_si": "accel_jax.noise",
        "model_parameters": "accel_jax.noise",
        "noise_innovations": "accel_jax.noise",
        "noise_log_likelihood": "accel_jax.noise",
        "one_sided_asd_to_density": "accel_jax.noise",
        "random_walk_to_discrete": "accel_jax.noise",
        "select_noise_model": "accel_jax.noise",
        "select_sensor_noise": "accel_jax.noise",
        "si_to_micro_g": "accel_jax.noise",
        "simulate_noise": "accel_jax.noise",
        "to_gnss_ins_sim": "accel_jax.noise",
        "to_ieee": "accel_jax.noise",
        "to_kalibr": "accel_jax.noise",
        "unit_to_si": "accel_jax.noise",
        "vrw_to_density": "accel_jax.noise",
        "EARTH_RADIUS": "accel_jax.kalman",
        "ConsistencyTrial": "accel_jax.kalman",
        "FilterOutput": "accel_jax.kalman",
        "INSChannel": "accel_jax.kalman",
        "LinearGaussianModel": "accel_jax.kalman",
        "SmootherOutput": "accel_jax.kalman",
        "ins_consistency_trial": "accel_jax.kalman",
        "ins_initial_covariance": "accel_jax.kalman",
        "kalman_filter": "accel_jax.kalman",
        "normalised_estimation_error_squared": "accel_jax.kalman",
        "normalised_innovation_squared": "accel_jax.kalman",
        "rts_smoother": "accel_jax.kalman",
        "scale_noise_coefficients": "accel_jax.kalman",
        "simulate_linear_gaussian": "accel_jax.kalman",
        "ASYMMETRY_RANDOM_FACTOR": "accel_jax.vibration",
        "ASYMMETRY_SINE_FACTOR": "accel_jax.vibration",
        "FIT_PARAMETERS": "accel_jax.vibration",
        "TABLE_COLUMNS": "accel_jax.vibration",
        "BandSpectrum": "accel_jax.vibration",
        "CoefficientFit": "accel_jax.vibration",
        "CompensationSteps": "accel_jax.vibration",
        "Identifiability": "accel_jax.vibration",
        "ShakerEstimate": "accel_jax.vibration",
        "VibrationEnvironment": "accel_jax.vibration",
        "compensate_in_flight": "accel_jax.vibration",
        "design_matrix": "accel_jax.vibration",
        "fit_coefficients": "accel_jax.vibration",
        "greedy_test_plan": "accel_jax.vibration",
        "identifiability": "accel_jax.vibration",
        "mean_abs_gauss": "accel_jax.vibration",
        "mean_abs_input": "accel_jax.vibration",
        "mean_abs_sine": "accel_jax.vibration",
        "mean_indicated_acceleration": "accel_jax.vibration",
        "paper_deterministic_error": "accel_jax.vibration",
        "paper_random_error": "accel_jax.vibration",
        "paper_vibration_error": "accel_jax.vibration",
        "predict_table": "accel_jax.vibration",
        "random_rms": "accel_jax.vibration",
        "read_band_spectrum": "accel_jax.vibration",
        "read_vibration_table": "accel_jax.vibration",
        "shaker_vibration_error": "accel_jax.vibration",
        "synthesize_vibration": "accel_jax.vibration",
        "time_domain_vibration_error": "accel_jax.vibration",
        "validate_vibration_table": "accel_jax.vibration",
        "vibration_error": "accel_jax.vibration",
        "write_vibration_table": "accel_jax.vibration",
        "AKS05_RANGES_PPM": "accel_jax.vibration",
        "PAPER_SHARES": "accel_jax.vibration",
        "TOLERANCED": "accel_jax.vibration",
        "ToleranceScenario": "accel_jax.vibration",
        "cyclone4": "accel_jax.vibration",
        "error_contributions": "accel_jax.vibration",
        "gradient_limits": "accel_jax.vibration",
        "paper_limits": "accel_jax.vibration",
        "sample_batch": "accel_jax.vibration",
        "sensitivities": "accel_jax.vibration",
        "sensitivity_profile": "accel_jax.vibration",
        "tactical_missile": "accel_jax.vibration",
        "tolerance_table": "accel_jax.vibration",
        "unit_vibration_error": "accel_jax.vibration",
        "within_rms_region": "accel_jax.vibration",
    },
)
del _moved_names
