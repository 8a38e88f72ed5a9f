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
# pinned to one core (a fresh clone with a cold compilation cache, 2026-11-25) [s]: the
# report starts the longest first when it runs studies side by side (its order stays
# STUDIES).
TYPICAL_SECONDS: dict[str, float] = {
    "scale_factor_identification": 92,
    "sensing_element_ml": 113,
    "vibration_compensation": 16,
    "tolerance_limits": 10,
    "noise_identification": 245,  # with the §4 paper's filter loop (issue 23), alone, 2026-11-25
    "sim_to_real_validation": 815,  # 520 blind records (issue 19)
    "table5_gap": 1,
}
