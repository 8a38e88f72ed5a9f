"""Sensor noise: models, their identification, the Allan deviation and IEEE terms, the
record screens, and the exports (docs/models.md §4).

The Gauss-Markov and exponential-cosine models of Chernodarov, Patrikeev & Ivanov and their
identification from the sample autocorrelation (the paper's rules, least squares, exact
maximum likelihood through a Kalman filter), structure selection among white, Gauss-Markov,
exponential-cosine, random-walk noise and their sums, the overlapping Allan deviation with
confidence intervals, the IEEE Std 952/1554 terms (Q, N, B, K, R), the static-record
analysis behind `accel-jax noise`, and the conversions to kalibr, gnss-ins-sim and IEEE
units.

Models are `eqx.Module`s whose fields are positive array leaves (σ [record unit], τ [s],
α [1/s], β [rad/s], q [unit²/s]); records are 1-D arrays sampled every `sample_interval`
seconds, in any unit: the parameters carry the record's unit. Precision: float64 for
maximum likelihood and structure selection; the autocorrelation and the paper's rules
follow the record's dtype.

    import accel_jax.noise as an
    model = an.GaussMarkov(sigma=1e-4, correlation_time=50.0)
"""

# The public names of this namespace (the modules that define them are private).
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
from ._noise.analysis import StaticRecordAnalysis as StaticRecordAnalysis
from ._noise.held_out import HeldOutCheck as HeldOutCheck
