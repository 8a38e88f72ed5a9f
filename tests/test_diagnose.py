"""The sim-to-real diagnosis of step records (accel_jax.diagnose), its CLI command and the
blind-validation study, checked by simulate-then-diagnose-then-recover against truth
simulators that are not the diagnosis's own model (`simulate_linear`, `simulate_nonlinear`)."""

import json

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from click.testing import CliRunner
from scipy import stats

import accel_jax as aj
from accel_jax._data import StepData, write_csv
from accel_jax.cli import main
from accel_jax.diagnose import (
    CandidateFit,
    diagnose,
    effect_library,
    held_out_gap,
    ljung_box,
    rank_candidates,
)
from accel_jax.diagnose.step import simulate_step

RATE = 100e3  # Hz
SEGMENT = 200
U = 2.0  # V
SIGMA = 5e-4  # V
PATTERN = (0.0, 1.0, 0.0, -1.0, 1.0, 0.0)


def _grid():
    u = np.repeat(np.asarray(PATTERN) * U, SEGMENT)
    return np.arange(u.size) / RATE, u


def _device(**overrides):
    # A device off the nominal by ~1σ of the 5 % prior in every refitted value.
    values = {
        "moment_of_inertia": 7.09e-9 * 1.04,
        "damping": 2.54e-5 * 0.96,
        "stiffness": 3.02e-4 * 1.05,
        "torquer_gain": 9.23e-6 * 0.97,
        "external_moment": 1.5e-6,
        "torquer_time_constant": 0.0,
        "filter_time_constant": 0.0,
        "noise_std": SIGMA,
    }
    return aj.ServoParams.reference(**{**values, **overrides})


def _record(effect, seed):
    ts, u = _grid()
    key = jax.random.key(seed)
    truth = {}
    if effect in ("none", "colored_noise"):
        params = _device()
        y = aj.simulate_linear(params, ts, u, key=key)
    elif effect == "torquer_lag":
        truth["torquer_time_constant_s"] = 8e-5
        y = aj.simulate_linear(_device(torquer_time_constant=8e-5), ts, u, key=key)
    elif effect == "output_filter":
        truth["filter_time_constant_s"] = 8e-5
        y = aj.simulate_linear(_device(filter_time_constant=8e-5), ts, u, key=key)
    elif effect == "small_lag":
        y = aj.simulate_linear(_device(torquer_time_constant=1.5e-5), ts, u, key=key)
    elif effect == "stop_saturation":
        params = _device()
        gain = float(params.pickoff_gain * params.amplifier_gain)
        truth["stop_output_V"] = 0.95 * U
        params = eqx.tree_at(lambda p: p.stop_displacement, params, 0.95 * U / gain)
        y = aj.simulate_nonlinear(params, ts, u, key=key, rtol=1e-8, atol=1e-8)
    elif effect == "disturbance_drift":
        params = _device()
        rate = 1e-7 / ts[-1]
        truth["moment_rate_Nm_per_s"] = rate
        y = aj.simulate_linear(params, ts, u, external_moment=1.5e-6 + rate * ts, key=key)
    y = np.asarray(y)
    if effect == "colored_noise":
        # AR(1) noise (sampled Gauss–Markov, τ = 50 µs) of 1.5σ on top of the white noise.
        phi = np.exp(-1 / RATE / 5e-5)
        # White + Gauss–Markov is ARMA(1,1); its best AR(1) one-step predictor has the
        # lag-1 autocorrelation ρ1 = φ σ_gm²/(σ_gm² + σ²) (closed form).
        truth["ar1_coefficient"] = phi * 1.5**2 / (1.5**2 + 1)
        rng = np.random.default_rng(seed)
        w = rng.normal(size=y.size) * 1.5 * SIGMA * np.sqrt(1 - phi**2)
        g = np.zeros(y.size)
        for i in range(1, y.size):
            g[i] = phi * g[i - 1] + w[i]
        y = y + g
    return StepData(ts, u, y), truth


CASES = (
    "none",
    "torquer_lag",
    "output_filter",
    "stop_saturation",
    "disturbance_drift",
    "colored_noise",
    "small_lag",
)


@pytest.fixture(scope="module")
def diagnosed():
    # One compiled diagnosis (records of one length, batch of one) serves every case.
    out = {}
    for i, case in enumerate(CASES):
        data, truth = _record(case, seed=10 + i)
        out[case] = (data, truth, diagnose(data))
    return out


# --- the model -----------------------------------------------------------------------


def test_simulate_step_matches_simulate_linear():
    ts, u = _grid()
    ts, u = jnp.asarray(ts), jnp.asarray(u)
    moment = 1e-6 + 2e-7 * ts / ts[-1]
    for lags in ((0.0, 0.0), (2e-5, 0.0), (0.0, 3e-5), (1e-5, 1e-5)):
        params = _device(torquer_time_constant=lags[0], filter_time_constant=lags[1])
        ours = simulate_step(params, ts, u, moment)
        reference = aj.simulate_linear(params, ts, u, external_moment=moment)
        np.testing.assert_allclose(ours, reference, rtol=0, atol=1e-12 * U)


def test_stop_surrogate_close_to_diffrax_contact():
    ts, u = _grid()
    params = _device()
    gain = float(params.pickoff_gain * params.amplifier_gain)
    stopped = eqx.tree_at(lambda p: p.stop_displacement, params, 0.95 * U / gain)
    exact = aj.simulate_nonlinear(stopped, ts, u, rtol=1e-9, atol=1e-9)
    moment = jnp.full(ts.shape, params.external_moment)
    ours = simulate_step(params, jnp.asarray(ts), jnp.asarray(u), moment, 1 / (0.95 * U))
    assert float(jnp.max(exact)) == pytest.approx(0.95 * U, rel=5e-3)  # contact penetration
    # O(dt) in the release time: within 2 % of the step everywhere.
    assert float(jnp.max(jnp.abs(ours - exact))) < 0.02 * U


def test_simulate_step_gradient_matches_finite_difference():
    ts, u = _grid()
    ts, u = jnp.asarray(ts), jnp.asarray(u)
    moment = jnp.full(ts.shape, 1e-6)

    def loss(tdm):
        params = _device(torquer_time_constant=tdm)
        return jnp.sum(simulate_step(params, ts, u, moment) ** 2)

    for tdm in (0.0, 2e-5):
        grad = jax.grad(loss)(jnp.asarray(tdm))
        h = 1e-9
        if tdm == 0.0:  # one-sided at the boundary T_dm = 0
            fd = (loss(2 * h) - loss(h)) / h  # slope just inside, O(h) from the limit
            assert float(grad) == pytest.approx(float(fd), rel=1e-3)
        else:
            fd = (loss(tdm + h) - loss(tdm - h)) / (2 * h)
            assert float(grad) == pytest.approx(float(fd), rel=1e-5)


def test_every_effect_is_nominal_at_zero():
    from accel_jax.diagnose.step import StepContext, _model

    ts, u = _grid()
    n = ts.size
    ctx = StepContext(
        *(jnp.asarray(v) for v in (SIGMA, ts[-1], U, 1e-8, 8.7e-6)),
        train=jnp.ones(n),
        test=jnp.zeros(n),
    )
    base = aj.ServoParams.reference()
    sigma = jnp.full(4, 0.05)
    z = jnp.zeros(6).at[1].set(0.3)  # a refit shift, effect slot 0
    nominal, _ = _model(z, 0, base, sigma, ctx, jnp.asarray(ts), jnp.asarray(u))
    assert len(effect_library("step")) == 5
    for i in range(1, 6):
        extended, phi = _model(z, i, base, sigma, ctx, jnp.asarray(ts), jnp.asarray(u))
        np.testing.assert_array_equal(extended, nominal)
        assert float(phi) == 0.0


# --- recovery of each effect ----------------------------------------------------------


def test_none_on_clean_records(diagnosed):
    data, _, result = diagnosed["none"]
    assert result.verdict == "none"
    assert all(r["evidence"] < 10 for r in result.ranking)
    assert result.gap["shrink"] == 0.0
    # The refit moves the ~1σ-off device values toward the truth.
    truth = _device()
    for field, entry in result.refit["parameters"].items():
        assert (
            abs(entry["refitted"] / float(getattr(truth, field)) - 1)
            < abs(entry["nominal"] / float(getattr(truth, field)) - 1) + 0.02
        ), field
    assert result.where["whiteness"]["p_value"] > 1e-3
    # The ~1σ parameter offsets alone make a gap of many σ that the refit closes.
    assert result.refit["rms_before_refit_V"] > 5 * SIGMA
    assert result.refit["rms_after_refit_V"] < 1.2 * SIGMA
    assert result.refit["parameter_error"]


@pytest.mark.parametrize(
    "case, name, tolerance",
    [
        ("torquer_lag", "torquer_time_constant_s", 0.1),
        ("output_filter", "filter_time_constant_s", 0.1),
        ("stop_saturation", "stop_output_V", 0.01),
        ("disturbance_drift", "moment_rate_Nm_per_s", 0.15),
        ("colored_noise", "ar1_coefficient", 0.15),
    ],
)
def test_effect_named_and_recovered(diagnosed, case, name, tolerance):
    _, truth, result = diagnosed[case]
    assert result.verdict == case, result.summary()
    best = result.ranking[0]
    assert best["effect"] == case and best["evidence"] > 10
    assert best["params"][name] == pytest.approx(truth[name], rel=tolerance)
    assert result.gap["shrink"] > 0.5
    assert result.gap["after"] < result.gap["before"]


def test_small_lag_cannot_tell(diagnosed):
    # In-loop and output lags give the same loop polynomial up to a damping shift
    # k_dm k_dp k_y l·T (here ≈ 5 % of μ, 1σ of its prior): not separable, both fit.
    _, _, result = diagnosed["small_lag"]
    assert result.verdict == "cannot_tell"
    assert set(result.tied) == {"torquer_lag", "output_filter"}
    assert result.gap["shrink"] > 0.5


def test_residual_localised(diagnosed):
    _, _, drift = diagnosed["disturbance_drift"]
    _, _, lag = diagnosed["torquer_lag"]
    _, _, colored = diagnosed["colored_noise"]
    # A lag's residual sits in the transients, a drift's spreads into the steady state.
    assert lag.where["time"]["rms_transient_V"] > 1.5 * lag.where["time"]["rms_steady_V"]
    assert (
        drift.where["time"]["rms_steady_V"] / drift.where["time"]["rms_transient_V"]
        > lag.where["time"]["rms_steady_V"] / lag.where["time"]["rms_transient_V"]
    )
    assert colored.where["whiteness"]["p_value"] < 1e-6
    assert len(lag.where["conditions"]) == len(PATTERN)


# --- evidence logic, gap, whiteness (independent of the model) ---------------------------


def _fit(name, k, log_like, held_out=1.0):
    return CandidateFit(name, k, log_like, 1000, held_out, np.zeros(3), 1.0, {})


def test_rank_candidates_paths():
    nominal = _fit("nominal", 0, 0.0)
    penalty = 0.5 * np.log(1000)
    verdict, ranking, tied = rank_candidates(
        nominal, [_fit("a", 1, penalty + 20, 0.5), _fit("b", 1, penalty + 2, 0.5)]
    )
    assert verdict == "a" and ranking[0]["evidence"] == pytest.approx(40) and not tied
    verdict, _, tied = rank_candidates(
        nominal, [_fit("a", 1, penalty + 20, 0.5), _fit("b", 1, penalty + 18, 0.5)]
    )
    assert verdict == "cannot_tell" and tied == ["a", "b"]
    verdict, _, _ = rank_candidates(nominal, [_fit("a", 1, penalty + 4.9, 0.5)])
    assert verdict == "none"  # evidence 9.8 < 10
    verdict, _, _ = rank_candidates(nominal, [_fit("a", 1, penalty + 20, 2.0)])
    assert verdict == "none"  # better in training, worse held out: over-fitting


def test_held_out_gap_limits():
    rng = np.random.default_rng(0)
    noise = rng.normal(size=4000)
    systematic = 2 * np.sin(np.arange(4000) / 50)
    gap = held_out_gap(noise + systematic, noise, 1.0)
    assert gap["before"] == pytest.approx(np.sqrt(2), rel=0.05)
    assert gap["shrink"] > 0.9 and gap["shrink_std"] < 0.1
    same = held_out_gap(noise + systematic, noise + systematic, 1.0)
    assert same["shrink"] == 0.0 and same["shrink_std"] == 0.0


def test_ljung_box_against_chi_square():
    rng = np.random.default_rng(1)
    white = rng.normal(size=2000)
    result = ljung_box(white, lags=20)
    assert result["p_value"] == pytest.approx(stats.chi2.sf(result["statistic"], 20), rel=1e-8)
    ar = np.zeros(2000)
    for i in range(1, 2000):
        ar[i] = 0.5 * ar[i - 1] + white[i]
    assert ljung_box(ar)["p_value"] < 1e-10


# --- the CLI ----------------------------------------------------------------------------


def test_cli_diagnose_writes_json_and_plot(diagnosed, tmp_path):
    data, truth, _ = diagnosed["stop_saturation"]
    csv = write_csv(tmp_path / "rec.csv", data)
    out_json, out_png = tmp_path / "d.json", tmp_path / "d.png"
    result = CliRunner().invoke(
        main, ["diagnose", str(csv), "--json", str(out_json), "--plot", str(out_png)]
    )
    assert result.exit_code == 0, result.output
    assert "verdict: stop_saturation" in result.output
    doc = json.loads(out_json.read_text())
    assert set(doc) >= {"kind", "verdict", "ranking", "gap", "where", "refit"}
    assert doc["kind"] == "step" and doc["verdict"] == "stop_saturation"
    assert set(doc["gap"]) >= {"metric", "before", "after", "shrink"}
    assert set(doc["ranking"][0]) >= {"effect", "evidence", "gap_shrink", "params"}
    assert out_png.stat().st_size > 10_000


def _bad_inputs(tmp_path):
    ts, u = _grid()
    good = "t,u_test,u_out\n" + "\n".join(f"{a!r},{b!r},0.1" for a, b in zip(ts, u, strict=True))
    lines = good.splitlines()
    swapped = lines[:5] + [lines[6], lines[5]] + lines[7:]
    uneven = lines[:5] + [f"{ts[4] + 0.3 / RATE!r},0.0,0.1"] + lines[6:]
    files = {
        "empty": "",
        "missing column": "t,u_out\n0,1\n",
        "unknown column": "t,u_test,u_out,x\n0,1,2,3\n",
        "nan": good.replace(",0.1\n", ",nan\n", 1),
        "non-monotonic": "\n".join(swapped),
        "non-uniform": "\n".join(uneven),
        "too few": "\n".join(lines[:50]),
        "text": good.replace(",0.1\n", ",hello\n", 1),
    }
    out = {}
    for name, text in files.items():
        path = tmp_path / f"{name.replace(' ', '_')}.csv"
        path.write_text(text)
        out[name] = path
    return out


def test_cli_bad_input_one_line_nonzero_exit(tmp_path):
    out_json = tmp_path / "never.json"
    for name, path in _bad_inputs(tmp_path).items():
        result = CliRunner().invoke(main, ["diagnose", str(path), "--json", str(out_json)])
        assert result.exit_code != 0, name
        lines = [line for line in result.stderr.splitlines() if line.strip()]
        assert len(lines) == 1 and lines[0].startswith("Error:"), (name, result.stderr)
        assert not out_json.exists(), name
    params = tmp_path / "dev.toml"
    params.write_text("stifness = 3e-4\n")
    csv = tmp_path / "ok.csv"
    ts, u = _grid()
    write_csv(csv, StepData(ts, u, 0.9 * u))
    result = CliRunner().invoke(main, ["diagnose", str(csv), "--params", str(params)])
    assert result.exit_code != 0 and "unknown key(s) ['stifness']" in result.stderr
    vib = tmp_path / "vib.csv"
    vib.write_text(
        "a_in,vib_amp,vib_freq,vib_rms,a_out\n" + "\n".join(f"{i},1,0,0,{i}" for i in range(10))
    )
    result = CliRunner().invoke(main, ["diagnose", str(vib)])
    assert result.exit_code != 0 and "frequencies positive" in result.stderr


# --- the study ----------------------------------------------------------------------------


@pytest.mark.slow
def test_validation_study_quick(quick_report):
    from helpers import study_result

    tmp_path, saved = study_result(quick_report, "sim_to_real_validation")
    assert set(saved) >= {"title", "summary", "figures", "assumptions", "provenance", "step"}
    step = saved["step"]
    assert step["n_datasets"] == 18 and sum(step["n_per_class"].values()) == 18
    assert step["false_alarm_rate"] <= 1 / 3
    assert step["accuracy_incl_cannot_tell_naming_truth"] >= 0.8
    assert step["median_gap_shrink"] > 0.5
    for figure in saved["figures"]:
        assert (tmp_path / figure["file"]).exists() and figure["caption"]


def test_torquer_lag_and_output_filter_fit_a_step_record_exactly_alike():
    """The step kind's known degeneracy, checked independently of the fits: a loop with a
    torquer lag T_dm gives the same test-step record as a loop with an output filter T_f'
    and shifted J', μ' (c, k_dm unchanged), found by matching the two all-pole cubics
    (J T, J + μT, μ + cT, c + K) = (J'T', J' + μ'T', μ' + (c + K)T', c + K)."""
    ref = aj.ServoParams.reference()
    tdm = 2e-5
    lagged = eqx.tree_at(
        lambda p: (p.torquer_time_constant, p.filter_time_constant),
        ref,
        (jnp.float64(tdm), jnp.float64(0.0)),
    )
    J, mu, c = (float(x) for x in (ref.moment_of_inertia, ref.damping, ref.stiffness))
    K = float(aj.loop_stiffness(ref)) - c
    a3, a2, a1 = J * tdm, J + mu * tdm, mu + c * tdm
    roots = np.roots([c + K, -a1, a2, -a3])
    tf = min(
        (r.real for r in roots if abs(r.imag) < 1e-12 and r.real > 0), key=lambda r: abs(r - tdm)
    )
    mu2 = a1 - (c + K) * tf
    J2 = a2 - mu2 * tf
    filtered = eqx.tree_at(
        lambda p: (p.moment_of_inertia, p.damping, p.torquer_time_constant, p.filter_time_constant),
        ref,
        (jnp.float64(J2), jnp.float64(mu2), jnp.float64(0.0), jnp.float64(tf)),
    )
    ts = jnp.arange(3000) * 5e-6
    u = jnp.where((ts >= 2.5e-3) & (ts < 10e-3), 1.0, -1.0)
    moment = jnp.full_like(ts, float(ref.external_moment))
    y_lag = simulate_step(lagged, ts, u, moment)
    y_filter = simulate_step(filtered, ts, u, moment)
    # Same record to rounding, though the two loops differ by a damping shift of ~6.6 %...
    assert float(jnp.max(jnp.abs(y_lag - y_filter))) < 1e-9 * float(jnp.max(jnp.abs(y_lag)))
    assert abs(mu2 / mu - 1) > 0.05
    # ...which to first order in T is Δμ = k_dm k_dp k_y l·T, as the summary note says.
    assert (mu - mu2) == pytest.approx(K * tdm, rel=0.05)
    # And the no-lag loop differs from both by far more than the rounding above.
    y_none = simulate_step(
        eqx.tree_at(lambda p: p.torquer_time_constant, lagged, 0.0), ts, u, moment
    )
    assert float(jnp.max(jnp.abs(y_none - y_lag))) > 1e-3 * float(jnp.max(jnp.abs(y_lag)))


def test_lag_forced_choice_ceiling():
    from pathlib import Path

    from accel_jax.report._run import load_study

    module = load_study(
        "sim_to_real_validation", Path(__file__).resolve().parent.parent / "studies"
    )

    def verdict(name, tied=(), tl=0.0, of=0.0):
        ranking = [
            {"effect": "torquer_lag", "evidence": tl},
            {"effect": "output_filter", "evidence": of},
        ]
        return {"verdict": name, "tied": list(tied), "ranking": ranking}

    pair = ("torquer_lag", "output_filter")
    truths = [{"effect": e} for e in ("torquer_lag", "output_filter", "torquer_lag", "none", "k2")]
    verdicts = [
        verdict("cannot_tell", pair, tl=30.0, of=28.0),  # forced to torquer_lag: right
        verdict("cannot_tell", pair, tl=30.0, of=28.0),  # forced to torquer_lag: wrong
        verdict("torquer_lag"),  # named: right
        verdict("none"),  # no effect: not counted
        verdict("cannot_tell", ("k2", "k4")),  # another tie: left as it is (wrong)
    ]
    out = module.lag_forced_choice(truths, verdicts)
    assert out["forced_datasets"] == 2
    assert out["accuracy_forced"] == pytest.approx(2 / 4)
    p = 1 / (1 + np.exp(-1.0))  # |Δ| = 2 on the 2 ln B scale
    assert out["accuracy_expected_by_evidence"] == pytest.approx((2 * p + 1) / 4)
    assert out["evidence_gap_median"] == pytest.approx(2.0)
