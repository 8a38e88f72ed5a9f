"""Noise models of inertial sensors and their identification (docs/models.md §4).

Chernodarov, Patrikeev & Ivanov identify the noise model of a sensor error from its sample
autocorrelation: the first-order Gauss-Markov (GM) model by a log-linear rule and the
exponential-cosine model by its first zero and a log-linear rule. This package implements,
one concept per module,

- `record`: record validation and the sample autocorrelation (11), by FFT, with what the
  other modules share (array aliases, the log-parameter clip, `NoiseFitResult`);
- `models`: the noise models (white, GM, exponential-cosine, random walk, their sums) in
  exact discrete state-space form, `simulate_noise` and `model_parameters`;
- `mean_models`: the deterministic terms of a record's mean (a periodic line, the start-up
  transient), each with its `signal(t)`;
- `paper`: the paper's rules (15) and (19)-(21);
- `fit`: beyond the paper, nonlinear least squares on the autocorrelation (optimistix
  Levenberg-Marquardt) and exact maximum likelihood of the discrete-time state-space form
  (a Kalman filter, `accel_jax._kalman.kalman_filter`) with confidence intervals from the
  observed information;
- `selection`: structure selection among white noise, GM, exponential-cosine, random walk
  and their sums by an information criterion, with the residual (standardised innovation)
  autocorrelation and a Ljung-Box test;
- `allan`: the overlapping Allan deviation and its standard slopes, as a cross-check;
  `allan_intervals`: the ADEV with χ² confidence intervals from equivalent degrees of
  freedom (allantools' noise identification and Greenhall EDF); `allan_terms`: the IEEE
  Std 952/1554 noise terms (Q, N, B, K, R) of an ADEV by weighted non-negative least
  squares, with parametric-bootstrap intervals and a rule for which terms the data
  support.
- `export`: an identified accelerometer noise model (`AccelNoiseTerms`) in kalibr's
  imu.yaml, gnss-ins-sim's error dictionary and IEEE 952/1293 units, with the √Δt, √2 and
  60 conversions between continuous densities and per-sample σ.

Models are `eqx.Module`s whose fields are positive array leaves (σ [record unit], τ [s],
α [1/s], β [rad/s], q [unit²/s]); records are 1-D arrays sampled every `sample_interval`
seconds, in any unit (g, m/s², rad/s): the parameters carry the record's unit.

Precision: float64 for maximum likelihood and structure selection (log-likelihoods of
thousands of samples are compared to within a few units; the random walk's diffuse prior
costs six digits); the autocorrelation and the paper's rules follow the record's dtype.
"""

from .allan import AllanCoefficients as AllanCoefficients
from .allan import allan_coefficients as allan_coefficients
from .allan import allan_deviation as allan_deviation
from .allan import allan_variance_of_model as allan_variance_of_model
from .allan_intervals import AllanDeviation as AllanDeviation
from .allan_intervals import allan_deviation_intervals as allan_deviation_intervals
from .allan_terms import AllanTerms as AllanTerms
from .allan_terms import fit_allan_terms as fit_allan_terms
from .analysis import analyse_static_record as analyse_static_record
from .analysis import analysis_to_json as analysis_to_json
from .export import AccelNoiseTerms as AccelNoiseTerms
from .export import density_to_discrete as density_to_discrete
from .export import density_to_one_sided_asd as density_to_one_sided_asd
from .export import density_to_vrw as density_to_vrw
from .export import discrete_to_density as discrete_to_density
from .export import discrete_to_gauss_markov as discrete_to_gauss_markov
from .export import discrete_to_random_walk as discrete_to_random_walk
from .export import gauss_markov_to_discrete as gauss_markov_to_discrete
from .export import kalibr_yaml as kalibr_yaml
from .export import micro_g_to_si as micro_g_to_si
from .export import one_sided_asd_to_density as one_sided_asd_to_density
from .export import random_walk_to_discrete as random_walk_to_discrete
from .export import si_to_micro_g as si_to_micro_g
from .export import to_gnss_ins_sim as to_gnss_ins_sim
from .export import to_ieee as to_ieee
from .export import to_kalibr as to_kalibr
from .export import unit_to_si as unit_to_si
from .export import vrw_to_density as vrw_to_density
from .fit import _DIFFUSE as _DIFFUSE
from .fit import NoiseFit as NoiseFit
from .fit import fit_autocorrelation_least_squares as fit_autocorrelation_least_squares
from .fit import fit_maximum_likelihood as fit_maximum_likelihood
from .fit import innovations as innovations
from .fit import log_likelihood as log_likelihood
from .models import AbstractNoiseModel as AbstractNoiseModel
from .models import ExponentialCosine as ExponentialCosine
from .models import GaussMarkov as GaussMarkov
from .models import NoiseSum as NoiseSum
from .models import RandomWalk as RandomWalk
from .models import WhiteNoise as WhiteNoise
from .models import model_parameters as model_parameters
from .models import simulate_noise as simulate_noise
from .paper import PaperExpCosineFit as PaperExpCosineFit
from .paper import PaperGaussMarkovFit as PaperGaussMarkovFit
from .paper import fit_exp_cosine_paper as fit_exp_cosine_paper
from .paper import fit_gauss_markov_paper as fit_gauss_markov_paper
from .record import NoiseFitResult as NoiseFitResult
from .record import autocorrelation as autocorrelation
from .selection import StructureSelection as StructureSelection
from .selection import initial_model as initial_model
from .selection import select_noise_model as select_noise_model
from .sensor import SensorNoiseSelection as SensorNoiseSelection
from .sensor_screens import detect_non_gaussian as detect_non_gaussian
from .sensor_screens import detect_quantization as detect_quantization
from .sensor_screens import detect_saturation as detect_saturation
from .sensor_screens import detect_spectral_change as detect_spectral_change
from .sensor import select_sensor_noise as select_sensor_noise
from .whiteness import ljung_box as ljung_box

# The top-level names of the noise model's innovations and likelihood (`accel_jax`).
noise_innovations = innovations
noise_log_likelihood = log_likelihood
