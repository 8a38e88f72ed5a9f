"""The `vibration` kind: a table of shaker/tumble tests, its nominal model and its effects.

**Nominal model** (the idealised transfer function the paper's shaker method assumes,
docs/models.md §3): a linear transfer function, bias and scale factor only,

    a_out = a0 + (1 + δ) a_in                                                        [g],

fitted freely to the rows (there is no prior: `NominalDevice` describes the servo loop and
does not enter this kind). With a single input level a_in the scale factor cannot be told
from the bias; δ is then held at 0 and the bias absorbs both (a note says so).

**Effects** (each adds coefficients of the static transfer function, docs/models.md §3 eq. (1),
and is exactly the nominal model when they are zero):

- `k2`, `k3`, `k4`, `k5`: the nonlinearity k_n a3ⁿ, whose time average under vibration
  rectifies (k2 b²/2, 1.5 k3 a b², …);
- `asymmetry`: the scale-factor asymmetry ½ A1 |a3|, which rectifies when the vibration
  crosses zero;
- `cross_coupling`: m31 a3 a1 + m32 a3 a2, which rectifies as ½ m3i b3 bi for in-phase
  sinusoids on the input and a cross axis. Only a table with cross-axis vibration columns
  (`vib_amp_oa`, `vib_amp_pa`, see `accel_jax._data.OPTIONAL_COLUMNS`) can show it: without
  them (or with them all zero) the effect is left out of the candidates and a note says so.

The mean output of every row is the exact expectation of `accel_jax._vibration`
(`design_matrix`: quadrature over the sine phase and the Gaussian random part, exact for the
polynomial terms and for |a3| with a sinusoid). The model is linear in the coefficients, so
that Jacobian is the whole model: a_out = a_in + J θ (θ in ppm). Every candidate and every
cross-validation fold is solved by optimistix least squares (Gauss–Newton, SVD solve) on
that design, all of a table's fits in one vmapped call (`fit`; `fit_coefficients` fits one
table per call and compiles per table size; the tests check the two agree).

**Held out**: cross-validation over rows: leave-one-out for tables of up to `MAX_FOLDS`
rows, else `MAX_FOLDS` folds with a fixed scrambled assignment (a test table is usually
ordered by condition; interleaving by row number would hold out whole conditions, e.g. every
cross-axis row at once). Each row is predicted by the fit that did not see it. The evidence
(2 ln B, BIC scale, noise variance profiled out) is from the fit to all rows.

**Modules.** `entry` (`diagnose_vibration`), `table` (a table read into a
`VibrationTable`, the typed state of `state`), `effects`, `fit` (the vmapped least
squares), `verdict` (the evidence, the lack-of-fit test, the open-world decision, the
refit), `localise` (where the nominal residual lies across the conditions).

Float64 throughout (ppm-level differences of O(1 g) numbers).
"""

from __future__ import annotations

from .effects import COEFFICIENTS as COEFFICIENTS
from .effects import NOMINAL_COEFFICIENTS as NOMINAL_COEFFICIENTS
from .effects import AbstractVibrationEffect as AbstractVibrationEffect
from .effects import Asymmetry as Asymmetry
from .effects import CrossCoupling as CrossCoupling
from .effects import K2 as K2
from .effects import K3 as K3
from .effects import K4 as K4
from .effects import K5 as K5
from .effects import vibration_effects as vibration_effects
from .entry import diagnose_vibration as diagnose_vibration
from .fit import FIT_TOLERANCE as FIT_TOLERANCE
from .table import IDENTIFIABLE as IDENTIFIABLE
from .table import MAX_FOLDS as MAX_FOLDS
from .table import N_PHASE as N_PHASE
from .verdict import LACK_OF_FIT_LEVEL as LACK_OF_FIT_LEVEL
