"""The vibration_compensation study (studies/vibration_compensation.py): its quick run's
results, read from the session's shared quick report (each study script run alone in a
fresh process; see tests/conftest.py)."""

import numpy as np
import pytest


@pytest.mark.slow
def test_vibration_compensation_study_quick(quick_report):
    from helpers import study_result

    tmp_path, r = study_result(quick_report, "vibration_compensation")
    # Hand values: basic error (2) at 1 g without a0, 0.5·A1 + k2 + k3 + k4 + k5 [ppm];
    # the paper's (19) at a = 1, b = 2: A1(0.673·2 − 0.5) + 2k2 + 6k3 + 18k4 + 50k5.
    hand = {"AKS-05": (15, 2, 7, 0.02, 0.3), "AL-1M": (25, 105, 87, 10, 0.9)}
    for name, (A1, k2, k3, k4, k5) in hand.items():
        u = r[name]
        assert u["basic_error_ppm"] == pytest.approx(0.5 * A1 + k2 + k3 + k4 + k5, rel=1e-9)
        paper = A1 * (0.673 * 2 - 0.5) + 2 * k2 + 6 * k3 + 18 * k4 + 50 * k5
        assert u["vibration_error_paper_ppm"] == pytest.approx(paper, rel=1e-9)
        mc = u["vibration_error_monte_carlo_ppm"]
        se = u["vibration_error_monte_carlo_standard_error_ppm"]
        assert abs(mc - u["vibration_error_exact_ppm"]) < 4 * se + 1e-9
        assert set(u["residual_after_compensation_ppm"]) == {
            "paper",
            "exact",
            "paper_printed_k5_1_185",
        }
    assert r["AKS-05"]["vibration_error_exact_ppm"] == pytest.approx(64.63, abs=0.01)
    assert r["AL-1M"]["vibration_error_exact_ppm"] == pytest.approx(962.45, abs=0.01)
    np.testing.assert_allclose(
        r["AKS-05"]["table5_measured"]["residual_ppm"], [100, 83, 6], atol=1e-6
    )
    # Against the measured Table 5 (see test_compensation_against_table5 for the tolerances).
    for name, (after_basic, after_vib) in {"AKS-05": (83, 6), "AL-1M": (1088, 110)}.items():
        u = r[name]
        assert u["residual_after_basic_compensation_ppm"] == pytest.approx(after_basic, abs=1.5)
        assert u["residual_after_compensation_ppm"]["paper"] == pytest.approx(after_vib, abs=3.5)
    for case in r["vibration_error"]["cases"].values():
        assert abs(case["monte_carlo_z"]) < 4, case
    t3 = r["table3_shaker"]["at_paper_sigma"]
    assert t3["estimator_error_rms_1e-4g"] < 0.01 and t3["axis_check_pass_fraction"] == 1.0
    fit = r["coefficient_fitting"]
    assert not fit["plans"]["±1 g only"]["identifiable"]["k3"]
    assert fit["plans"]["recommended (greedy D-optimal)"]["meets_target"]
    assert fit["recovery"]["max_abs_z"] < 5
    assert r["assumptions"]["precision"] == "float64"
    for fig in r["figures"]:
        assert fig["caption"] and (tmp_path / fig["file"]).exists()
