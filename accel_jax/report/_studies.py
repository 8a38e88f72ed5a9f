"""The studies of the report (`accel-jax report`), in the page's order, and how long each
typically runs."""

STUDIES = (
    "scale_factor_identification",
    "sensing_element_ml",
    "vibration_compensation",
    "tolerance_limits",
    "noise_identification",
    "sim_to_real_validation",
    "table5_gap",
)
# Wall time of each study in a full report on a 2-core CPU, two at a time, each process
# pinned to one core (a fresh clone at c6485f4 with this machine's compilation cache, 2026-11-27;
# the blind validation as measured alone after its step fits stopped batching, the same
# day) [s]: the report starts the longest first when it runs studies side by side (its
# order stays STUDIES).
TYPICAL_SECONDS: dict[str, float] = {
    "scale_factor_identification": 104,
    "sensing_element_ml": 143,
    "vibration_compensation": 17,
    "tolerance_limits": 11,
    "noise_identification": 874,  # the in-flight identification of issue 47: 711 s of it
    "sim_to_real_validation": 1045,  # 520 blind records (issue 19)
    "table5_gap": 2,
}
