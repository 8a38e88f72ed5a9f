"""The table5_gap study (studies/table5_gap.py): its quick run's
results, read from the session's shared quick report (each study script run alone in a
fresh process; see tests/conftest.py)."""

import pytest


@pytest.mark.slow
def test_table5_gap_study(quick_report):
    from helpers import study_result

    tmp_path, saved = study_result(quick_report, "table5_gap")
    assert set(saved) >= {"title", "summary", "figures", "units", "conclusions", "provenance"}
    aks, al = saved["units"]["AKS-05"], saved["units"]["AL-1M"]
    # docs/models.md §3: basic error 16.8 / 215.4 ppm; exact vibration error 64.6 / 962.4 ppm.
    assert aks["basic_error_ppm"] == pytest.approx(16.82, abs=0.01)
    assert al["basic_error_ppm"] == pytest.approx(215.4, abs=0.01)
    assert aks["explained_exact_ppm"] == pytest.approx(64.6, abs=0.05)
    assert al["explained_exact_ppm"] == pytest.approx(962.4, abs=0.1)
    # The closed form reproduces what the paper removed for AL-1M (978 ppm).
    assert al["explained_paper_ppm"] == pytest.approx(978.0, abs=0.5)
    assert aks["gap"]["after_exact_ppm"] == pytest.approx(83 - aks["explained_exact_ppm"], abs=1e-6)
    for unit in (aks, al):
        assert unit["verdict"] == "cannot_tell"
        for entry in unit["one_effect_closing_the_gap"].values():
            # Every single-effect explanation meets the one reading exactly ...
            assert entry["predicted_at_probes_ppm"][0] == pytest.approx(
                unit["measured_vibration_error_ppm"], abs=1e-6
            )
        # ... and they part at a = −1 g.
        assert unit["discriminating_rows"][1]["spread_ppm"] > 10
    for figure in saved["figures"]:
        assert (tmp_path / figure["file"]).exists() and figure["caption"]
