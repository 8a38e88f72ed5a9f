"""The scale_factor_identification study (studies/scale_factor_identification.py): its
quick run's results, read from the session's shared quick report, checked against
relations that hold independently of the simulation."""

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

import accel_jax as aj

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def report_dir(quick_report):
    return quick_report


@pytest.fixture(scope="module")
def study(report_dir):
    return json.loads(
        (report_dir.parent / "scale_factor_identification" / "result.json").read_text()
    )


def _load_study_module():
    spec = importlib.util.spec_from_file_location(
        "sfi", ROOT / "studies" / "scale_factor_identification.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow
def test_result_schema(study):
    for method in ("oscillatory", "aperiodic"):
        assert np.isfinite(study["dKa_percent"][method])
    assert study["assumptions"]["sample_rate_Hz"] > 0
    assert study["assumptions"]["precision"] == "float64"
    assert "seeds" in study["provenance"] and study["provenance"]["accel_jax_version"]


@pytest.mark.slow
def test_gamma_rounding_row_is_exactly_the_closed_form(study):
    # K̂ scales with γ, so δ(3/4) = 1 − (1 − δ(γ)) γ/(3/4) for the same record.
    rows = study["decomposition"]["oscillatory"]["dKa_percent"]
    gamma = float(aj.shape_factor(aj.ServoParams.reference()))
    ideal = rows["ideal (T_dm = T_f = 0, γ exact, 10 MHz, no noise)"] / 100
    rounded = rows["γ rounded to 3/4"] / 100
    assert rounded == pytest.approx(1 - (1 - ideal) * gamma / 0.75, abs=1e-12)
    # The ideal case is exact up to the 10 MHz sampling: |δK_a| below 1e-3 %.
    assert abs(ideal) < 1e-5


@pytest.mark.slow
def test_torquer_lag_row_matches_dominant_pole_prediction(study):
    # Independent of the simulation: the roots of the test-signal transfer function.
    dec = study["decomposition"]["oscillatory"]
    measured = dec["dKa_percent"]["T_dm = 1e-5 s"]
    predicted = dec["T_dm_row_predicted_from_dominant_poles"]
    # 2e-3 percentage points: the ideal row's own error (3e-4) plus the transient of the
    # fast real pole (−1/T_dm) that the prediction neglects.
    assert measured == pytest.approx(predicted, abs=2e-3)
    sweep = study["sweeps"]["oscillatory"]["torquer_time_constant_s"]
    # Monte Carlo means track the prediction within 5 standard errors (noise ε = 1e-5 V).
    seeds = study["assumptions"]["monte_carlo_seeds_per_point"]
    for mean, std, pred in zip(
        sweep["mean"], sweep["std"], sweep["predicted_noise_free"], strict=True
    ):
        assert abs(mean - pred) < 5 * std / np.sqrt(seeds) + 0.02


@pytest.mark.slow
def test_aperiodic_lag_compensation_helps(study):
    table = study["decomposition"]["aperiodic"]["dKa_percent"]
    full = table["T_dm and T_f, compensated (16)"]["gamma_exact"]
    none = table["T_dm and T_f, uncompensated"]["gamma_exact"]
    assert abs(full) < abs(none) / 5
    assert abs(table["no lags"]["gamma_exact"]) < 0.01  # exact method on exact data


@pytest.mark.slow
def test_known_filter_removes_the_fit_bias(study):
    fits = study["least_squares_fit"]
    known, ignored = fits["fit_order_3_known_filter"], fits["fit_order_3"]
    seeds = study["assumptions"]["monte_carlo_seeds_per_point"]
    # Folding T_f into T_dm biases K_a by about −0.43 %; with T_f given, only noise is left.
    assert ignored["mean"] < -0.2
    assert abs(known["mean"]) < 4 * known["std"] / np.sqrt(seeds) + 1e-3


@pytest.mark.slow
def test_half_period_keeps_high_damping_usable(study):
    full = study["sweeps"]["oscillatory"]["damping_ratio"]
    half = study["sweeps"]["oscillatory"]["damping_ratio_half_period"]
    assert full["x"] == half["x"]
    # Same records and the same result codes (the variant changes only the period); where
    # the records are usable at ξ ≥ 0.7 the half period scatters less (t2 is shallow).
    assert full["usable_fraction"] == half["usable_fraction"]
    for x, use, f_std, h_std in zip(
        full["x"], full["usable_fraction"], full["std"], half["std"], strict=True
    ):
        if x >= 0.7 and use == 1:
            assert h_std <= 1.05 * f_std


def test_dominant_pole_prediction_without_lag_is_gamma_only():
    module = _load_study_module()
    p = aj.ServoParams.reference(torquer_time_constant=0.0)
    gain = float(p.pickoff_gain * p.amplifier_gain)
    assert module.dominant_pole_prediction(p, float(aj.shape_factor(p)), gain) == pytest.approx(
        0.0, abs=1e-10
    )


def test_user_device_and_its_twin():
    module = _load_study_module()
    ref, ref_ap, label = module._devices(None)
    assert label == "reference"
    device = aj.ServoParams.reference(damping=3.5e-5, stiffness=3.1e-4)
    osc, ape, label = module._devices(device)
    assert osc is device and "user's device" in label
    # The twin differs from the device only in μ, and has the reference aperiodic ξ.
    assert float(aj.damping_ratio(ape)) == pytest.approx(
        float(aj.damping_ratio(aj.ServoParams.reference_aperiodic())), rel=1e-12
    )
    assert float(ape.stiffness) == float(device.stiffness)
    heavy = aj.ServoParams.reference(damping=2e-4)
    osc, ape, _ = module._devices(heavy)
    assert ape is heavy and float(aj.damping_ratio(osc)) == pytest.approx(
        float(aj.damping_ratio(aj.ServoParams.reference())), rel=1e-12
    )


@pytest.mark.slow
def test_stop_displacement_error_enters_one_for_one(study):
    # Eq. (11) divides outputs ∝ h_true by the design h: K̂_a ∝ h_true/h_design, so δK_a
    # moves by 1 % per 1 % of stop error (to the sweep's ±2 %: (1 + e) is linear in e).
    sweep = study["decomposition"]["stop_tolerance"]
    assert sweep["slope_percent_per_percent"] == pytest.approx(1.0, abs=0.01)
    at = dict(zip(sweep["stop_error_percent"], sweep["dKa_percent"], strict=True))
    # The e = 0 point is the gain's own error from the stops (small: the stop outputs are
    # settled and noise-free); each ±e scales the gain by (1 + e).
    assert abs(at[0.0]) < 0.05
    assert at[1.0] - at[0.0] == pytest.approx(1.0 + at[0.0] / 100, rel=1e-3)
