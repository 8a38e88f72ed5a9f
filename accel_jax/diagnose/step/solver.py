"""The step fits' solvers: `MinimumEnding` (a fit ended once its result would count as
converged), `StallEnding` (for dear steps: a Levenberg–Marquardt fit ended as at its step
limit once it has stalled) and its thresholds, which live with the minimiser
variant in `accel_jax._solvers` (the module describes both)."""

from ..._solvers import STALL_ABSOLUTE as STALL_ABSOLUTE
from ..._solvers import STALL_RELATIVE as STALL_RELATIVE
from ..._solvers import STALL_WINDOW as STALL_WINDOW
from ..._solvers import MinimumEnding as MinimumEnding
from ..._solvers import StallEnding as StallEnding
