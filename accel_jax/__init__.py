"""accel_jax: a JAX differentiable model of servo (pendulum compensating) accelerometers.

The public API is re-exported here; modules starting with an underscore are private.
The library never changes JAX's global configuration: enable float64 yourself
(`jax.config.update("jax_enable_x64", True)`) where a computation needs it — the studies do.
"""

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
    inflection_time_ratio as inflection_time_ratio,
)
from ._identify import (
    pickoff_gain_from_stops as pickoff_gain_from_stops,
)
from ._identify import (
    scale_factor_from_fit as scale_factor_from_fit,
)
from ._identify import (
    second_order_step as second_order_step,
)
from ._io import (
    provenance as provenance,
)
from ._io import (
    save_figure_atomic as save_figure_atomic,
)
from ._io import (
    write_json_atomic as write_json_atomic,
)
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
from ._progress import show_progress as show_progress
from ._servo import (
    aperiodic_time_constants as aperiodic_time_constants,
)
from ._servo import (
    closed_loop_test_gain as closed_loop_test_gain,
)
from ._servo import (
    damping_ratio as damping_ratio,
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
from ._sweep import device_count as device_count
from ._sweep import sweep as sweep

__version__ = "0.1.0"
