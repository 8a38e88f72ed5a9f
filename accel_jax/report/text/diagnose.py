"""The notes `accel-jax diagnose` prints after a diagnosis's summary (options that had no
effect on what was asked)."""

from __future__ import annotations


def diagnose_notes(n_files: int, kind: str, discover: bool, params_given: bool) -> list[str]:
    """The notes for `n_files` records of `kind` diagnosed with `--discover` (`discover`)
    and `--params` (`params_given`): what those options did not do."""
    notes = []
    if discover and n_files > 1:
        notes.append(
            "note: --discover (and --ceiling) look at one record; a set of records is not "
            "searched"
        )
    if params_given and kind != "step":
        notes.append(
            f"note: --params is not used by the {kind} diagnosis (its nominal model has no "
            "servo-loop parameters)"
        )
    return notes
