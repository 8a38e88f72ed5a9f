"""accel_jax: a JAX differentiable model of servo (pendulum compensating) accelerometers.

The public API is re-exported here; modules starting with an underscore are private.
The library never changes JAX's global configuration: enable float64 yourself
(`jax.config.update("jax_enable_x64", True)`) where a computation needs it — the studies do.
"""

from ._params import (
    APERIODIC_DAMPING as APERIODIC_DAMPING,
    PAPER_GAMMA as PAPER_GAMMA,
    REFERENCE_VALUES as REFERENCE_VALUES,
    ServoParams as ServoParams,
)
from ._servo import (
    aperiodic_time_constants as aperiodic_time_constants,
    closed_loop_test_gain as closed_loop_test_gain,
    damping_ratio as damping_ratio,
    feedback_stiffness as feedback_stiffness,
    loop_stiffness as loop_stiffness,
    natural_frequency as natural_frequency,
    relative_error_percent as relative_error_percent,
    scale_factor as scale_factor,
    scale_factor_from_time_constant as scale_factor_from_time_constant,
    shape_factor as shape_factor,
    time_constant as time_constant,
    transfer_function as transfer_function,
    transfer_function_test_signal as transfer_function_test_signal,
)

from ._io import (
    provenance as provenance,
    save_figure_atomic as save_figure_atomic,
    write_json_atomic as write_json_atomic,
)
from ._sweep import device_count as device_count, sweep as sweep

__version__ = "0.1.0"
