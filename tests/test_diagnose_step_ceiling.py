"""The network reference of what a term of the loop's states could remove
(`accel_jax.diagnose.step.ceiling`): nested exactly at its start, its residual entering the
loop where a term of the same form does, its weights' derivatives reaching the output, and
the option refused without a discovery. (On records: tests/test_diagnose_step_discover.py.)"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from accel_jax._data import NominalDevice
from accel_jax._simulate.sequence import SequenceInputs
from accel_jax.diagnose.step import ceiling, terms
from accel_jax.diagnose.step.entry import diagnose_step


@pytest.fixture(autouse=True)
def _x64():
    with jax.enable_x64(True):
        yield


DT, N, M = 2e-6, 200, 5
SEQUENCE = SequenceInputs(
    0.5, 1.02, 0.1, 0.01, 0.02, -0.01, jnp.array([200, 500, 800]),
    jnp.array([1.0, -2.0, 0.7]), jnp.array([-0.3, 0.4, -0.9]),
)
SCALES = terms.Scales(1.3, 1e-3, DT * (N * M - 1), 2 * np.pi * 1e3)


def _record(params, coefficients=None, residual=None):
    c = jnp.zeros(terms.N_COEFFICIENTS) if coefficients is None else coefficients
    return terms.term_record(params, DT, N, M, SEQUENCE, c, SCALES, residual)


def _column(name, value):
    k = terms.OFFSETS[[t.name for t in terms.TERMS].index(name)]
    return jnp.zeros(terms.N_COEFFICIENTS).at[k].set(value)


def test_the_network_at_its_start_is_the_nominal_model():
    params = NominalDevice.reference().params
    nominal = _record(params)
    starts = ceiling.starts()
    assert len(starts) == ceiling.STARTS and starts[0].dtype == jnp.float64
    assert not np.allclose(starts[0], starts[1])  # the hidden layers differ
    for flat in starts:
        with_network = _record(params, residual=ceiling.residual(flat, SCALES.half))
        assert float(jnp.max(jnp.abs(with_network - nominal))) == 0.0


def test_a_residual_enters_where_the_term_of_its_form_does():
    # A residual moment c·v³/h² is the term spring_cube; a residual output c·v²/h with no
    # output filter (the output reads v) is the term output_square.
    params = NominalDevice.reference(torquer_time_constant=0.0, filter_time_constant=0.0).params
    h, c = SCALES.half, 0.05
    cube = _record(params, residual=lambda v, w, m, g: (c * v**3 / h**2, 0.0 * v))
    assert float(jnp.max(jnp.abs(cube - _record(params, _column("spring_cube", c))))) < 1e-12
    square = _record(params, residual=lambda v, w, m, g: (0.0 * v, c * v * v / h))
    expected = _record(params, _column("output_square", c))
    assert float(jnp.max(jnp.abs(square - expected))) < 1e-12
    # Each is a visible change of the record (the comparison is not between zeros).
    assert float(jnp.max(jnp.abs(cube - _record(params)))) > 1e-4


def test_every_weight_reaches_the_output_once_the_last_layer_moves():
    # At the start only the last layer's weights have a derivative (the hidden layer acts
    # through it); one step away from zero every weight does, as the fit needs.
    params = NominalDevice.reference().params
    flat = ceiling.starts()[0]
    n_last = ceiling.OUTPUTS * (ceiling.WIDTH + 1)
    moved = flat.at[-n_last:].set(0.05)

    def record(p):
        return _record(params, residual=ceiling.residual(p, SCALES.half))

    jac = jax.jacfwd(record)(moved)
    assert jac.shape == (N, ceiling.size())
    assert bool(jnp.all(jnp.max(jnp.abs(jac), axis=0) > 0))
    # Forward mode against central differences on a few weights.
    for k in (0, 7, ceiling.size() - 1):
        e = jnp.zeros_like(moved).at[k].set(1e-6)
        central = (record(moved + e) - record(moved - e)) / 2e-6
        scale = float(jnp.max(jnp.abs(central)))
        assert float(jnp.max(jnp.abs(jac[:, k] - central))) < 1e-5 * scale


def test_no_terms_is_zero_coefficients_without_their_signals():
    # The network's fit passes no coefficients (None): `term_record` leaves the terms'
    # signals out. The same record and Jacobian as zero coefficients, bitwise, with a
    # moved network and with both lags and an output filter in the loop.
    params = NominalDevice.reference().params
    moved = ceiling.starts()[1].at[-ceiling.OUTPUTS * (ceiling.WIDTH + 1) :].set(0.05)

    def record(p, with_zeros: bool):
        c = jnp.zeros(terms.N_COEFFICIENTS) if with_zeros else None
        residual = ceiling.residual(p, SCALES.half)
        return terms.term_record(params, DT, N, M, SEQUENCE, c, SCALES, residual)

    for f in (record, jax.jacfwd(record)):
        zeros, none = (jax.jit(f, static_argnums=1)(moved, z) for z in (True, False))
        assert bool(jnp.all(zeros == none)) and float(jnp.max(jnp.abs(zeros))) > 0


def test_a_ceiling_without_a_discovery_is_refused():
    with pytest.raises(ValueError, match="ceiling=True needs discover"):
        diagnose_step([], NominalDevice.reference(), ceiling=True)


def test_the_summary_states_the_reference_and_what_the_term_reaches():
    import dataclasses

    from accel_jax.diagnose.base import discovery_lines
    from accel_jax.diagnose.discovery_result import (
        DiscoveredColumn,
        Discovery,
        DiscoveryCandidate,
        DiscoveryScales,
        NetworkReference,
    )

    column = DiscoveredColumn(
        term="pickoff_cube", place="pickoff", family="pickoff", formula="U_amp += c·v³/h²",
        coefficient=-0.06, sigma=0.009,
    )
    best = DiscoveryCandidate(
        terms=("pickoff_cube",), columns=(column,), evidence=1e6, criterion=-1e6,
        delta_chi2_train=1e6, ebic_linearised=-1e6, held_out_gap_before_V=0.07,
        held_out_gap_after_V=0.0, explained_fraction=1.0, held_out_at_floor=True,
        stability=1.0, converged=True, chi2_per_dof_train=1.0, ceiling_fraction=1.71,
        ceiling_compared=True,
    )
    reference = NetworkReference(
        method="", parameters=58, delta_chi2_train=1e5, held_out_gap_before_V=0.07,
        held_out_gap_after_V=0.046, explained_fraction=0.58, converged=True, extrapolates=False,
    )
    found = Discovery(
        method="", sinusoid_start_Hz=0.0, scales=DiscoveryScales(1.0, 3e-4),
        candidates=(best,), best=best, rating="credible", ceiling=reference,
    )
    text = "\n".join(discovery_lines(found))
    assert "removes 58% of the held-out gap; the term reaches 171% of that" in text
    assert "extrapolated" not in text
    # Nothing found: the reference is still stated, and where the held-out part leaves the
    # training part's levels, that it is extrapolated there.
    nothing = dataclasses.replace(
        found, best=None, rating="nothing found",
        ceiling=dataclasses.replace(reference, extrapolates=True),
    )
    lines = discovery_lines(nothing)
    assert lines[0].endswith("nothing found in the term library")
    assert "removes 58%" in lines[1] and "extrapolated there" in lines[1]
    without = dataclasses.replace(found, ceiling=None)
    assert discovery_lines(without)[1].startswith("   held-out")
