"""Vibration error of a navigation accelerometer (docs/models.md §3): exact expectation,
the paper's closed forms (3)-(5), (19), (20), a time-domain Monte Carlo check, the shaker
estimator (16), the in-flight compensation algorithm (17)-(20) and coefficient fitting from
a table of vibration tests.

The vibration error is the mean indicated acceleration under vibration minus the indicated
acceleration without it, δ_V = E[a_F(a + v)] − a_F(a), for the static transfer function of
`accel_jax._static` (in g). Vibration: a sinusoid of one frequency on each axis (amplitude,
phase) plus zero-mean stationary Gaussian random vibration (RMS per axis, correlation
between axes; band PSDs with the η(f) factors of the paper's Table 1 via `random_rms`).

Precision: vibration errors are ppm-level differences of O(1 g) numbers: evaluate in
float64 (float32 leaves ~0.1 ppm of rounding per evaluation and more after the subtraction).
The functions keep the caller's dtype and do not change JAX's settings.

Modules:

- `environment`: `VibrationEnvironment`, `BandSpectrum`, `random_rms`, `AXES`;
- `expectation`: the exact expectation — `mean_abs_sine`, `mean_abs_gauss`,
  `mean_abs_input`, `mean_indicated_acceleration`, `vibration_error`;
- `paper`: the paper's closed forms — `paper_deterministic_error` (19),
  `paper_random_error` (20), `paper_vibration_error` (3), `ASYMMETRY_SINE_FACTOR`,
  `ASYMMETRY_RANDOM_FACTOR`;
- `time_domain`: the Monte Carlo check — `synthesize_vibration`,
  `time_domain_vibration_error`;
- `shaker`: the shaker estimator (16) — `ShakerEstimate`, `shaker_vibration_error`;
- `compensation`: in-flight compensation (17)-(20) — `CompensationSteps`,
  `compensate_in_flight`;
- `table`: test tables — `TABLE_COLUMNS`, `validate_vibration_table`,
  `read_vibration_table`, `write_vibration_table` (CSV through `accel_jax._data`) — and
  band PSDs, `read_band_spectrum`;
- `fitting`: `predict_table`, `design_matrix`, `Identifiability`, `identifiability`,
  `CoefficientFit`, `fit_coefficients`, `FIT_PARAMETERS`, `PPM_SCALE`.
"""

from .compensation import CompensationSteps as CompensationSteps
from .compensation import compensate_in_flight as compensate_in_flight
from .environment import AXES as AXES
from .environment import BandSpectrum as BandSpectrum
from .environment import VibrationEnvironment as VibrationEnvironment
from .environment import random_rms as random_rms
from .expectation import mean_abs_gauss as mean_abs_gauss
from .expectation import mean_abs_input as mean_abs_input
from .expectation import mean_abs_sine as mean_abs_sine
from .expectation import mean_indicated_acceleration as mean_indicated_acceleration
from .expectation import vibration_error as vibration_error
from .fitting import FIT_PARAMETERS as FIT_PARAMETERS
from .fitting import PPM_SCALE as PPM_SCALE
from .fitting import CoefficientFit as CoefficientFit
from .fitting import Identifiability as Identifiability
from .fitting import design_matrix as design_matrix
from .fitting import fit_coefficients as fit_coefficients
from .fitting import greedy_test_plan as greedy_test_plan
from .fitting import identifiability as identifiability
from .fitting import predict_table as predict_table
from .paper import ASYMMETRY_RANDOM_FACTOR as ASYMMETRY_RANDOM_FACTOR
from .paper import ASYMMETRY_SINE_FACTOR as ASYMMETRY_SINE_FACTOR
from .paper import paper_deterministic_error as paper_deterministic_error
from .paper import paper_random_error as paper_random_error
from .paper import paper_vibration_error as paper_vibration_error
from .shaker import ShakerEstimate as ShakerEstimate
from .shaker import shaker_vibration_error as shaker_vibration_error
from .table import TABLE_COLUMNS as TABLE_COLUMNS
from .table import read_band_spectrum as read_band_spectrum
from .table import read_vibration_table as read_vibration_table
from .table import validate_vibration_table as validate_vibration_table
from .table import write_vibration_table as write_vibration_table
from .time_domain import synthesize_vibration as synthesize_vibration
from .time_domain import time_domain_vibration_error as time_domain_vibration_error
