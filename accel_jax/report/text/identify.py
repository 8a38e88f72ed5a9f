"""`accel-jax identify` with several records of one device: what it prints
(`identify_set_lines`) and the records of its JSON (`identify_set_records`), from
`accel_jax._identify.step_record.identify_step_records`' results (`StepIdentification`
or `StopRecordGain`). One record alone prints `accel_jax.identification_summary`."""

from __future__ import annotations

from ..._identify.step_result import StepIdentification, StopRecordGain
from .identification import identification_summary


def _stops_line(file, stops: StopRecordGain) -> str:
    return (
        f"{file}: stop-level record, eq. (11): k_dp·k_y = "
        f"{stops.pickoff_amplifier_gain_V_per_m:.6g} V/m (nominal "
        f"{stops.nominal_V_per_m:.6g}, {stops.shift_relative:+.2%}) from "
        f"U⁺ = {stops.u_plus_V:.5g} V, U⁻ = {stops.u_minus_V:.5g} V, h_max = "
        f"{stops.h_max_m:.4g} m (the device's); output offset "
        f"{stops.offset_V:+.4g} V"
    )


def identify_set_lines(files, results: list[StepIdentification | StopRecordGain]) -> list[str]:
    """One entry per record: a stop-level record's k_dp·k_y by eq. (11) in one line, any
    other record's identification summary under its file name."""
    return [
        _stops_line(file, result)
        if isinstance(result, StopRecordGain)
        else f"{file}:\n" + identification_summary(result)
        for file, result in zip(files, results, strict=True)
    ]


def identify_set_records(files, results: list[StepIdentification | StopRecordGain]) -> list[dict]:
    """The JSON's `records`: each result's `to_dict()` with its source (without the traces,
    the record and the model sample by sample)."""
    return [
        {"source": str(file), **result.to_dict()}
        for file, result in zip(files, results, strict=True)
    ]
