"""Names that moved keep their old place for one release, with a warning naming the new one
(`accel_jax._deprecated.moved_names`; the moves are listed in CHANGELOG.md)."""

import importlib
import re
from pathlib import Path

import pytest

from accel_jax._deprecated import MOVED, moved_names

MOVES = {
    "accel_jax": {
        "identification_summary": "accel_jax.report",
        "identification_figure": "accel_jax.report",
    },
    "accel_jax.diagnose.step_joint": {
        "SetDiagnosis": "accel_jax.diagnose.step.joint_verdict",
        "diagnose_step_set": "accel_jax.diagnose.step.joint_verdict",
        "next_experiments": "accel_jax.diagnose.step.design",
        "set_figure": "accel_jax.report.figures.diagnosis",
        "fit_set": "accel_jax.diagnose.step.joint",
        "PreparedSet": "accel_jax.diagnose.step.joint",
    },
    "accel_jax.diagnose.report": {
        "figure": "accel_jax.report.figures.diagnosis",
        "save_plot": "accel_jax.report.figures.diagnosis",
    },
    "accel_jax.diagnose.step_verdict": {
        "nested_failed": "accel_jax.diagnose.step.assess",
        "nuisance_test": "accel_jax.diagnose.step.nuisance",
        "evaluate": "accel_jax.diagnose.step.verdict",
    },
    # The step diagnosis's modules, now the subpackage `accel_jax.diagnose.step`.
    "accel_jax.diagnose.step_fit": {"StepContext": "accel_jax.diagnose.step.fit"},
    "accel_jax.diagnose.step_input": {"read_inputs": "accel_jax.diagnose.step.inputs"},
    "accel_jax.diagnose.step_effects": {"TorquerLag": "accel_jax.diagnose.step.effects"},
    "accel_jax.diagnose.step_assess": {"nested_losers": "accel_jax.diagnose.step.assess"},
    "accel_jax.diagnose.step_refit": {"KNOWN_FIELDS": "accel_jax.diagnose.step.refit"},
    "accel_jax.diagnose.step_nuisance": {"strained_sentence": "accel_jax.diagnose.step.nuisance"},
    "accel_jax.diagnose.step_joint_verdict": {
        "SetDiagnosis": "accel_jax.diagnose.step.joint_verdict"
    },
    "accel_jax.diagnose.step_design": {"experiment_menu": "accel_jax.diagnose.step.design"},
    "accel_jax.diagnose.step_record": {
        "prepare": "accel_jax.diagnose.step.record",
        "segments": "accel_jax.diagnose.step.segments",
        "RecordView": "accel_jax.diagnose.step.state",
    },
    # The noise and vibration kinds' modules, now the subpackages `noise` and `vibration`.
    "accel_jax.diagnose.noise_effects": {"GaussMarkovNoise": "accel_jax.diagnose.noise.effects"},
    "accel_jax.diagnose.noise_sensor": {"combine": "accel_jax.diagnose.noise.sensor"},
    "accel_jax.diagnose.noise_fit": {"filter_terms": "accel_jax.diagnose.noise.fit"},
    "accel_jax.diagnose.vibration_effects": {"K3": "accel_jax.diagnose.vibration.effects"},
    # The rescaling of a record far above its floor, with the rest of the rescaling.
    "accel_jax.diagnose.step.entry": {"REWEIGHT_ABOVE": "accel_jax.diagnose.step.rescale"},
}

_OLD_MODULES = (
    "step_fit", "step_input", "step_effects", "step_assess", "step_verdict", "step_refit",
    "step_nuisance", "step_joint", "step_joint_verdict", "step_design", "step_record",
    "noise_effects", "noise_sensor", "noise_fit", "vibration_effects",
)  # fmt: skip
# Names an old place still holds without a warning, for a module of the package that has
# not moved its import yet (tests/test_package.py lists it): none now.
_KEPT: dict[str, set[str]] = {}


@pytest.mark.parametrize(
    "old, name, new",
    [(old, name, new) for old, names in MOVES.items() for name, new in names.items()],
)
def test_a_moved_name_warns_and_is_the_same_object(old, name, new):
    module = importlib.import_module(old)
    with pytest.warns(DeprecationWarning, match=re.escape(f"{new}.{name}")):
        value = getattr(module, name)
    assert value is getattr(importlib.import_module(new), name)


def test_from_import_of_a_moved_name_warns_too():
    with pytest.warns(DeprecationWarning, match=re.escape("step.joint_verdict")):
        from accel_jax.diagnose.step_joint import diagnose_step_set  # noqa: F401


@pytest.mark.parametrize("old", _OLD_MODULES)
def test_every_name_of_an_old_module_is_at_its_new_place(old):
    """Each old module of a diagnosis kind (`accel_jax.diagnose.step_*`, `noise_effects`,
    `noise_sensor`, `vibration_effects`) is only its aliases, and each alias names an object
    that its new module holds."""
    module = importlib.import_module(f"accel_jax.diagnose.{old}")
    aliases = MOVED[module.__name__]
    assert aliases
    kept = _KEPT.get(old, set())
    assert {n for n in vars(module) if not n.startswith("_")} <= {"moved_names"} | kept
    for name, new in aliases.items():
        if name in kept:
            value = getattr(module, name)
        else:
            with pytest.warns(DeprecationWarning, match=re.escape(f"{new}.{name}")):
                value = getattr(module, name)
        assert value is getattr(importlib.import_module(new), name), (old, name)


def test_the_compact_form_is_the_mapping_form():
    """`moved_names(module, new_module, "a b", other_module, ["c"])` moves what the mapping
    {"a": new_module, "b": new_module, "c": other_module} moves; a name listed twice or an
    odd pair is refused."""
    moved_names(__name__ + ".compact", "accel_jax.noise", "GaussMarkov WhiteNoise", "accel_jax.kalman", ["kalman_filter"])
    moved_names(__name__ + ".mapping", {"GaussMarkov": "accel_jax.noise", "WhiteNoise": "accel_jax.noise", "kalman_filter": "accel_jax.kalman"})
    assert MOVED[__name__ + ".compact"] == MOVED[__name__ + ".mapping"]
    with pytest.raises(ValueError, match="twice"):
        moved_names("x", "accel_jax.noise", "GaussMarkov", "accel_jax.kalman", "GaussMarkov")
    with pytest.raises(TypeError):
        moved_names("x", "accel_jax.noise")


def test_an_unknown_name_is_still_an_attribute_error():
    module = importlib.import_module("accel_jax.diagnose.step_joint")
    with pytest.raises(AttributeError, match="no attribute 'no_such_name'"):
        module.no_such_name  # noqa: B018


def test_every_alias_is_in_the_changelog():
    """Each deprecated alias (`moved_names(...)` in the package) names its old and new place
    in CHANGELOG.md, so that a user told of a move can read why."""
    root = Path(__file__).resolve().parent.parent
    changelog = (root / "CHANGELOG.md").read_text()
    found = 0
    for path in sorted((root / "accel_jax").rglob("*.py")):
        if "moved_names(" not in path.read_text() or path.name == "_deprecated.py":
            continue
        parts = path.relative_to(root).with_suffix("").parts
        module = importlib.import_module(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
        for name, target in MOVED[module.__name__].items():
            found += 1
            assert f"`{name}`" in changelog and target in changelog, (path.name, name)
    assert found >= 6


_NAMESPACES = ("noise", "vibration", "kalman")
# Names new in 0.2, in their namespace only (never at the top level, so no alias there).
_NEW_IN_NAMESPACES = {
    "StaticRecordAnalysis",
    "HeldOutCheck",
    "INSNoiseChannel",
    "OnlineIdentification",
    "OnlineRun",
    "SensorErrorModel",
    "structure_candidates",
    "identify_in_flight",
    "online_channel",
    "SmoothedAutocovariance",
    "expected_sample_autocovariance",
    "smoothed_autocovariance",
}


def _public(module):
    return {n for n in vars(module) if not n.startswith("_") and n != "annotations"}


@pytest.mark.parametrize("namespace", _NAMESPACES)
def test_a_regrouped_top_level_name_warns_and_is_the_namespace_s_object(namespace):
    """Every name of `accel_jax.noise` / `.vibration` / `.kalman` was at the top level
    before 0.2: it still is for one release, with a warning naming its namespace."""
    import accel_jax

    module = importlib.import_module(f"accel_jax.{namespace}")
    names = _public(module) - _NEW_IN_NAMESPACES
    assert len(names) >= 14
    for name in sorted(names):
        with pytest.warns(DeprecationWarning, match=re.escape(f"accel_jax.{namespace}.{name}")):
            value = getattr(accel_jax, name)
        assert value is getattr(module, name), name


def test_the_namespaces_and_the_top_level_do_not_overlap():
    """One home per name: nothing is both at the top level and in a namespace (the aliases
    are read lazily, so they are not in the top level's own names)."""
    import accel_jax

    top = _public(accel_jax) - set(_NAMESPACES)
    homes = {n: _public(importlib.import_module(f"accel_jax.{n}")) for n in _NAMESPACES}
    for namespace, names in homes.items():
        assert not names & top, (namespace, sorted(names & top))
    assert not homes["noise"] & homes["vibration"] and not homes["noise"] & homes["kalman"]
    assert len(top) < 120, len(top)  # was 209 flat
