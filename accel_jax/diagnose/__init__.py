"""Sim-to-real diagnosis (SPEC.md §5): where the gap between a measured record and the
nominal model lies, which unmodelled effect causes it, and how far it shrinks once that
effect is added.

    from accel_jax._data import read_csv
    from accel_jax.diagnose import diagnose
    data = read_csv("record.csv")               # kind inferred from the columns
    result = diagnose(data)                      # the reference device, ±5 % prior
    print(result.summary()); result.to_dict()

Kinds: `step` (`step.py`), `vibration` (`vibration.py`) and `noise` (`noise.py`). A kind
module provides its nominal model, an effect base class with hooks, the effects registered
with `register_effect`, and a `diagnose_<kind>(datasets, nominal)` listed in `_KINDS`.
"""

from __future__ import annotations

from .._data import DataError, Dataset, NominalDevice
from .base import (
    INDISTINCT as INDISTINCT,
)
from .base import (
    SIGNIFICANCE as SIGNIFICANCE,
)
from .base import (
    AbstractEffect as AbstractEffect,
)
from .base import (
    CandidateFit as CandidateFit,
)
from .base import (
    DiagnosisResult as DiagnosisResult,
)
from .base import (
    effect_library as effect_library,
)
from .base import (
    held_out_gap as held_out_gap,
)
from .base import (
    ljung_box as ljung_box,
)
from .base import (
    rank_candidates as rank_candidates,
)
from .base import (
    register_effect as register_effect,
)
from .noise import NoiseEffect as NoiseEffect
from .noise import diagnose_noise as diagnose_noise
from .step import StepEffect as StepEffect
from .step import diagnose_step as diagnose_step
from .vibration import VibrationEffect as VibrationEffect
from .vibration import diagnose_vibration as diagnose_vibration

_KINDS = {"step": diagnose_step, "vibration": diagnose_vibration, "noise": diagnose_noise}

EFFECT_NAMES: dict[str, tuple[str, ...]] = {
    "step": (
        "torquer_lag",
        "output_filter",
        "stop_saturation",
        "disturbance_drift",
        "colored_noise",
    ),
    "vibration": ("k2", "k3", "k4", "k5", "asymmetry", "cross_coupling"),
    "noise": ("gauss_markov", "exp_cosine", "random_walk"),
}
"""The named effect library of each kind (SPEC.md §5)."""


def diagnose_many(
    datasets: list[Dataset], nominal: NominalDevice | None = None
) -> list[DiagnosisResult]:
    """Diagnose several records (same kind) against one nominal device; records of one
    length are fitted as one batch (one compilation). See `diagnose`."""
    if not datasets:
        return []
    kinds = {d.kind for d in datasets}
    if len(kinds) != 1:
        raise ValueError(f"diagnose_many needs records of one kind, got {sorted(kinds)}.")
    kind = kinds.pop()
    if kind not in _KINDS:
        raise DataError(
            f"the {kind!r} diagnosis is not available yet (its effect library "
            f"{list(EFFECT_NAMES[kind])} is still to be added); available: {sorted(_KINDS)}."
        )
    nominal = NominalDevice.reference() if nominal is None else nominal
    return _KINDS[kind](list(datasets), nominal)


def diagnose(data: Dataset, nominal: NominalDevice | None = None) -> DiagnosisResult:
    """Diagnose the sim-to-real gap of one record.

    1. Refits the nominal parameters (under their prior where the kind has one); 2.
    localises the residual; 3. fits each effect of the kind's library and ranks them by
    evidence (2 ln B against the nominal model, BIC approximation); 4. reports the held-out
    gap before and after the chosen effect with a bootstrap uncertainty. Held out: the last
    ~1/3 of a step or noise record; for a vibration table, each row by cross-validation.

    **Arguments:**

    - `data`: a validated record (`accel_jax._data.read_csv` / `parse_csv`).
    - `nominal`: the nominal device and the relative uncertainty of its values; default the
        SPEC.md reference device with J, μ, c, k_dm known to ±5 %. Only the `step` kind
        uses it (the vibration and noise nominal models have no servo parameters).

    **Returns:** a `DiagnosisResult` (`.verdict`, `.ranking`, `.gap`, `.where`, `.refit`,
    `.to_dict()`, `.summary()`). Computed in float64 (x64 must be enabled).
    """
    return diagnose_many([data], nominal)[0]
