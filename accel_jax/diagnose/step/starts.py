"""Where the step diagnosis's later fits start (`entry`): at the nominal fit's optimum with
the effect switched off (`nominal_start`: the nominal model exactly, so that a nested fit can
never end below it), and the compliant stops' starts moved to the inelastic clamp's fit
(`contact_from_clamp`, over `CONTACT_GRID`'s stiffness and damping)."""

from __future__ import annotations

import numpy as np

from .layout import W
from .state import StepFit, StepRecord


CONTACT_GRID = ((0.0, 0.0), (-1.15, -0.73), (1.15, 0.8))
"""(z₂, z₃) of the compliant-stop starts from the clamp's fit: κ ≈ 300, 30, 3000 with
ζ_c ≈ 0.3, 0.1, 1 (`effects.StopContact`): a soft contact lets the pendulum well past the
clamp's stop and bounces, a stiff one is near the clamp."""


def contact_from_clamp(fit: StepFit, rec: StepRecord, starts: np.ndarray) -> np.ndarray:
    """Starts of the compliant stops (`starts`, one per contact candidate) moved to the
    clamp's fit: its device and nuisances, its two stops (at the output offset c ± h) as
    the clearances; the contact's stiffness and damping as they were."""
    out = np.array(starts, dtype=np.float64)
    w = np.asarray(fit.w_trained, dtype=np.float64)
    half, scale = float(rec.host.half), float(rec.host.scale)
    z_stop, z_offset = w[W.EFFECT][:2]
    stop = half / abs(z_stop) if abs(z_stop) > 1e-9 else np.inf
    offset = 0.1 * scale * z_offset
    out[..., W.BEFORE_EFFECT] = w[W.BEFORE_EFFECT]
    out[..., W.INPUT] = w[W.INPUT]
    for k, edge in ((0, offset + stop), (1, stop - offset)):
        out[..., W.EFFECT.start + k] = half / edge if np.isfinite(edge) and edge > 0 else 0.0
    return out


def nominal_start(w_nominal) -> np.ndarray:
    """A start at the nominal fit's optimum with the effect's slot at 0: the nominal model
    exactly, for every effect (each is the identity at z = 0)."""
    w = np.array(w_nominal, dtype=np.float64)
    w[W.EFFECT] = 0.0
    return w
