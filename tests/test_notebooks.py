"""Every notebook in `notebooks/` runs top to bottom as a plain Python script (they are
jupytext percent scripts), so none can rot: each is executed in a subprocess from an empty
temporary folder with a non-interactive matplotlib backend, and must exit with status 0."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
NOTEBOOKS = sorted((ROOT / "notebooks").glob("*.py"))
TIMEOUT_S = 300  # per notebook; each is meant to run in well under a minute


def test_notebooks_are_found():
    # Guards the glob above: a moved folder would otherwise silently test nothing.
    assert NOTEBOOKS, f"no notebooks found under {ROOT / 'notebooks'}"


@pytest.mark.slow
@pytest.mark.parametrize("notebook", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs_as_a_script(notebook, tmp_path):
    env = dict(os.environ)
    env["MPLBACKEND"] = "Agg"
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
    try:
        done = subprocess.run(
            [sys.executable, str(notebook)],
            cwd=tmp_path,
            env=env,
            capture_output=True,
            text=True,
            timeout=TIMEOUT_S,
        )
    except subprocess.TimeoutExpired as error:
        pytest.fail(f"{notebook.name} did not finish within {TIMEOUT_S} s:\n{error.stderr!s}")
    assert done.returncode == 0, (
        f"{notebook.name} exited with {done.returncode}\n"
        f"--- stdout (tail) ---\n{done.stdout[-3000:]}\n"
        f"--- stderr (tail) ---\n{done.stderr[-3000:]}"
    )
