"""Sim-to-real diagnosis (docs/models.md §5): where the gap between a measured record and the
nominal model lies, which unmodelled effect causes it, and how far it shrinks once that
effect is added.

    from accel_jax._data import read_csv
    from accel_jax.diagnose import diagnose
    data = read_csv("record.csv")               # kind inferred from the columns
    result = diagnose(data)                      # the reference device, ±5 % prior
    print(result.summary()); result.to_dict()

Several step records of one device together: `diagnose_step_set` (`step/joint_verdict.py`;
the joint fit in `step/joint.py`).

Kinds, one subpackage each: `step`, `vibration` and `noise`,
beside what they share: `base` (the effect interface, evidence, `DiagnosisResult`),
`openworld` (the open-world verdict) and `dispatch`. A kind provides its nominal model, an
effect base class with hooks, the effects registered with `register_effect`, and a
`diagnose_<kind>(datasets, nominal)` listed in `dispatch._KINDS`, which `diagnose` and
`diagnose_many` dispatch on.
"""

from __future__ import annotations

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
from .dispatch import diagnose as diagnose
from .dispatch import diagnose_many as diagnose_many
from .noise import AbstractNoiseEffect as AbstractNoiseEffect
from .noise import diagnose_noise as diagnose_noise
from .step import AbstractStepEffect as AbstractStepEffect
from .step import SetDiagnosis as SetDiagnosis
from .step import diagnose_step as diagnose_step
from .step import diagnose_step_set as diagnose_step_set
from .vibration import AbstractVibrationEffect as AbstractVibrationEffect
from .vibration import diagnose_vibration as diagnose_vibration
