"""The typed discovery of a missing term (`accel_jax.diagnose.discovery_result`): its
`to_dict()` is the `discovery` block the plain dict gave, key for key and in the same order,
with the same keys present (`frequency_Hz` for a sinusoid, `ceiling_fraction` where the
network reference ran, `consequence` on the best subset and its tie, in the `candidates`
list too); the old dict access still works, with a `DeprecationWarning` naming the
attribute. (On records, the JSON itself: tests/test_diagnose_step_discover.py.)"""

from __future__ import annotations

import dataclasses
import json
import re
import warnings

import pytest

from accel_jax.diagnose.base import DiagnosisResult
from accel_jax.diagnose.discovery_result import (
    DiscoveredColumn,
    Discovery,
    DiscoveryCandidate,
    DiscoveryScales,
    NetworkReference,
)

# The keys of the dicts these replaced, in their order (as the JSON has them).
DISCOVERY = ["method", "sinusoid_start_Hz", "scales", "candidates", "best", "tie", "rating"]
CANDIDATE = [
    "terms", "columns", "evidence", "criterion", "delta_chi2_train", "ebic_linearised",
    "held_out_gap_before_V", "held_out_gap_after_V", "explained_fraction", "held_out_at_floor",
    "stability", "converged", "chi2_per_dof_train",
]  # fmt: skip
COLUMN = ["term", "place", "family", "formula", "coefficient", "sigma"]
REFERENCE = [
    "method", "parameters", "delta_chi2_train", "held_out_gap_before_V",
    "held_out_gap_after_V", "explained_fraction", "converged", "extrapolates",
]  # fmt: skip


def _column(term, coefficient, sigma):
    return DiscoveredColumn(term, "pickoff", "polynomial", "U_amp += c·v²/h", coefficient, sigma)


def _candidate(terms, columns, criterion, **more):
    return DiscoveryCandidate(
        terms=tuple(terms), columns=tuple(columns), evidence=-criterion, criterion=criterion,
        delta_chi2_train=-criterion + 20.0, ebic_linearised=criterion + 1.0,
        held_out_gap_before_V=0.07, held_out_gap_after_V=0.001, explained_fraction=0.99,
        held_out_at_floor=True, stability=0.9, converged=True, chi2_per_dof_train=1.1, **more,
    )


def _discoveries():
    """(what the reference ran on, with a tie and an excitation; nothing found, no
    reference)."""
    pair = _candidate(
        ["pickoff_square", "pickoff_cube"],
        [_column("pickoff_square", 0.05, 0.02), _column("pickoff_cube", -0.04, 0.001)],
        -500.0, ceiling_fraction=1.5, ceiling_compared=True,
    )
    tone = _candidate(
        ["forcing_sinusoid"],
        [_column("forcing_sinusoid (sin)", 0.1, 0.01), _column("forcing_sinusoid (cos)", 0, 1)],
        -497.0, frequency_Hz=1300.0, ceiling_fraction=None, ceiling_compared=True,
    )
    third = _candidate(["pickoff_abs"], [_column("pickoff_abs", 0.1, 0.1)], -100.0,
                       ceiling_fraction=0.2, ceiling_compared=True)  # fmt: skip
    meaning = ({"term": "pickoff_square", "static": None, "text": "no static term"},)
    pair = dataclasses.replace(pair, consequence=meaning)
    tone = dataclasses.replace(tone, consequence=meaning[:0])
    reference = NetworkReference("a network", 58, 1e4, 0.07, 0.05, 0.5, True, False)
    found = Discovery(
        method="m", sinusoid_start_Hz=1290.0, scales=DiscoveryScales(2.1, 2.9e-4),
        candidates=(pair, tone, third), best=pair, tie=tone, rating="credible",
        ceiling=reference, excite=({"term": "pickoff_square", "text": "barely excited"},),
    )
    nothing = Discovery(
        method="m", sinusoid_start_Hz=1290.0, scales=DiscoveryScales(2.1, 2.9e-4),
        candidates=(_candidate(["pickoff_abs"], [_column("pickoff_abs", 0.1, 0.1)], 5.0),),
    )
    return found, nothing


def test_to_dict_is_the_old_block_key_for_key():
    found, nothing = _discoveries()
    plain = found.to_dict()
    assert list(plain) == [*DISCOVERY, "ceiling", "excite"]
    assert plain["scales"] == {"half_V": 2.1, "period_s": 2.9e-4}
    assert list(plain["ceiling"]) == REFERENCE
    pair, tone, third = plain["candidates"]
    assert list(pair) == [*CANDIDATE, "ceiling_fraction", "consequence"]
    assert list(tone) == [*CANDIDATE, "frequency_Hz", "ceiling_fraction", "consequence"]
    assert list(third) == [*CANDIDATE, "ceiling_fraction"]
    assert tone["ceiling_fraction"] is None and tone["consequence"] == []
    assert [list(c) for c in pair["columns"]] == [COLUMN, COLUMN]
    assert pair["terms"] == ["pickoff_square", "pickoff_cube"]  # lists, as the dicts held
    # `best` and `tie` were the candidates' own dicts: the same content, consequence too.
    assert plain["best"] == pair and plain["tie"] == tone
    assert plain["excite"] == [{"term": "pickoff_square", "text": "barely excited"}]
    assert json.loads(json.dumps(plain)) == plain  # JSON-ready
    empty = nothing.to_dict()
    assert list(empty) == DISCOVERY
    assert empty["best"] is None and empty["tie"] is None and empty["rating"] == "nothing found"
    assert list(empty["candidates"][0]) == CANDIDATE


def test_the_diagnosis_writes_the_block_and_the_old_access_warns():
    found, _ = _discoveries()
    result = DiagnosisResult("step", "unexplained", [], [], {}, {}, {}, discovery=found)
    assert result.to_dict()["discovery"] == found.to_dict()
    old = found.to_dict()
    pattern = r"result\['best'\] is deprecated.*use result\.best \(or result\.to_dict\(\)"
    with pytest.warns(DeprecationWarning, match=pattern) as caught:
        assert result.discovery["best"] == old["best"]
    assert "next release" in str(caught[0].message)
    assert caught[0].filename == __file__  # attributed to the caller
    with pytest.warns(DeprecationWarning, match=re.escape("result.get('rating')")):
        assert found.get("rating") == "credible"
    with pytest.warns(DeprecationWarning, match="'ceiling' in result"):
        assert "ceiling" in found
    with pytest.warns(DeprecationWarning, match=r"result\.keys\(\)"):
        assert list(found.keys()) == list(old)
    with pytest.raises(KeyError):
        _discoveries()[1]["excite"]
    assert _discoveries()[1].get("excite") is None  # absent, no warning
    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)
        assert found.best is not None and found.best.terms == ("pickoff_square", "pickoff_cube")
        with pytest.raises(dataclasses.FrozenInstanceError):
            found.rating = "tentative"  # type: ignore[misc]


def test_a_sigma_whose_profile_interval_was_not_found_is_said_so():
    from accel_jax.diagnose.discovery_text import discovery_lines

    found, _ = _discoveries()
    square, cube = found.best.columns
    cube = dataclasses.replace(cube, profile_found=False, sigma_linearised=0.009)
    square = dataclasses.replace(square, profile_found=True, sigma_linearised=0.08)
    best = dataclasses.replace(found.best, columns=(square, cube))
    first = discovery_lines(dataclasses.replace(found, best=best))[0]
    assert first.count("profile interval not found") == 1
    assert "-0.04 ± 0.001 (profile interval not found: σ uncertain)" in first
    # A linearised σ alone (no profile run: profile_found None) is not flagged.
    assert "not found" not in discovery_lines(found)[0]
