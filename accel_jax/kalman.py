"""The linear Kalman filter and smoother, their consistency statistics, and the
single-channel INS test bed on which a wrong sensor-noise model makes the filter diverge
(docs/models.md §4).

    import accel_jax.kalman as ak
    channel = ak.INSChannel(accel_sigma=1e-3, accel_correlation_time=300.0, gyro_sigma=1e-7,
                            gyro_correlation_time=3600.0, velocity_noise=0.1)
"""

# The public names of this namespace (the modules that define them are private).
from ._kalman_ins import EARTH_RADIUS as EARTH_RADIUS
from ._kalman_ins import ConsistencyTrial as ConsistencyTrial
from ._kalman import FilterOutput as FilterOutput
from ._kalman_ins import INSChannel as INSChannel
from ._kalman import LinearGaussianModel as LinearGaussianModel
from ._kalman import SmootherOutput as SmootherOutput
from ._kalman_ins import ins_consistency_trial as ins_consistency_trial
from ._kalman_ins import ins_initial_covariance as ins_initial_covariance
from ._kalman import kalman_filter as kalman_filter
from ._kalman import normalised_estimation_error_squared as normalised_estimation_error_squared
from ._kalman import normalised_innovation_squared as normalised_innovation_squared
from ._kalman import rts_smoother as rts_smoother
from ._kalman import simulate_linear_gaussian as simulate_linear_gaussian
from ._kalman_models import INSNoiseChannel as INSNoiseChannel
from ._kalman_spectral import SmoothedAutocovariance as SmoothedAutocovariance
from ._kalman_spectral import expected_sample_autocovariance as expected_sample_autocovariance
from ._kalman_spectral import smoothed_autocovariance as smoothed_autocovariance
from ._kalman_models import scale_noise_coefficients as scale_noise_coefficients
from ._kalman_online import OnlineIdentification as OnlineIdentification
from ._kalman_online import OnlineRun as OnlineRun
from ._kalman_sensor import SensorErrorModel as SensorErrorModel
from ._kalman_sensor import structure_candidates as structure_candidates
from ._kalman_online import identify_in_flight as identify_in_flight
from ._kalman_sensor import online_channel as online_channel
