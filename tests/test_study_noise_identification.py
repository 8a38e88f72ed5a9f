"""The noise_identification study (studies/noise_identification.py): its quick run's
results, read from the session's shared quick report (each study script run alone in a
fresh process; see tests/conftest.py)."""

import pytest


@pytest.mark.slow
def test_study_quick(quick_report):
    from helpers import study_result

    tmp_path, saved = study_result(quick_report, "noise_identification")
    for key in ("title", "summary", "figures", "assumptions", "provenance"):
        assert key in saved
    gm, ec = saved["gauss_markov"], saved["exp_cosine"]
    assert gm["tau_fit"] == pytest.approx(gm["tau_true"], rel=0.2)
    assert gm["sigma_fit"] == pytest.approx(gm["sigma_true"], rel=0.1)
    assert ec["beta_fit"] == pytest.approx(ec["beta_true"], rel=0.1)
    kal = saved["kalman"]
    assert (
        kal["wrong_model"]["fraction_outside_3sigma"]
        > 10 * kal["identified"]["fraction_outside_3sigma"]
    )
    assert kal["identified"]["fraction_outside_3sigma"] < 0.02
    for figure in saved["figures"]:
        assert (tmp_path / figure["file"]).exists() and figure["caption"]
