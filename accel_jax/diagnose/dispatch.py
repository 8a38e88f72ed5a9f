"""`diagnose` and `diagnose_many`: a record's kind picks its diagnosis (`_KINDS`)."""

from __future__ import annotations

from typing import cast

from .._data import DataError, Dataset, NominalDevice, StepData, VibrationData
from .base import DiagnosisResult
from .noise import diagnose_noise
from .step import diagnose_step
from .vibration import diagnose_vibration

_KINDS = {"step": diagnose_step, "vibration": diagnose_vibration, "noise": diagnose_noise}


def diagnose_many(
    datasets: list[Dataset],
    nominal: NominalDevice | None = None,
    *,
    recommend: bool = True,
    discover: bool = False,
    ceiling: bool = False,
) -> list[DiagnosisResult]:
    """Diagnose several records (same kind) against one nominal device, each on its own;
    records of one length are fitted as one batch (one compilation). See `diagnose`.
    `recommend` (step records): compute the next experiment for a lag tie; `discover`
    (step records): look for the missing term of an unexplained record (or of a noise
    verdict, `step.verdict.noise_verdict`)
    (`step.discover`), with `ceiling` the network reference of what a term of the states
    could remove (`step.ceiling`). Several step
    records of one device diagnosed *together*: `step.joint_verdict.diagnose_step_set`."""
    if not datasets:
        return []
    kinds = {d.kind for d in datasets}
    if len(kinds) != 1:
        raise ValueError(f"diagnose_many needs records of one kind, got {sorted(kinds)}.")
    kind = kinds.pop()
    if kind not in _KINDS:
        raise DataError(f"there is no diagnosis of {kind!r} records; available: {sorted(_KINDS)}.")
    nominal = NominalDevice.reference() if nominal is None else nominal
    if kind == "step":
        steps = cast(list[StepData], list(datasets))  # every record of kind "step"
        return diagnose_step(
            steps, nominal, recommend=recommend, discover=discover, ceiling=ceiling
        )
    if kind == "vibration":
        tables = cast(list[VibrationData], list(datasets))  # every record of kind "vibration"
        return diagnose_vibration(tables, nominal, discover=discover)
    results = _KINDS[kind](list(datasets), nominal)
    if discover:
        for result in results:
            result.notes.append(
                f"no discovery: the search for a missing term covers step records and "
                f"vibration tables, not {kind}"
            )
    return results


def diagnose(
    data: Dataset,
    nominal: NominalDevice | None = None,
    *,
    discover: bool = False,
    ceiling: bool = False,
) -> DiagnosisResult:
    """Diagnose the sim-to-real gap of one record.

    1. Refits the nominal parameters (under their prior where the kind has one); 2.
    localises the residual; 3. fits each effect of the kind's library and ranks them by
    evidence (2 ln B against the nominal model, BIC approximation); 4. reports the held-out
    gap before and after the chosen effect with a bootstrap uncertainty. Held out: the last
    ~1/3 of a step or noise record; for a vibration table, each row by cross-validation.

    **Arguments:**

    - `data`: a validated record (`accel_jax._data.read_csv` / `parse_csv`).
    - `nominal`: the nominal device and the relative uncertainty of its values; default the
        docs/models.md reference device with J, μ, c, k_dm known to ±5 %. Only the `step` kind
        uses it (the vibration and noise nominal models have no servo parameters).

    **Returns:** a `DiagnosisResult` (`.verdict`, `.ranking`, `.gap`, `.where`, `.refit`,
    `.to_dict()`, `.summary()`). Computed in float64 (x64 must be enabled). With
    `discover` (step records), an unexplained record also gets `.discovery`: the missing
    term found in the term library, a hypothesis (`step.discover`); so does a noise
    verdict (`step.verdict.noise_verdict`), which a credible term that brings the
    held-out gap to the floor, where the noise's free run does not, makes `unexplained`
    (`step.question.weigh_discovery`); with `ceiling` too,
    the share of the held-out gap a network of the loop's states removes (`step.ceiling`).
    """
    return diagnose_many([data], nominal, discover=discover, ceiling=ceiling)[0]
