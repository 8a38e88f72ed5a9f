"""Package-level behaviour: import side effects, the CLI, atomic outputs."""

import json
import subprocess
import sys

import numpy as np
import pytest
from click.testing import CliRunner

import accel_jax as aj
from accel_jax.cli import main
from accel_jax.report import write_json_atomic


def test_import_does_not_change_jax_config():
    code = (
        "import jax; before = jax.config.read('jax_enable_x64');"
        "import accel_jax as aj; aj.ServoParams.reference();"
        "assert jax.config.read('jax_enable_x64') == before == False;"
        "print(aj.ServoParams.reference().damping.dtype)"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    # Without x64 the library computes in float32: it does not upgrade precision silently.
    assert proc.stdout.strip() == "float32"


def test_cli_info_prints_closed_forms():
    result = CliRunner().invoke(main, ["info"])
    assert result.exit_code == 0, result.output
    xi = float(result.output.split("damping ratio ξ       =")[1].split()[0])
    assert xi == pytest.approx(float(aj.damping_ratio(aj.ServoParams.reference())), rel=1e-5)


def test_cli_unknown_command_is_a_clear_error():
    result = CliRunner().invoke(main, ["frobnicate"])
    assert result.exit_code == 2
    assert "No such command" in result.output


def test_write_json_atomic(tmp_path):
    path = write_json_atomic(
        tmp_path / "a" / "r.json", {"x": np.float64(1.5), "v": np.arange(3), "n": float("nan")}
    )
    assert json.loads(path.read_text()) == {"x": 1.5, "v": [0, 1, 2], "n": None}
    assert [p.name for p in path.parent.iterdir()] == ["r.json"]  # no temporary left behind


def test_atomic_writes_get_the_usual_permissions(tmp_path):
    # The temporary file comes from mkstemp (0600); the result must look like open()'s.
    import os

    old = os.umask(0o022)
    try:
        path = write_json_atomic(tmp_path / "r.json", {"x": 1})
    finally:
        os.umask(old)
    assert path.stat().st_mode & 0o777 == 0o644


def test_write_json_atomic_keeps_old_file_on_failure(tmp_path):
    path = write_json_atomic(tmp_path / "r.json", {"x": 1})
    with pytest.raises(TypeError):
        write_json_atomic(path, {"x": object()})
    assert json.loads(path.read_text()) == {"x": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["r.json"]


def test_studies_and_notebooks_use_only_the_public_api():
    # STYLE.md: studies and notebooks import `accel_jax` (and its subpackages such as
    # `accel_jax.diagnose`, `accel_jax.report`), never the private modules `accel_jax._*` —
    # except the process-level modules (`_runtime`, `_cache`, `_placement`), which the entry
    # points (CLI, study scripts, tests, benchmarks) use by design (docs/architecture.md).
    import pathlib
    import re

    root = pathlib.Path(__file__).resolve().parent.parent
    scripts = sorted((root / "studies").glob("*.py")) + sorted((root / "notebooks").glob("*.py"))
    assert scripts
    private = re.compile(r"^\s*(from|import)\s+accel_jax\._(?!runtime\b|cache\b|placement\b)", re.M)
    offenders = [p.name for p in scripts if private.search(p.read_text())]
    runtime = re.compile(r"^\s*(from|import)\s+accel_jax\._(runtime|cache|placement)\b", re.M)
    assert not [
        p.name for p in sorted((root / "notebooks").glob("*.py")) if runtime.search(p.read_text())
    ]
    assert offenders == []


# The layers of docs/architecture.md, lowest first; a module may import its own layer's
# foundations and lower layers only; within the foundations and within the entry points
# freely, within the estimation layer only as listed.
_LAYERS = {
    "foundations": (
        "_params", "_checks", "_data", "_format", "_io", "_progress", "_runtime", "_cache",
        "_placement", "_deprecated", "_solvers",
    ),
    "models": ("_servo", "_static", "_pendulum"),
    "simulation": ("_simulate",),
    "estimation": (
        "_identify",
        "_ml_estimate",
        "_noise",
        "_kalman",
        "_kalman_ins",
        "_kalman_models",
        "_kalman_online",
        "_kalman_sensor",
        "_kalman_spectral",
        "_vibration",
        "_tolerance",
        "_sweep",
    ),
    "diagnosis": ("diagnose",),
    "entry": ("cli", "report", "", "noise", "vibration", "kalman"),
}
_SAME_LAYER = {
    ("_noise", "_kalman"),
    ("_tolerance", "_vibration"),
    ("_identify", "_noise"),
    ("_identify", "_sweep"),
    ("_kalman_ins", "_kalman"),
    ("_kalman_models", "_kalman"),
    ("_kalman_models", "_kalman_ins"),
    ("_kalman_online", "_kalman"),
    ("_kalman_online", "_noise"),
    ("_kalman_online", "_kalman_ins"),
    ("_kalman_online", "_kalman_sensor"),
    ("_kalman_sensor", "_kalman"),
    ("_kalman_sensor", "_kalman_ins"),
    ("_kalman_spectral", "_kalman"),
    ("_kalman_sensor", "_noise"),
}
# Upward imports inside functions, each for one name: the package version for provenance,
# and whether the user set XLA's log level before `import accel_jax`.
_UPWARD = {("_io", ""): "__version__", ("_runtime", ""): "_USER_SET_XLA_LOG_LEVEL"}


def _internal_imports():
    """{unit: {unit it imports: [names]}} over accel_jax's modules, a unit being a top-level
    module or subpackage ('' for the package's __init__)."""
    import ast
    import pathlib

    root = pathlib.Path(aj.__file__).resolve().parent
    graph = {}
    for path in sorted(root.rglob("*.py")):
        parts = list(path.relative_to(root).with_suffix("").parts)
        unit = "" if parts == ["__init__"] else parts[0]
        package = parts[:-1] if parts[-1] != "__init__" else parts[:-1]
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, ast.ImportFrom):
                continue
            if node.level:
                base = package[: len(package) - (node.level - 1)]
                target = base + (node.module.split(".") if node.module else [])
            elif node.module and node.module.split(".")[0] == "accel_jax":
                target = node.module.split(".")[1:]
            else:
                continue
            other = target[0] if target else ""
            if other != unit:
                names = [alias.name for alias in node.names]
                graph.setdefault(unit, {}).setdefault(other, []).extend(names)
    return graph


def test_import_layers():
    rank = {unit: i for i, units in enumerate(_LAYERS.values()) for unit in units}
    graph = _internal_imports()
    assert set(graph) <= set(rank), set(graph) - set(rank)  # every unit has a layer
    wrong = []
    for unit, targets in graph.items():
        for other, names in targets.items():
            if (unit, other) in _UPWARD:
                assert set(names) == {_UPWARD[unit, other]}, (unit, other, names)
                continue
            # Foundations and entry points may use each other within their layer.
            open_layer = rank[unit] == rank[other] in (0, rank["cli"])
            if rank[other] < rank[unit] or open_layer or (unit, other) in _SAME_LAYER:
                continue
            wrong.append(f"{unit or 'accel_jax'} imports {other or 'accel_jax'} {names}")
    assert wrong == []
    # Process settings stay with the entry points (and the package's import-time hook);
    # the library may read the CPUs it may run on (`usable_cpus`, `spare_cpu`) and spread
    # independent calls over them (`thread_map`, `in_background`, `beside`), which change
    # nothing.
    for unit, targets in graph.items():
        for settings in ("_runtime", "_cache", "_placement"):
            names = set(targets.get(settings, ())) - {
                "usable_cpus", "spare_cpu", "thread_map", "in_background", "beside"
            }
            if names and rank[unit] not in (0, rank["cli"]):
                wrong.append(f"{unit} imports {settings} {sorted(names)}")
    assert wrong == []


def test_import_layers_catch_an_upward_import(monkeypatch):
    """The layer check itself: a model importing the diagnosis is reported."""
    graph = _internal_imports()
    graph.setdefault("_servo", {})["diagnose"] = ["diagnose"]
    monkeypatch.setattr(sys.modules[__name__], "_internal_imports", lambda: graph)
    with pytest.raises(AssertionError, match="_servo imports diagnose"):
        test_import_layers()


# Inside the diagnosis (docs/architecture.md): the modules every kind shares, below the
# kinds; each kind is a subpackage that imports, of the diagnosis, only those and itself (the
# kinds' fits included); and nothing imports an old place of the kinds'
# modules (kept for one release, CHANGELOG.md).
_DIAGNOSE_SHARED = {"base", "openworld", "discovery_text", "discovery_result"}
_DIAGNOSE_KINDS = {"step": set(), "noise": set(), "vibration": set()}
_DIAGNOSE_OLD = {
    "step_fit", "step_input", "step_effects", "step_assess", "step_verdict", "step_refit",
    "step_nuisance", "step_joint", "step_joint_verdict", "step_design", "step_record",
    "noise_effects", "noise_sensor", "noise_fit", "vibration_effects",
}  # fmt: skip
_OLD_PLACE_PENDING: dict[str, set[str]] = {}  # a module still reading an old place (none)


def test_the_diagnosis_kinds_sit_on_its_shared_modules():
    from pathlib import Path

    package = Path(aj.__file__).resolve().parent
    root = package.parent
    assert len(list((package / "diagnose" / "step").glob("*.py"))) >= 12
    assert len(list((package / "diagnose" / "noise").glob("*.py"))) >= 7
    assert len(list((package / "diagnose" / "vibration").glob("*.py"))) >= 7
    wrong = []
    for path in sorted(package.rglob("*.py")):
        parts = list(path.relative_to(root).with_suffix("").parts)
        used = {
            m.split(".")[2]
            for m in _imported_modules(path, parts[:-1])
            if m.startswith("accel_jax.diagnose.")
        }
        where = path.relative_to(root).as_posix()
        old = (used & _DIAGNOSE_OLD) - _OLD_PLACE_PENDING.get(where, set())
        if old:
            wrong.append(f"{where} imports the old place of {sorted(old)}")
        if parts[:2] != ["accel_jax", "diagnose"]:
            continue
        if parts[2] in _DIAGNOSE_SHARED and used - _DIAGNOSE_SHARED:
            wrong.append(f"{where} (shared) imports {sorted(used - _DIAGNOSE_SHARED)}")
        if parts[2] in _DIAGNOSE_KINDS and len(parts) >= 4:
            other = used - _DIAGNOSE_SHARED - {parts[2]} - _DIAGNOSE_KINDS[parts[2]]
            if other:
                wrong.append(f"{where} imports {sorted(other)}")
    assert wrong == []


def _imported_modules(path, package: list[str]) -> set[str]:
    """The dotted names a Python file imports ("accel_jax.report.text", and for `from X
    import name` also "X.name"), relative imports resolved from `package` (its package's
    parts, e.g. ["accel_jax", "report"])."""
    import ast

    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - (node.level - 1)]
                module = ".".join(base + (node.module.split(".") if node.module else []))
            else:
                module = node.module or ""
            found.add(module)
            found.update(f"{module}.{alias.name}" for alias in node.names)
    return found


def test_report_text_is_presentation_only():
    """`accel_jax.report.text` renders the CLI's and the report's text: only the entry points
    (cli.py, accel_jax/report/) import it, and it imports neither click nor matplotlib (nor
    changes JAX's settings): data in, strings out."""
    from pathlib import Path

    package = Path(aj.__file__).resolve().parent
    root = package.parent
    text = package / "report" / "text"
    assert (text / "__init__.py").exists()
    users, wrong = [], []
    files = sorted(package.rglob("*.py")) + [
        p
        for folder in ("studies", "notebooks", "benchmarks")
        for p in (root / folder).rglob("*.py")
    ]
    for path in files:
        parts = list(path.relative_to(root).with_suffix("").parts)
        inside = parts[:2] == ["accel_jax", "report"] or parts == ["accel_jax", "cli"]
        imported = _imported_modules(path, parts[:-1])
        if any(
            m == "accel_jax.report.text" or m.startswith("accel_jax.report.text.") for m in imported
        ):
            users.append(path.relative_to(root).as_posix())
            if not inside:
                wrong.append(f"{path.relative_to(root)} imports accel_jax.report.text")
        if path.is_relative_to(text):
            for m in sorted(imported):
                if m.split(".")[0] in ("click", "matplotlib"):
                    wrong.append(f"{path.relative_to(root)} imports {m}")
            if "config.update" in path.read_text() or "enable_x64" in path.read_text():
                wrong.append(f"{path.relative_to(root)} changes JAX's settings")
    assert "accel_jax/cli.py" in users  # the check sees the CLI's imports
    assert wrong == []


# The modules below the entry points that may still import matplotlib, each with why.
_MATPLOTLIB_BELOW_ENTRY: dict[str, str] = {}


def test_figures_are_drawn_only_in_the_presentation_layer():
    """matplotlib is imported by the entry points (cli.py, accel_jax/report/: its `figures`
    package) and nowhere below them, except the modules listed in `_MATPLOTLIB_BELOW_ENTRY`;
    `_io.save_figure_atomic` writes a figure it is given without importing matplotlib."""
    from pathlib import Path

    package = Path(aj.__file__).resolve().parent
    root = package.parent
    found = set()
    for path in sorted(package.rglob("*.py")):
        parts = list(path.relative_to(root).with_suffix("").parts)
        if parts[:2] == ["accel_jax", "report"] or parts == ["accel_jax", "cli"]:
            continue
        if any(m.split(".")[0] == "matplotlib" for m in _imported_modules(path, parts[:-1])):
            found.add(path.relative_to(root).as_posix())
    assert found == set(_MATPLOTLIB_BELOW_ENTRY)


def _tracked_text_files():
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent
    listed = subprocess.run(
        ["git", "ls-files"], cwd=root, capture_output=True, text=True, check=False
    )
    names = listed.stdout.split() if listed.returncode == 0 else []
    if not names:  # (not a git checkout: every file under the package's folders)
        names = [
            str(p.relative_to(root))
            for folder in ("accel_jax", "studies", "tests", "notebooks", "docs", "benchmarks")
            for p in (root / folder).rglob("*")
            if p.is_file()
        ]
    for name in names:
        path = root / name
        if path.suffix in {".py", ".md", ".ipynb", ".toml", ".txt", ".cfg", ".yml"} or path.name in {
            "Makefile"
        }:
            yield name, path.read_text(encoding="utf-8", errors="replace")


def test_nothing_points_outside_the_repository():
    """The papers' models, equations and numbers live in docs/models.md; no file names the
    developers' notes outside the repository (a person who clones it cannot follow them)."""
    import re

    outside = re.compile(r"SPEC\.md|\bSPEC\b|\.\./shared|shared/(SPEC|STYLE|ARCHITECTURE)|seeds/|seed 00\d")
    found = [
        f"{name}:{i}: {line.strip()[:80]}"
        for name, text in _tracked_text_files()
        if name != "tests/test_package.py"
        for i, line in enumerate(text.splitlines(), 1)
        if outside.search(line)
    ]
    assert not found, "\n".join(found)


def test_every_cited_section_and_table_of_the_models_page_exists():
    import re
    from pathlib import Path

    page = (Path(__file__).resolve().parent.parent / "docs" / "models.md").read_text()
    sections = set(re.findall(r"^## (\d)\. ", page, flags=re.M))
    tables = set(re.findall(r"Table (\d)", page))
    cited_sections, cited_tables = set(), set()
    for _, text in _tracked_text_files():
        for ref in re.findall(r"docs/models\.md[ ,]*§(\d)", text):
            cited_sections.add(ref)
        for ref in re.findall(r"docs/models\.md §3, Table (\d)", text):
            cited_tables.add(ref)
    assert cited_sections and cited_sections <= sections, (cited_sections, sections)
    assert cited_tables <= tables, (cited_tables, tables)
