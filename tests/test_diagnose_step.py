"""The sim-to-real diagnosis of step records (accel_jax.diagnose.step and its modules,
with the shared base: evidence, held-out gap, Ljung-Box) and its CLI command, checked on
records of the independent SciPy truth simulator (studies/step_truth.py: its own loop
equations and conventions, never the diagnosis's model): every verdict, every nuisance,
the domain check."""

import dataclasses
import json
import sys
from pathlib import Path
from types import SimpleNamespace

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest
from click.testing import CliRunner
from scipy import stats

import accel_jax as aj
from accel_jax._data import StepData, write_csv
from accel_jax._simulate.sequence import SequenceInputs, linear_record
from accel_jax.cli import main
from accel_jax.diagnose import (
    CandidateFit,
    diagnose_many,
    held_out_gap,
    ljung_box,
    rank_candidates,
)
from accel_jax.diagnose.step.assess import NESTED_LNL_SLACK, NESTED_RESTART_ABOVE
from accel_jax.diagnose.step.entry import DOMAIN_NOTE

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "studies"))
import colored_truth  # noqa: E402
import step_truth  # noqa: E402

RATE = 500e3  # Hz: blocks of 5 samples (T/30 of the reference device)
SEGMENT = 2e-3  # s
U = 2.0  # V
SIGMA = 4e-4  # V
LEVELS = (0.0, 1.0, -1.0, 0.0, 1.0, 0.0)
GAIN = 2.5e5 * 8.5  # k_dp k_y [V/m]


def _record(seed, *, device=None, moment_gm=None, levels=LEVELS, **record):
    """A record of the independent simulator: changes at arbitrary times between samples
    (a DAC on its own clock), `u_test` sampled, the reference device off by ~1σ; `levels`
    the test sequence in units of U.
    `moment_gm` (ratio, τ [s]): a Gauss–Markov moment inside the loop whose part of the
    output has `ratio` × the white noise's σ (studies/colored_truth.py)."""
    rng = np.random.default_rng(seed)
    times = np.arange(1, len(levels)) * SEGMENT * RATE + rng.uniform(-1, 0, len(levels) - 1)
    options = {"noise": SIGMA, "moment": 1e-6, **record}
    rec = step_truth.Record(
        levels=np.asarray(levels) * U,
        change_times=times / RATE,
        rate=RATE,
        n=int(round(len(levels) * SEGMENT * RATE)),
        **options,
    )
    values = {
        "J": 7.09e-9 * 1.04,
        "mu": 2.54e-5 * 0.96,
        "c": 3.02e-4 * 1.05,
        "k_dm": 9.23e-6 * 0.97,
        # The reference device's own lags (the default nominal takes them as known).
        "T_dm": 1e-5,
        "T_f": 1e-5,
    }
    dev = step_truth.Device(**{**values, **(device or {})})
    if moment_gm is not None:
        ratio, tau = moment_gm
        sigma = colored_truth.moment_sigma_for_output_std(dev, tau, ratio * SIGMA)
        t, u, y = colored_truth.simulate(dev, rec, rng=rng, moment_gm=(sigma, tau))
        return StepData(t - t[0], u, y)
    t, u, y = step_truth.simulate(dev, rec, rng=rng)
    return StepData(t - t[0], u, y)


CASES = {
    "clean": {},
    # Every convention the library's own records never have, at once.
    "clean_conventions": dict(
        device={"test_gain": -1.02},
        output_sign=-1.0,
        output_offset=0.04,
        adc_step=20 / 2**16,
        start=4e-4,
        start_level=-U,
    ),
    "torquer_lag": dict(device={"T_dm": 4e-5}),
    "output_filter": dict(device={"T_f": 4e-5}),
    "stop_saturation": dict(device={"h_max": 0.95 * U * 0.996 / GAIN}),
    "disturbance_drift": dict(moment_rate=2e-7 / 12e-3),
    "colored_noise": dict(gm=(1.5 * SIGMA, 1e-4)),
    "pickoff_nonlinearity": dict(
        device={
            "pickoff_p2": 0.06,
            "pickoff_p3": -0.05,
            "pickoff_reference_rad": U / GAIN / 4.28e-3,
        }
    ),
    "periodic_disturbance": dict(vibration=(2.0, 1300.0, 0.3)),
    "bandpass_sensor": dict(bandpass=(2 * np.pi * 300, 0.5, 1e-3)),
    "other_device": dict(device={"J": 3 * 7.09e-9}),
    # Gauss–Markov output noise 12× the white noise's σ (issue 44 item 2).
    "colored_noise_strong": dict(gm=(12 * SIGMA, 2e-4)),
    # A Gauss–Markov moment inside the loop, its output part 3× the white noise's σ: the
    # loop filters it, and only the moment-noise model describes it.
    "moment_noise": dict(moment_gm=(3.0, 2e-4)),
}


@pytest.fixture(scope="module")
def diagnosed(step_cases):
    # Records of one length and test sequence: one compiled fit for all of them (made once
    # per session, tests/conftest.py, and shared with test_diagnose_step_measured.py). The
    # next experiment of a lag tie is tested in test_diagnose_step_set.py and below.
    return step_cases


def _entry(result, effect):
    return next(e for e in result.ranking if e["effect"] == effect)


def test_none_on_clean_records_whatever_the_conventions(diagnosed):
    for name in ("clean", "clean_conventions"):
        _, result = diagnosed[name]
        assert result.verdict == "none", (name, result.summary())
        assert result.gap["rms_before"] < 1.5 * result.remaining_gap["noise_floor_V"]
        assert "noise floor" in result.reason
    _, result = diagnosed["clean"]
    truth = {"moment_of_inertia": 7.09e-9 * 1.04, "damping": 2.54e-5 * 0.96}
    for field, value in truth.items():  # the refit moves the ~1σ-off values toward the truth
        entry = result.refit["parameters"][field]
        assert abs(entry["refitted"] / value - 1) < abs(entry["nominal"] / value - 1)


def test_the_default_device_as_given_is_none_and_its_lags_are_known():
    """A record of `ServoParams.reference()` itself (T_dm = T_f = 10 µs), simulated by the
    library as the README shows, diagnosed against the default nominal: nothing is missing.
    The same record against a nominal that claims ideal lags is told apart (the lags are
    departures from the nominal device, never silently zeroed); a device whose torquer lag
    is 3× the data sheet's names the lag with a credible refit of J, μ, c, k_dm."""
    import jax

    from accel_jax._data import NominalDevice

    ts = np.arange(1200) / 100e3
    u = np.repeat(np.array([0.0, 1.0, 0.0, -1.0, 1.0, 0.0]) * 2.0, 200)
    rng = np.random.default_rng(4)

    def record(**values):
        params = aj.ServoParams.reference(**values)
        y = aj.simulate_linear(params, jnp.asarray(ts), jnp.asarray(u), key=jax.random.key(0))
        return StepData(ts, u, np.asarray(y) + 3e-4 * rng.normal(size=ts.size))

    default, slow = record(), record(torquer_time_constant=3e-5)
    as_given, slow_lag = diagnose_many([default, slow])
    assert as_given.verdict == "none", as_given.summary()
    assert "T_dm 10 µs, T_f 10 µs" in as_given.refit["description"]
    for entry in as_given.refit["parameters"].values():
        assert abs(entry["shift_sigma"]) < 2
    named = slow_lag.verdict == "torquer_lag" or (
        slow_lag.verdict == "cannot_tell" and "torquer_lag" in slow_lag.tied
    )
    assert named, slow_lag.summary()
    if slow_lag.verdict == "cannot_tell" and set(slow_lag.tied) == {"torquer_lag", "output_filter"}:
        # The single-record tie carries the experiment that would break it.
        assert slow_lag.next_experiment, slow_lag.summary()
        assert slow_lag.next_experiment[0]["expected_2lnB"] > 10
        assert "next_experiment" in slow_lag.to_dict()
    assert slow_lag.refit["model"] in [*slow_lag.tied, "torquer_lag"]
    for entry in slow_lag.refit["parameters"].values():  # the device, not a compensation
        assert abs(entry["shift_sigma"]) < 3, slow_lag.summary()
    lag = _entry(slow_lag, "torquer_lag")["params"]
    assert lag["torquer_time_constant_s"] == pytest.approx(3e-5, rel=0.15)
    assert lag["nominal_torquer_time_constant_s"] == pytest.approx(1e-5)
    ideal = NominalDevice.reference(torquer_time_constant=0.0, filter_time_constant=0.0)
    claimed_ideal = diagnose_many([default], ideal)[0]
    assert claimed_ideal.verdict != "none", claimed_ideal.summary()


def test_nuisances_are_fitted_not_assumed(diagnosed):
    _, result = diagnosed["clean_conventions"]
    nuisances = result.refit["nuisances"]
    # Polarity: reversed test winding and inverting recorder cancel; the output offset,
    # the ADC step and the start in a transient are found.
    assert nuisances["test_winding_polarity"] == "as the nominal"
    assert nuisances["test_winding_gain"] == pytest.approx(1.02, rel=0.02)
    assert nuisances["adc_step_V"] == pytest.approx(20 / 2**16, rel=1e-6)
    assert abs(nuisances["initial_displacement_V"]) > 0.1  # a record that starts moving
    shifts = np.asarray(nuisances["change_time_shift_samples"])
    assert np.all(shifts < 0.1) and np.all(shifts > -1.1)  # between samples, before t_i
    _, plain = diagnosed["clean"]
    assert plain.refit["nuisances"]["test_winding_polarity"] == "as the nominal"
    reversed_only = diagnose_many([_record(3, device={"test_gain": -1.0})])[0]
    assert reversed_only.verdict == "none", reversed_only.summary()
    assert reversed_only.refit["nuisances"]["test_winding_polarity"] == "reversed"


@pytest.mark.parametrize(
    "case, name, tolerance",
    [
        ("stop_saturation", "stop_V", 0.01),
        ("disturbance_drift", "moment_rate_Nm_per_s", 0.15),
        ("colored_noise", "correlation_time_s", 0.35),
    ],
)
def test_effect_named_and_recovered(diagnosed, case, name, tolerance):
    _, result = diagnosed[case]
    assert result.verdict == case, result.summary()
    truth = {
        "stop_V": 0.95 * U * 0.996,
        "moment_rate_Nm_per_s": 2e-7 / 12e-3,
        "correlation_time_s": 1e-4,
    }[name]
    assert _entry(result, case)["params"][name] == pytest.approx(truth, rel=tolerance)
    # A deterministic effect removes its misfit; a noise's free-run errors only match its
    # variance to sampling error: with τ_c = 1e-4 s over 400 held-out 10 µs block means
    # there are ~20 independent samples, so the variance is known to ±30 % (1σ).
    assert result.explained_fraction > (0.5 if case == "colored_noise" else 0.9)
    # The named effect's own fit judged by the joint nuisance test (the nominal refit of
    # this stop record strains a change time at ~ −4.5σ; the effect's fit does not).
    own = result.refit["effect_nuisance_test"]
    assert own is not None and not own["strained"], own
    assert "Its own fit needs strained nuisances" not in result.reason


def test_lags_named_or_honestly_tied(diagnosed):
    for case in ("torquer_lag", "output_filter"):
        _, result = diagnosed[case]
        ok = result.verdict == case or (result.verdict == "cannot_tell" and case in result.tied)
        assert ok, result.summary()
        key = "torquer_time_constant_s" if case == "torquer_lag" else "filter_time_constant_s"
        assert _entry(result, case)["params"][key] == pytest.approx(4e-5, rel=0.2)
        assert result.gap["shrink"] > 0.9


def test_outside_the_library_unexplained_with_a_reason(diagnosed):
    for case in ("pickoff_nonlinearity", "periodic_disturbance", "bandpass_sensor"):
        _, result = diagnosed[case]
        assert result.verdict == "unexplained", result.summary()
        assert result.remaining_gap["over_floor"] > 3
        assert result.reason
    _, periodic = diagnosed["periodic_disturbance"]
    assert "periodic" in periodic.reason  # correlated noise would absorb it: refused
    # Without `discover` (diagnose_many's default) no missing term is searched for.
    assert periodic.discovery is None and "discovered" not in periodic.summary()
    assert _entry(periodic, "colored_noise")["deterministic_misfit"]
    _, bandpass = diagnosed["bandpass_sensor"]
    assert "returns to its previous level" in bandpass.reason  # the domain check
    assert bandpass.where["domain"]["settled_over_excursion"] < 0.4
    # Outside the model family: no effect fitted, the nominal alone (its gap above).
    assert bandpass.ranking == [] and DOMAIN_NOTE in bandpass.notes
    assert bandpass.gap["model_after"] == "nominal"


def test_strong_output_noise_is_named_and_its_size_recovered(diagnosed):
    # Gauss–Markov output noise 12× the white noise. Its block means are ARMA(1,1) with a
    # moving-average part of the other sign than white + AR(1)'s; modelled as white +
    # AR(1) on the block means, the held-out one-step errors failed Ljung–Box and the
    # record read unexplained (before `effects.block_noise`).
    _, result = diagnosed["colored_noise_strong"]
    assert result.verdict == "colored_noise", result.summary()
    params = _entry(result, "colored_noise")["params"]
    assert params["correlation_time_s"] == pytest.approx(2e-4, rel=0.35)
    assert params["sigma_correlated_per_sample_V"] == pytest.approx(12 * SIGMA, rel=0.3)
    # The white part (0.14 % of a block mean's variance here) is not asserted: it read
    # 5.4e-4 V against the truth's 4e-4 V, and the fit gives no standard error for it.


def test_a_nested_fit_is_judged_on_its_training_likelihood_and_a_flag_is_shown(diagnosed):
    # The strong coloured noise's record: its stop fit's reported ln L ended ~1,800 below
    # the nominal's (evidence −3,668) while the ln L read the training samples after the
    # held-out change times had moved; the solver's objective, at the training optimum,
    # was better than the nominal's. Read at the training optimum, no nested fit ends
    # below the nominal model it contains, and the stop, which fits the training part
    # better (evidence > 0) but predicts the held-out part worse, is not significant.
    _, result = diagnosed["colored_noise_strong"]
    assert result.verdict == "colored_noise", result.summary()
    stop = _entry(result, "stop_saturation")
    assert not stop["fit_failed"] and stop["evidence"] > 0, result.summary()
    assert stop["gap_shrink"] < 0 and not stop["significant"], stop
    assert all(e["log_likelihood_below_nominal"] <= NESTED_LNL_SLACK for e in result.ranking)
    # A flagged entry is never ranked as evidence: failed in the solver (the objective's
    # `nested_failed`), shown failed with both shortfalls; one whose reported ln L alone
    # ended below (`assess.reported_below`) is reported at its no-effect value
    # (`rescale.settle_at_no_effect`), shown with its evidence and its optimum's shortfall.
    entry = {**stop, "fit_failed": True, "solver_failed": True, "objective_below_nominal": 4.2,
             "log_likelihood_below_nominal": 1830.0}
    shown = dataclasses.replace(result, ranking=[*result.ranking, entry]).summary()
    assert "stop_saturation    fit failed (ended 4.2 below the nominal model's" in shown
    assert "1.83e+03 below its reported ln L" in shown
    entry = {**stop, "evidence": -9.2, "gap_shrink": 0.0, "at_no_effect": True,
             "optimum_log_likelihood_below_nominal": 1830.0}
    shown = dataclasses.replace(result, ranking=[*result.ranking, entry]).summary()
    assert ("stop_saturation    evidence       -9.2  shrink +0.00  (at its no-effect value: "
            "the solver's optimum ended 1.83e+03 below the nominal's ln L)") in shown, shown
    assert "fit failed" not in shown
    # No fit is flagged on the clean records (their shortfalls ≤ 0.8 ln L).
    for name in ("clean", "clean_conventions"):
        assert not any(e["fit_failed"] for e in diagnosed[name][1].ranking), name


def test_no_nested_fit_ends_below_the_nominal_by_more_than_the_restart_threshold(diagnosed):
    # A fit ends at the first point that passes the Newton-decrement test, short of its
    # optimum by up to about that test's bound; a linear candidate that ends more than
    # `NESTED_RESTART_ABOVE` below the nominal (or the round-off share of its objective)
    # is refitted from the nominal optimum. When only a shortfall above `NESTED_ABSOLUTE`
    # (1e-3) was restarted, the clean record's colored_noise fit ended 1.9e-6 below the
    # nominal, unflagged; with the threshold, the largest over these cases is 4.4e-8.
    for name, (_, result) in diagnosed.items():
        for entry in result.ranking:
            assert entry["objective_below_nominal"] <= NESTED_RESTART_ABOVE, (name, entry)


def test_records_no_linear_model_brings_near_the_floor_are_fitted_at_their_scale(diagnosed):
    # `rescale.REWEIGHT_ABOVE`: a record that no linear candidate fits to within twice its
    # floor has its linear fits made again at the nominal's residual scale, and there no
    # nested fit ends below the nominal's reported ln L (at the floor the stop record's
    # torquer_lag ended 39 below). The clean records and those a linear model explains (a
    # lag, a drift) stay at the floor; so does the different device, whose nominal refit
    # reaches the floor from its own optimum in the restarts (its moment of inertia far
    # from the prior) before the rescale is judged. The band-pass record, which fails the
    # domain check, has no effect fitted, so nothing to rescale (`entry.DOMAIN_NOTE`).
    note = "linear models fitted at the record's residual scale"
    rescaled = {
        name for name, (_, result) in diagnosed.items() if any(note in n for n in result.notes)
    }
    assert {"stop_saturation", "pickoff_nonlinearity"} <= rescaled
    assert not rescaled & {
        "clean", "clean_conventions", "torquer_lag", "output_filter", "disturbance_drift",
        "other_device", "bandpass_sensor",
    }
    for name in rescaled:
        assert not any(e["fit_failed"] for e in diagnosed[name][1].ranking), name
    assert diagnosed["stop_saturation"][1].verdict == "stop_saturation"  # its stop fit at the floor


def test_moment_noise_inside_the_loop_is_named_at_its_place(diagnosed):
    # A Gauss–Markov moment inside the loop, its output part 3× the white noise's σ: the
    # loop filters it (a correlation time near the loop's own), so the output noise model
    # leaves coloured one-step errors (Ljung–Box fails on the held-out part) and only the
    # moment-noise model, a Kalman filter of the fitted loop, whitens them. Before
    # `moment_noise` the record read unexplained.
    _, result = diagnosed["moment_noise"]
    assert result.verdict == "moment_noise", result.summary()
    output = _entry(result, "colored_noise")
    assert output["significant"] and not output["explains"]
    assert not output["one_step_whiteness"]["white"]
    params = _entry(result, "moment_noise")["params"]
    assert params["correlation_time_s"] == pytest.approx(2e-4, rel=0.35)
    assert params["sigma_correlated_per_sample_V"] == pytest.approx(3 * SIGMA, rel=0.3)


def test_a_noise_not_credited_says_which_of_its_checks_failed():
    # The summary of an unexplained record whose best partial is a noise model says which
    # of the noise's checks failed, not the free-run gap's "explains N % of the excess",
    # which a noise model cannot close (it read "explains 100 %; 0 V remains" beside the
    # verdict unexplained on blind records).
    from accel_jax.diagnose.openworld import Whiteness
    from accel_jax.diagnose.step.effects import ColoredNoise
    from accel_jax.diagnose.step.verdict import _noise_not_credited

    fit = SimpleNamespace(
        one_step_whiteness=Whiteness(80.0, 20, 1e-9, False, 1e-3),
        variance_consistent=False,
        free_run_over_noise_variance=[1.2, 6.5],
        model=ColoredNoise(),
    )
    text = _noise_not_credited("colored_noise", fit, SimpleNamespace(evidence=812.0))
    assert "colored_noise" in text and "812.0" in text
    assert "one-step prediction errors on the held-out part are not white" in text
    assert "p = 1e-09 over 20 lags" in text
    assert "not of the size it predicts" in text and "1.2, 6.5" in text
    assert "of the excess" not in text
    fit.one_step_whiteness = Whiteness(12.0, 20, 0.9, True, 1e-3)
    fit.variance_consistent = True
    entry = SimpleNamespace(evidence=1.0)
    assert "not significant and credible" in _noise_not_credited("colored_noise", fit, entry)


def test_a_different_device_is_never_none(diagnosed):
    _, result = diagnosed["other_device"]
    assert result.verdict != "none"
    if result.verdict == "unexplained":
        assert "moment_of_inertia" in result.reason or "remains" in result.reason
    # Its refit rests past the bound (three times the moment of inertia): a nested fit that
    # eased it at the cost of its reported ln L is reported at its no-effect value
    # (`rescale.settle_at_no_effect`), and the record says why; no fit is flagged unless it
    # failed in the solver, and no other case, every refit within its bound, says so.
    assert not any(e["fit_failed"] and not e["solver_failed"] for e in result.ranking)
    settled = [e["effect"] for e in result.ranking if e["at_no_effect"]]
    said = [n for n in result.notes if "rests past its bound" in n]
    assert bool(settled) == bool(said), result.summary()
    if settled:
        assert "moment_of_inertia +" in said[0] and all(f in said[0] for f in settled)
        assert all(
            e["evidence"] < 0 and not e["significant"] and e["gap_shrink"] == 0
            for e in result.ranking if e["at_no_effect"]
        ), result.ranking
    for name, (_, other) in diagnosed.items():
        if name != "other_device":
            assert not any("rests past its bound" in n for n in other.notes), name


def test_time_scale_domain_check():
    # A slow sensor (seconds, not 0.3 ms) recorded at 1 kHz: refused with the time scales.
    t = np.arange(6000) * 1e-3
    u = np.where((t >= 1) & (t < 3), 1.0, 0.0) + np.where(t >= 4, -1.0, 0.0)
    y = np.zeros_like(t)
    for tau, step in ((1.0, 1.0), (3.0, -1.0), (4.0, -1.0)):
        y += step * (t > tau) * (1 - np.exp(-np.clip(t - tau, 0, None) / 0.3))
    y += 1e-3 * np.random.default_rng(0).normal(size=t.size)
    result = diagnose_many([StepData(t, u, y)])[0]
    assert result.verdict == "unexplained"
    assert "time scales" in result.reason and "--params" in result.reason
    # The nominal's rise (~0.4 ms) is under the 1 ms sample period: the ratio (to the
    # period) is said to be a lower bound, not set beside the unresolved rise as if exact.
    assert "under one sample period (1 ms): time scales at least" in result.reason
    # No effect is fitted outside the model family: the nominal alone, said so (before, the
    # effects were fitted, restarted and reweighted here for a ranking the verdict never
    # read: 57.1 s of diagnosis against 12.3 s, warm, docs/performance.md).
    assert result.ranking == [] and DOMAIN_NOTE in result.notes
    assert "ranking: none (see the notes)" in result.summary()
    assert result.to_dict()["ranking"] == []


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
    data, _ = diagnosed["stop_saturation"]
    csv = write_csv(tmp_path / "rec.csv", data)
    out_json, out_png = tmp_path / "d.json", tmp_path / "d.png"
    result = CliRunner().invoke(
        main, ["diagnose", str(csv), "--json", str(out_json), "--plot", str(out_png)]
    )
    assert result.exit_code == 0, result.output
    assert "verdict: stop_saturation" in result.output and "why: " in result.output
    doc = json.loads(out_json.read_text())
    assert set(doc) >= {
        "kind",
        "verdict",
        "ranking",
        "gap",
        "where",
        "refit",
        "reason",
        "explained_fraction",
        "remaining_gap",
    }
    assert doc["kind"] == "step" and doc["verdict"] == "stop_saturation"
    assert set(doc["gap"]) >= {"metric", "before", "after", "shrink"}
    assert set(doc["ranking"][0]) >= {"effect", "evidence", "gap_shrink", "params"}
    assert out_png.stat().st_size > 10_000


def test_cli_diagnose_unexplained_and_rounded_timestamps(diagnosed, tmp_path):
    data, _ = diagnosed["bandpass_sensor"]
    text = "t,u_test,u_out\n" + "\n".join(
        f"{t:.6f},{float(u)!r},{float(y)!r}"
        for t, u, y in zip(data.t, data.u_test, data.u_out, strict=True)
    )
    csv = tmp_path / "rounded.csv"
    csv.write_text(text)  # 2 µs steps written to 1 µs: no rounding
    result = CliRunner().invoke(main, ["diagnose", str(csv)])
    assert result.exit_code == 0, result.output
    assert (
        "verdict: unexplained" in result.output and "returns to its previous level" in result.output
    )
    coarse = "t,u_test,u_out\n" + "\n".join(
        f"{t * 1.37:.6f},{float(u)!r},{float(y)!r}"
        for t, u, y in zip(data.t, data.u_test, data.u_out, strict=True)
    )
    csv.write_text(coarse)  # 2.74 µs written to 1 µs: up to 18 % of an interval
    result = CliRunner().invoke(main, ["diagnose", str(csv)])
    assert result.exit_code != 0 and "sample intervals off the uniform grid" in result.stderr
    assert "Traceback" not in result.output + result.stderr


def _grid():
    n = int(round(len(LEVELS) * SEGMENT * RATE))
    u = np.repeat(np.asarray(LEVELS) * U, n // len(LEVELS))
    return np.arange(u.size) / RATE, u


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
        "flat output": good,  # u_out constant: a disconnected channel
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
    kept = tmp_path / "kept.json"
    kept.write_text("{}")  # a user's file is not replaced unasked (and nothing is run)
    result = CliRunner().invoke(main, ["diagnose", str(csv), "--json", str(kept)])
    assert result.exit_code != 0 and "--force" in result.stderr and kept.read_text() == "{}"


# --- the study ----------------------------------------------------------------------------


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
    index, steps, shift = jnp.array([500, 2000]), jnp.array([2.0, -2.0]), jnp.zeros(2)

    def record(params):
        return linear_record(
            params, 5e-6, 3000, SequenceInputs(-1.0, 1.0, 0.1, 0.0, 0.0, 0.0, index, steps, shift)
        )

    y_lag, y_filter = record(lagged), record(filtered)
    # Same record to rounding, though the two loops differ by a damping shift of ~6.6 %...
    assert float(jnp.max(jnp.abs(y_lag - y_filter))) < 1e-9 * float(jnp.max(jnp.abs(y_lag)))
    assert abs(mu2 / mu - 1) > 0.05
    # ...which to first order in T is Δμ = k_dm k_dp k_y l·T, as the summary note says.
    assert (mu - mu2) == pytest.approx(K * tdm, rel=0.05)
    # And the no-lag loop differs from both by far more than the rounding above.
    y_none = record(eqx.tree_at(lambda p: p.torquer_time_constant, lagged, 0.0))
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
    effects = ("torquer_lag", "output_filter", "torquer_lag", "none", "k2", "stop_saturation")
    truths = [{"effect": e} for e in effects]
    verdicts = [
        verdict("cannot_tell", pair, tl=30.0, of=28.0),  # forced to torquer_lag: right
        verdict("cannot_tell", pair, tl=30.0, of=28.0),  # forced to torquer_lag: wrong
        verdict("torquer_lag"),  # named: right
        verdict("none"),  # no effect: not counted
        verdict("cannot_tell", ("k2", "k4")),  # another tie: left as it is (wrong)
        # A member of the truth's family is named, as the confusion's scoring counts it (a
        # compliant stop named for an inelastic one: 5 such records read as misses here).
        verdict("stop_contact"),
    ]
    out = module.lag_forced_choice(truths, verdicts)
    assert out["forced_datasets"] == 2
    assert out["accuracy_forced"] == pytest.approx(3 / 5)
    p = 1 / (1 + np.exp(-1.0))  # |Δ| = 2 on the 2 ln B scale
    assert out["accuracy_expected_by_evidence"] == pytest.approx((2 * p + 2) / 5)
    assert out["evidence_gap_median"] == pytest.approx(2.0)


def test_evidence_slack_in_the_likelihoods_units():
    # A nominal fit that stopped short: the Newton decrement D (cost in noise-floor units)
    # is worth about 2D of 2 ln L at the floor and far less when the fit misses widely.
    from accel_jax.diagnose.step.assess import evidence_slack

    n, sigma, decrement = 800, 1e-3, 5.0
    prep = SimpleNamespace(sigma=sigma)  # the `StepRecord` field it reads
    at_floor = SimpleNamespace(innovation_variance=sigma**2, decrement=decrement)
    assert evidence_slack(at_floor, prep, n) == pytest.approx(2 * decrement, rel=0.02)
    far = SimpleNamespace(innovation_variance=(500 * sigma) ** 2, decrement=decrement)
    assert evidence_slack(far, prep, n) == pytest.approx(2 * decrement / 500**2, rel=1e-3)
    whole = SimpleNamespace(innovation_variance=sigma**2, decrement=n)  # removes it all
    assert evidence_slack(whole, prep, n) == float("inf")


def test_later_stages_compiled_ahead_on_a_spare_cpu_change_nothing(monkeypatch, caplog):
    # With a CPU to spare, the loop noise's and the clamp's programs are compiled on a
    # background thread while the linear fits run (`_compile_ahead`); those stages then
    # compile nothing themselves, and the diagnosis is the one made with no CPU to spare,
    # to the bit. A record that nothing explains (a pickoff nonlinearity) reaches both and
    # the compliant contact's stage; its shape (three levels: 3,000 samples, 768 blocks
    # padded) is this test's own, so no other test has compiled its programs. (Five
    # levels, as before, cost 91.5 s alone against 60.7 s: the diagnosis is run-bound.)
    import logging
    import threading

    import jax

    from accel_jax._data import NominalDevice
    from accel_jax.diagnose.step import entry

    data = _record(3, levels=(0.0, 1.0, -1.0), **CASES["pickoff_nonlinearity"])
    found, compiled = {}, {}
    for spare in (True, False):
        monkeypatch.setattr(entry, "spare_cpu", lambda spare=spare: spare)
        caplog.clear()
        with jax.log_compiles(True), caplog.at_level(logging.DEBUG, logger="jax"):
            with jax.enable_x64(True):
                found[spare] = aj.diagnose.diagnose_step(
                    [data], NominalDevice.reference(), recommend=False
                )[0]
        compiled[spare] = [
            (r.thread == threading.get_ident(), r.getMessage()) for r in caplog.records
            if "Finished XLA compilation of jit(wrapped)" in r.getMessage()
        ]
    assert found[True].verdict == "unexplained"
    names = {e["effect"] for e in found[True].ranking}
    assert {"stop_saturation", "stop_contact"} <= names
    # The linear fits' and the contact's programs in the caller's thread; the loop
    # noise's and the clamp's in the background; none twice.
    assert [main for main, _ in compiled[True]].count(True) == 2
    assert [main for main, _ in compiled[True]].count(False) == 2
    assert compiled[False] == []  # every program compiled already, by the first diagnosis
    first, second = found[True].to_dict(), found[False].to_dict()
    first.pop("provenance", None), second.pop("provenance", None)
    assert first == second
