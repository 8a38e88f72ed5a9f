"""The sensing_element_ml study (studies/sensing_element_ml.py): its quick run's
results, read from the session's shared quick report (each study script run alone in a
fresh process; see tests/conftest.py)."""

import pytest


@pytest.mark.slow
def test_study_quick(quick_report):
    from helpers import study_result

    tmp_path, saved = study_result(quick_report, "sensing_element_ml")
    for key in ("title", "summary", "figures", "assumptions", "provenance", "error_rms_rad"):
        assert key in saved
    table = saved["error_rms_rad"]
    for amplitude in ("0.005", "0.01", "0.02", "0.033"):
        row = table[amplitude]
        assert set(row) >= {"linear", "compensated", "nonlinear_fit", "predicted"}
        # Compensation and the nonlinear fit both beat the linear estimator.
        assert row["compensated"] < row["linear"] / 10
        assert row["nonlinear_fit"] < row["linear"] / 10
        # The paper's Δ_αP predicts the measured bias (first order in A²).
        assert row["predicted"] == pytest.approx(row["linear"], rel=0.05)
    # The linearisation bias grows like A³.
    growth = table["0.02"]["linear"] / table["0.01"]["linear"]
    assert 6 < growth < 10
    for figure in saved["figures"]:
        assert (tmp_path / figure["file"]).exists()
