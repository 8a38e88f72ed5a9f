"""Package-level behaviour: import side effects, the CLI, atomic outputs."""

import json
import subprocess
import sys

import numpy as np
import pytest
from click.testing import CliRunner

import accel_jax as aj
from accel_jax.cli import main


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
    path = aj.write_json_atomic(
        tmp_path / "a" / "r.json", {"x": np.float64(1.5), "v": np.arange(3), "n": float("nan")}
    )
    assert json.loads(path.read_text()) == {"x": 1.5, "v": [0, 1, 2], "n": None}
    assert [p.name for p in path.parent.iterdir()] == ["r.json"]  # no temporary left behind


def test_atomic_writes_get_the_usual_permissions(tmp_path):
    # The temporary file comes from mkstemp (0600); the result must look like open()'s.
    import os

    old = os.umask(0o022)
    try:
        path = aj.write_json_atomic(tmp_path / "r.json", {"x": 1})
    finally:
        os.umask(old)
    assert path.stat().st_mode & 0o777 == 0o644


def test_write_json_atomic_keeps_old_file_on_failure(tmp_path):
    path = aj.write_json_atomic(tmp_path / "r.json", {"x": 1})
    with pytest.raises(TypeError):
        aj.write_json_atomic(path, {"x": object()})
    assert json.loads(path.read_text()) == {"x": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["r.json"]


def test_studies_and_notebooks_use_only_the_public_api():
    # STYLE.md: studies and notebooks import `accel_jax` (and its subpackages such as
    # `accel_jax.diagnose`), never the private modules `accel_jax._*`.
    import pathlib
    import re

    root = pathlib.Path(__file__).resolve().parent.parent
    scripts = sorted((root / "studies").glob("*.py")) + sorted((root / "notebooks").glob("*.py"))
    assert scripts
    private = re.compile(r"^\s*(from|import)\s+accel_jax\._", re.MULTILINE)
    offenders = [p.name for p in scripts if private.search(p.read_text())]
    assert offenders == []
