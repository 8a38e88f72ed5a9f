"""What a discovered term means for a designer (`accel_jax.diagnose.step.consequence`):
each static map against the loop with the term simulated to rest (`term_record`), the
static gain K1 against the simulated output per g, and the entries' vibration errors and
limits; and the record that would excite a barely measured term (`excite`): its standard
errors against the closed form of a linear model, the terms it picks. Float64."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from accel_jax._data import NominalDevice
from accel_jax._servo import time_constant
from accel_jax._simulate.sequence import SequenceInputs, accel_moment
from accel_jax.diagnose.discovery_result import DiscoveredColumn, DiscoveryCandidate
from accel_jax.diagnose.step import terms
from accel_jax.diagnose.step.consequence import consequence, static_gain

H = 2.0  # V, the record's half span
C = 0.01


@pytest.fixture(autouse=True)
def _x64():
    with jax.enable_x64(True):
        yield


@pytest.fixture(scope="module")
def settle():
    """The settled output [V] of the loop under a constant external moment M̃ [V] with one
    term's coefficient set (20 loop time constants at 500 kHz)."""
    with jax.enable_x64(True):
        nominal = NominalDevice.reference(torquer_time_constant=0.0, filter_time_constant=0.0)
        params = nominal.params
        dt, n, m = 2e-6, 100, 60
        scales = terms.Scales(H, float(time_constant(params)), dt * (n * m - 1), 2e3 * np.pi)
        names = [t.name for t in terms.TERMS]

        @jax.jit
        def settled(moment, coefficients):
            seq = SequenceInputs(
                0.0, 1.0, moment, 0.0, 0.0, 0.0, jnp.array([0]), jnp.array([0.0]),
                jnp.array([0.0]),
            )
            return terms.term_record(params, dt, n, m, seq, coefficients, scales)[-1]

        def run(name, c, moment):
            column = terms.columns((names.index(name),))[0]
            coefficients = jnp.zeros(terms.N_COEFFICIENTS).at[column].set(c)
            return float(settled(moment, coefficients))

        yield nominal, run


def test_static_gain_is_the_simulated_output_per_g(settle):
    nominal, run = settle
    per_g = float(accel_moment(nominal.params))
    assert static_gain(nominal) == pytest.approx(run("forcing_ramp", 0.0, per_g), rel=1e-9)


@pytest.mark.parametrize(
    "name, shift",
    [
        ("torquer_asymmetry", lambda y: C * abs(y)),
        ("spring_square", lambda y: C * y * y / H),
        ("output_square", lambda y: C * y * y / H),
        ("spring_cube", lambda y: C * y**3 / H**2),
        ("torquer_square", lambda y: -C * y * abs(y) / H),
        ("torquer_dead_zone", lambda y: -C * H * np.sign(y)),
    ],
)
def test_static_maps_against_the_loop_at_rest(settle, name, shift):
    _, run = settle
    for moment in (1.0, -1.0, 2.0, -2.0):
        y0 = run(name, 0.0, moment)
        dy = run(name, C, moment) - y0
        # First order in c: the maps' error is O(c²) of the shift itself.
        assert dy == pytest.approx(shift(y0), rel=0.04, abs=1e-6), (name, moment)


def test_pickoff_terms_leave_almost_nothing_at_rest(settle):
    _, run = settle
    for name in ("pickoff_square", "pickoff_cube", "pickoff_abs"):
        y0 = run(name, 0.0, 2.0)
        assert abs(run(name, C, 2.0) - y0) < 0.01 * C * y0 * y0 / H


def _column(term, coefficient, sigma=0.0):
    """A discovered column (only its term, coefficient and σ read here)."""
    return DiscoveredColumn(term, "", "", "", coefficient, sigma)


def _candidate(terms, columns):
    """A refitted subset (only its terms and columns read here)."""
    return DiscoveryCandidate(
        tuple(terms), tuple(columns), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, False, 0.0, True, 1.0
    )


def test_consequence_entries(settle):
    nominal, _ = settle
    k1 = static_gain(nominal)
    columns = [
        _column("torquer_asymmetry", 2e-4),
        _column("spring_square", 1e-3),
        _column("spring_cube", -1e-3),
        _column("output_pole", 0.1),
        _column("forcing_sinusoid (sin)", 0.1),
    ]
    out = consequence(columns, H, nominal)
    asym, k2, k3, pole, tone = out
    assert asym["static"]["coefficient"] == "asymmetry"
    assert asym["static"]["value"] == pytest.approx(4e-4)
    assert k2["static"]["value"] == pytest.approx(1e-3 * k1 / H)
    assert k3["static"]["value"] == pytest.approx(-1e-3 * k1**2 / H**2)
    # An asymmetry A1 under a mean 2 g (more than the vibration's sine + 2σ most of the
    # time) gives about A1/2·E[|a + v| − |a|]: smaller than A1/2·(0.5 + 1.4·0.8) g.
    error = asym["static"]["vibration_error_ug"] * 1e-6
    assert 0 < error < 2e-4 * (0.5 + 1.4 * 0.8)
    assert asym["static"]["within_limit"] == (4e-4 <= asym["static"]["paper_limit_ppm"] * 1e-6)
    assert pole["static"] is None and "dynamic" in pole["text"]
    assert tone["static"] is None and "disturbance" in tone["text"]
    assert all(isinstance(e["text"], str) and e["text"] for e in out)



def test_excite_standard_errors_against_the_closed_form():
    # A model linear in everything: y = θ₀ + a² c x (x a fixed signal, a the step factor),
    # θ₀ under a unit normal prior, the floor σ: σ_c from the 2×2 information exactly.
    import equinox as eqx

    from accel_jax.diagnose.step import excite

    class Linear(eqx.Module):  # the record's model's interface (`term_model.RecordModel`)
        x: jax.Array

        def prediction(self, theta, c, scales, amplitude):
            return theta[0] + amplitude**2 * c[0] * self.x

        def penalties(self, theta):
            return theta

    x = jnp.linspace(-1.0, 1.0, 50) ** 2
    sigma = 0.1
    pick = jnp.eye(1)
    errors = excite.standard_errors(
        Linear(x), jnp.zeros(1), jnp.asarray([0.3]), pick, None, sigma, (1.0, 2.0)
    )
    for row, a in zip(errors, (1.0, 2.0), strict=True):
        j = np.stack([np.ones(50), a**2 * np.asarray(x)], axis=1) / sigma
        info = j.T @ j + np.diag([1.0, 0.0])
        assert row[0] == pytest.approx(np.sqrt(np.linalg.inv(info)[1, 1]), rel=1e-10)
    assert errors[1, 0] == pytest.approx(errors[0, 0] / 4, rel=1e-10)
    # A second model of the same shape runs the same compiled Jacobians (the model is an
    # argument, not a constant of the program: records of one layout share it).
    size = excite._jacobians._cached._cache_size()
    again = excite.standard_errors(
        Linear(2 * x), jnp.zeros(1), jnp.asarray([0.3]), pick, None, sigma, (1.0, 2.0)
    )
    assert excite._jacobians._cached._cache_size() == size
    assert again[0, 0] == pytest.approx(errors[0, 0] / 2, rel=1e-10)


def test_excite_picks_the_barely_measured_terms():
    from accel_jax.diagnose.step import excite

    def cand(terms, values):
        columns = [_column(t, c, s) for t, (c, s) in zip(terms, values, strict=True)]
        return _candidate(terms, columns)

    best = cand(["pickoff_cube"], [(0.1, 1e-4)])
    pair = cand(["pickoff_square", "pickoff_cube"], [(-0.12, 0.05), (0.08, 0.02)])
    other = cand(["pickoff_abs"], [(0.025, 0.01)])  # weak, but not beside the best
    noise = cand(["pickoff_abs", "pickoff_cube"], [(0.01, 0.01), (0.1, 1e-4)])  # z = 1
    weak = excite.weak_terms(best, None, [best, pair, other, noise])
    assert [(c.terms, i) for c, i in weak] == [(("pickoff_square", "pickoff_cube"), 0)]
    scale = excite.StepScale(factor=2.0, deflection_V=3.2, stop_V=4.0)
    e = excite.entry("pickoff_square", pair, -0.12, 0.05, 0.01, scale)
    assert e["z_here"] == pytest.approx(2.4) and e["z_excited"] == pytest.approx(12.0)
    assert "beside pickoff_cube" in e["text"] and e["records_for_z5"] == 1
    assert (e["step_factor"], e["deflection_V"], e["stop_voltage_V"]) == (2.0, 3.2, 4.0)
    assert "the same steps ×2 (deflection to 3.2 V" in e["text"]
    slow = excite.entry("pickoff_square", pair, -0.12, 0.05, 0.048, scale)
    assert slow["records_for_z5"] == 4 and "4 such records" in slow["text"]  # (5/2.5)²
