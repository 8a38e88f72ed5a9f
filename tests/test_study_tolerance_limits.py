"""The tolerance_limits study (studies/tolerance_limits.py): its quick run's
results, read from the session's shared quick report (each study script run alone in a
fresh process; see tests/conftest.py)."""

import numpy as np
import pytest


@pytest.mark.slow
def test_tolerance_limits_study_quick(quick_report):
    from helpers import study_result

    tmp_path, r = study_result(quick_report, "tolerance_limits")
    limits = ["A1", "k2", "k3", "k4", "k5", "m"]
    for example in (r["cyclone4"], r["tactical"], r["tactical"]["long_range"]):
        for block in ("paper", "gradient", "table2"):
            assert sorted(example[block]) == sorted(limits)
            assert all(np.isfinite(v) and v > 0 for v in example[block].values())
        # Where the gradient method's assumptions coincide with the paper's (k2, k3, m: the
        # paper's closed-form denominators are the exact sensitivities, same shares), the
        # limits agree to rounding.
        for name in ("k2", "k3", "m"):
            assert example["gradient"][name] == pytest.approx(example["paper"][name], rel=1e-12)
        # Every entry that does not reproduce carries a reason.
        for name in limits:
            if not example["reproduced"][name]:
                assert " — " in example["explanation"][name]
    cyc = r["cyclone4"]
    assert cyc["paper"]["A1"] == pytest.approx(430.1, abs=0.1)
    assert cyc["paper"]["m"] == pytest.approx(48.67, abs=0.01)
    assert cyc["table2"] == {"A1": 445, "k2": 10, "k3": 37, "k4": 24, "k5": 1, "m": 48}
    # Reproduced means: rounds to the printed value at its printed significant figures.
    # 430.1 is not 445, 0.72 is not 1, and 48.67 prints as 49 (48 if truncated).
    assert [n for n in limits if cyc["reproduced"][n]] == []
    assert cyc["reproduced_by_reading"]["k3"] == ["k3 with σ² for 3σ² in (15)"]
    assert cyc["reproduced_by_reading"]["m"] == ["truncated, not rounded, to the printed figures"]
    assert cyc["reproduced_by_reading"]["k2"] == ["k2 with its last digit lost (105 → 10)"]
    assert cyc["reproduced_by_reading"]["A1"] == []
    # The printed fourth-moment coefficients (σ⁴, 5σ⁴ for 3σ⁴, 15σ⁴): the long flight's k4
    # 0.0134 prints as the table's 0.01; the k5 digits appear on the opposite flights.
    long = r["tactical"]["long_range"]
    assert long["paper_printed_reading"]["k4"] == pytest.approx(0.0134, abs=5e-5)
    assert long["reproduced_by_reading"]["k4"] == [
        "the printed coefficients (σ⁴ in (4)/(13), 5σ⁴ in (5)/(15))"
    ]
    assert f"{long['paper_printed_reading']['k5']:.1g}" == "0.001"  # the short flight's digit
    assert f"{r['tactical']['paper_printed_reading']['k5']:.1g}" == "0.0004"  # the long's
    # Exact A1 sensitivity at 2 g is far below the paper's: its gradient limit is looser.
    assert cyc["gradient"]["A1"] > 2 * cyc["paper"]["A1"]
    # The profile reaches 5 g: the worst instant is tighter for k3..k5.
    for name in ("k3", "k4", "k5"):
        assert cyc["gradient_worst_over_profile"][name] < cyc["gradient"][name]
    # The short flight's k4, k5 reproduce only with the random level before the mount's η.
    for name in ("k4", "k5"):
        assert r["tactical"]["reproduced_by_reading"][name] == ["σ = 5 g (before η)"]
    assert r["tactical"]["paper"]["A1"] == pytest.approx(35.6, abs=0.05)
    assert r["tactical"]["table2"]["k5"] == 0.001
    assert r["tactical"]["long_range"]["table2"]["k5"] == 0.0004
    assert 0 <= r["autodiff_vs_closed_form_max_rel_err"] < 1e-10
    t1 = r["table1_random_vibration"]
    assert t1["psd_implied_within_printed_range_3pc"]
    # η applied linearly reproduces the printed column; η² (the physical amplitude-response
    # reading) would need PSDs outside the printed ranges, and gives a smaller σ.
    assert not t1["eta_squared"]["psd_implied_within_printed_range_3pc"]
    assert t1["eta_squared"]["paper_formula_sigma_g_midpoint_psd"] == pytest.approx(0.90, abs=0.01)
    assert t1["mean_square_of_printed_column_g2"] == pytest.approx(1.40, abs=0.01)
    for region in r["joint_region"].values():
        assert region["library_region_test_agrees"]
    y = r["yield"]["cyclone4"]
    assert 0.0 <= y["yield_worst_over_profile"] <= y["yield_at_mean_a3"] <= 1.0
    assert y["phase_average_rel_err_vs_2048_phases"] < 1e-12
    assert r["assumptions"]["precision"] == "float64"
    assert r["figures"][-1]["file"] == "autodiff_vs_closed_form.png"
    for fig in r["figures"]:
        assert fig["caption"] and (tmp_path / fig["file"]).exists()
