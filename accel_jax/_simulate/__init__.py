"""Time-domain simulation of the closed-loop servo accelerometer (docs/models.md §1): every
simulator of the loop lives here, once.

- `state_space` (`state_space`, `discretise`, `equilibrium_state`): the loop's matrices,
  their exact zero-order-hold discretisation, the settled state;
- `loop`: input handling and the scaled internal form shared by the simulators;
- `linear` (`simulate_linear`): the linear loop, exact ZOH, `lax.scan`;
- `blocked` (`fast_step_response`): the same record for constant inputs from a settled
  device, by block powers of the affine ZOH map (no long scan);
- `nonlinear` (`simulate_nonlinear`): the loop with the mechanical stops, diffrax;
- `response` (`step_response`): the identification record by either simulator;
- `modal` (`second_order_step`, `_third_order_step`): the normalised loop's closed-form
  and companion-form step responses the identification fits evaluate;


The ideal lags (T_dm = 0, T_f = 0) are singular limits of the lagged model: there the lag
states become dummies and the algebraic values are used instead. To make the derivative
with respect to T_dm (T_f) at exactly 0 the one-sided derivative of the lagged model, the
ideal branch keeps the first-order singular-perturbation terms in T_dm (T_f); they are
zero in value at T = 0 and only carry the derivative.
"""

from .blocked import fast_step_response as fast_step_response
from .linear import simulate_linear as simulate_linear
from .modal import second_order_step as second_order_step
from .nonlinear import simulate_nonlinear as simulate_nonlinear
from .response import step_response as step_response
from .state_space import discretise as discretise
from .state_space import equilibrium_state as equilibrium_state
from .state_space import state_space as state_space
