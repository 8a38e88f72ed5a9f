"""Discovery of a missing term on step records (`accel_jax.diagnose.step.discover`): the
simulator with terms against the exact linear record, its first-order effects against
finite differences, and discovery on records of the independent SciPy simulator
(studies/step_truth.py) whose effect lies outside the library (a pickoff nonlinearity, a
vibrating stand, from the command line), on a clean record, and on a library effect's record
as if the library lacked it (the output filter: its equivalent is the term `output_pole`)."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from accel_jax._data import NominalDevice
from accel_jax._simulate.sequence import SequenceInputs, linear_record
from accel_jax.diagnose.step import ceiling, term_model, terms
from accel_jax.diagnose.step.discover import STABLE
from accel_jax.diagnose.step.entry import diagnose_step

from test_diagnose_step import CASES, U, _record

import step_truth  # noqa: E402  (studies/, on the path once test_diagnose_step is imported)


@pytest.fixture(autouse=True)
def _x64():
    with jax.enable_x64(True):
        yield


def _sequence():
    return SequenceInputs(
        0.5, 1.02, 0.1, 0.01, 0.02, -0.01, jnp.array([200, 700, 1100]),
        jnp.array([1.0, -2.0, 0.7]), jnp.array([-0.3, 0.4, -0.9]),
    )


@pytest.mark.parametrize("lags", [(1e-5, 1e-5), (0.0, 0.0), (2e-5, 0.0)])
def test_at_zero_the_exact_linear_record(lags):
    params = NominalDevice.reference(
        torquer_time_constant=lags[0], filter_time_constant=lags[1]
    ).params
    dt, n, m = 2e-6, 300, 5
    duration = dt * (n * m - 1)
    exact = linear_record(params, dt, n, _sequence(), block=m, max_block=m, duration=duration)
    scales = terms.Scales(1.0, 1e-3, duration, 2 * np.pi * 1e3)
    mine = terms.term_record(params, dt, n, m, _sequence(), jnp.zeros(terms.N_COEFFICIENTS), scales)
    assert float(jnp.max(jnp.abs(mine - exact))) < 1e-12


def test_first_order_effects_against_finite_differences():
    params = NominalDevice.reference().params
    dt, n, m = 2e-6, 200, 5
    scales = terms.Scales(1.0, 1e-3, dt * (n * m - 1), 2 * np.pi * 1e3)

    def record(c):
        return terms.term_record(params, dt, n, m, _sequence(), c, scales)

    c0 = jnp.zeros(terms.N_COEFFICIENTS)
    jac = jax.jacfwd(record)(c0)
    h = 1e-6
    for k in range(terms.N_COEFFICIENTS):
        e = jnp.zeros(terms.N_COEFFICIENTS).at[k].set(h)
        central = (record(e) - record(-e)) / (2 * h)
        scale = float(jnp.max(jnp.abs(central))) + 1e-12
        assert float(jnp.max(jnp.abs(jac[:, k] - central))) < 1e-5 * scale, terms.TERMS
    # Every term reaches the output (none is a dead column).
    assert bool(jnp.all(jnp.max(jnp.abs(jac), axis=0) > 0))


@pytest.fixture(scope="module")
def discovered():
    # One batch (one compiled fit), discovery on every record (`discover="all"`). The
    # output-filter record is the leave-one-out case: its nominal fit, which discovery
    # starts from, is the same whatever the library holds, and discovery runs on it here
    # although the full library names its effect.
    names = ("pickoff_nonlinearity", "clean", "output_filter")
    data = [_record(1, **CASES[k]) for k in names]
    programs = (term_model.linearised, term_model.refit_at, term_model.refit_jacobian_at)
    before = [p._cached._cache_size() for p in programs]  # equinox's jit wrapper's own
    with jax.enable_x64(True):
        # (recommend=False: no test here reads a lag tie's next experiment, which the
        # output-filter record's tie would design, ~30 s; test_diagnose_step_set.py tests it)
        results = diagnose_step(
            data, NominalDevice.reference(), discover="all", recommend=False
        )
    # Three records of one layout: the discovery's programs compiled once per shape, not per
    # record (the record's model and arrays are their arguments, not constants).
    grown = [p._cached._cache_size() - b for p, b in zip(programs, before, strict=True)]
    return dict(zip(names, results, strict=True)), grown


def test_records_of_one_layout_share_the_discoverys_programs(discovered):
    # The screen (every entry of w free) compiles once for the three; the refit's shape is
    # its free entries', which a change time seen only by the held-out part leaves out:
    # here two shapes among three records (measured growth 1, 2, 2), one per record before.
    _, grown = discovered
    assert grown[0] <= 1 and all(g < 3 for g in grown[1:]), grown


def test_a_pickoff_nonlinearity_is_found_at_the_pickoff(discovered):
    # The truth: U_amp = G θ (1 + p2 x + p3 x²), x = θ/θ_ref, G θ_ref = U: in the terms'
    # units c2 = p2 h/U and c3 = p3 (h/U)² (h the training output's half range).
    result = discovered[0]["pickoff_nonlinearity"]
    assert result.verdict == "unexplained"  # the library did not contain it
    discovery = result.discovery
    best = discovery.best
    assert best is not None and discovery.rating in ("credible", "tentative")
    assert sorted(best.terms) == ["pickoff_cube", "pickoff_square"], result.summary()
    assert step_truth.Device().l == 4.28e-3  # so that G θ_ref = U in CASES
    ratio = discovery.scales.half_V / U
    truth = {"pickoff_square": 0.06 * ratio, "pickoff_cube": -0.05 * ratio**2}
    for column in best.columns:
        assert abs(column.coefficient - truth[column.term]) < 3 * column.sigma, column
        # Its σ from the profile likelihood, found on both sides; here the linearised σ is
        # far too wide (the model is strongly nonlinear along the square's trade-off).
        assert column.profile_found and column.interval is not None, column
        assert column.interval[0] < column.coefficient < column.interval[1], column
        assert column.sigma_linearised is not None and column.sigma < column.sigma_linearised
    assert best.explained_fraction > 0.9
    assert "discovered (hypothesis" in result.summary()
    assert result.to_dict()["discovery"] == discovery.to_dict()
    # At rest the loop's gain takes a pickoff's error: no coefficient of the static model.
    assert [c["static"] for c in best.consequence] == [None, None]
    assert "no static term" in result.summary()


def test_a_vibrating_stand_is_found_from_the_command_line(tmp_path, monkeypatch, discovered):
    # `accel-jax diagnose` looks for the missing term of an unexplained record by default
    # (`--no-discover`: not). A vibrating stand (2 m/s² at 1300 Hz): a sinusoidal moment.
    # (`discovered` is not read: asking for it runs this test on the fixture's pytest-xdist
    # worker after it, where the record's layout has every program of the diagnosis and the
    # discovery compiled and traced in this process; the command runs in-process.)
    from click.testing import CliRunner

    from accel_jax import write_csv
    from accel_jax.cli import main

    csv = write_csv(tmp_path / "rec.csv", _record(1, **CASES["periodic_disturbance"]))
    out_json = tmp_path / "d.json"
    # What `--ceiling` must do here is fit the network reference and state it beside the
    # term; how far the network gets is not checked (a forcing is outside what it can
    # represent), so its fit stops early (its second start ran to the 400-evaluation limit:
    # most of this test's time).
    monkeypatch.setattr(ceiling, "REFERENCE_MAX_EVALUATIONS", 30)
    result = CliRunner().invoke(
        main, ["diagnose", str(csv), "--ceiling", "--json", str(out_json)]
    )
    assert result.exit_code == 0, result.output
    assert "discovered (hypothesis, credible): forcing_sinusoid" in result.output
    doc = json.loads(out_json.read_text())
    assert doc["verdict"] == "unexplained"
    best = doc["discovery"]["best"]
    assert best["terms"] == ["forcing_sinusoid"]
    assert best["frequency_Hz"] == pytest.approx(1300.0, abs=1.0)
    assert best["held_out_at_floor"] and best["stability"] >= STABLE
    # What it means for a designer: a disturbance, no coefficient of the static model.
    assert all(c["static"] is None for c in best["consequence"])
    assert "for a designer: forcing_sinusoid" in result.output
    # `--ceiling`: the network reference fitted and stated beside the term (a forcing is a
    # term of time, outside what a function of the states represents).
    reference = doc["discovery"]["ceiling"]
    assert reference["parameters"] == ceiling.size() and 0 <= reference["explained_fraction"] <= 1
    if reference["explained_fraction"] > 0:
        ratio = best["explained_fraction"] / reference["explained_fraction"]
        assert best["ceiling_fraction"] == pytest.approx(ratio)
    assert "a network of the loop's states" in result.output
    # `--no-discover` reaches the library as discover=False. Checked on the call itself, not
    # by a second full diagnosis of the record (its saving in CI not measured).
    import accel_jax.diagnose

    class Plain:
        def summary(self):
            return "plain"

    calls = []

    def record_call(data, nominal, **options):
        calls.append(options)
        return Plain()

    monkeypatch.setattr(accel_jax.diagnose, "diagnose", record_call)
    plain = CliRunner().invoke(main, ["diagnose", str(csv), "--no-discover"])
    assert plain.exit_code == 0, plain.output
    assert calls == [{"discover": False, "ceiling": False}]


def test_nothing_credible_on_a_clean_record(discovered):
    result = discovered[0]["clean"]
    assert result.verdict == "none"
    assert result.discovery.rating != "credible"


def test_leave_one_out_the_output_filter_is_found_as_an_extra_lag(discovered):
    # The record's T_f is 40 µs against the nominal's 10 µs. The term library's equivalent
    # is an extra pole at the output (in series with the nominal's, so not exact); an extra
    # pole in the feedback path describes the record about as well (the lag tie of the
    # library's own two lags). (With `output_filter` removed from the library the verdict
    # is `torquer_lag`, its own nuisances within their priors; the nominal refit's input
    # delay is at −7σ: it takes up the lag the nominal lacks. Discovery starts from the
    # nominal fit, which the library changes only where a restart from its optimum
    # improves it.)
    discovery = discovered[0]["output_filter"].discovery
    assert {"torquer_pole", "output_pole"} & set(discovery.best.terms), discovery
    alone = next(c for c in discovery.candidates if c.terms == ("output_pole",))
    extra = alone.columns[0].coefficient * discovery.scales.period_s
    assert extra == pytest.approx(3e-5, rel=0.3)
    assert alone.explained_fraction > 0.9


def test_discover_refuses_an_unknown_mode():
    nominal = NominalDevice.reference()
    with pytest.raises(ValueError, match="discover must be False, True or 'all'"):
        diagnose_step([], nominal, discover="every")


def test_the_sinusoids_start_is_tuned_near_the_periodograms_peak():
    # A line 0.7 resolutions above where the periodogram peaked (a 672 Hz forcing of 12 ms
    # peaked at 615 Hz beside the nominal fit's own misfit): of the offsets scored, the one
    # nearest the line removes the most training χ² beside the nuisances (an offset and a
    # trend, under priors), and its columns are returned with it.
    from accel_jax.diagnose.step.discover import SINUSOID_OFFSETS, tuned_offset

    duration, n = 12e-3, 1200
    t = np.arange(n) * duration / n
    resolution = 2 * np.pi / duration
    peak = 2 * np.pi * 615.0
    line = peak + 0.7 * resolution
    rng = np.random.default_rng(3)
    sigma = 1e-3
    r = 4e-3 * np.sin(line * t + 0.4) + 2e-3 + sigma * rng.normal(size=n)
    free = np.stack([np.ones(n), t / duration], axis=1)
    train = np.arange(n) % 5 != 0  # a held-out sample in five

    def columns_at(offset):
        omega = peak + offset * resolution
        return np.stack([np.sin(omega * t), np.cos(omega * t)], axis=1)

    normal = (free[train] / sigma, r[train] / sigma, 0.1 * np.eye(2), np.zeros(2))
    offset, chosen = tuned_offset(columns_at, normal, train, sigma)
    nearest = SINUSOID_OFFSETS[np.argmin(np.abs(SINUSOID_OFFSETS - 0.7))]
    assert offset == nearest == 0.75
    np.testing.assert_array_equal(chosen, columns_at(0.75))
    # A line at the peak itself keeps its start.
    at_peak = 4e-3 * np.sin(peak * t + 0.4) + 2e-3 + sigma * rng.normal(size=n)
    normal = (free[train] / sigma, at_peak[train] / sigma, 0.1 * np.eye(2), np.zeros(2))
    assert tuned_offset(columns_at, normal, train, sigma)[0] == 0.0
