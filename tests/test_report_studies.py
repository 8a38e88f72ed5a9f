"""The report, end to end (quick mode): every study and figure in it, each study script run
alone in a fresh process to completion, the quick run's compile options, CPU shares."""

import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from accel_jax.cli import main

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def report_dir(quick_report):
    return quick_report


@pytest.mark.slow
def test_report_has_every_study_and_figure(report_dir):
    from accel_jax.report._studies import STUDIES

    index = (report_dir / "index.html").read_text()
    embedded = 0
    for name in STUDIES:
        result = json.loads((report_dir.parent / name / "result.json").read_text())
        assert f'id="{name}"' in index
        assert result["figures"], name
        for figure in result["figures"]:
            assert figure["caption"], (name, figure["file"])
            assert (report_dir.parent / name / figure["file"]).exists()
        embedded += len(result["figures"])
        assert result.get("provenance", {}).get("accel_jax_version"), name
    assert index.count("data:image/png;base64,") == embedded
    assert "missing figure" not in index
    # The studies' own "At a glance" tables (the report knows no study's schema).
    overview = index.split('id="overview"')[1].split("<h2")[0]
    assert "Tolerance limits on the transfer-function coefficients" in overview
    assert "Cyclone-4" in overview and "445" in overview
    assert "Sim-to-real diagnosis, checked blind" in overview


@pytest.mark.slow
def test_quick_compiles_one_off_work_for_speed_and_says_so(report_dir):
    """--quick compiles the one-off parts with most XLA optimisations off and records it;
    the sensing-element fits (run-bound) and every Monte Carlo kernel keep the default."""
    import jax

    def provenance(name):
        return json.loads((report_dir.parent / name / "result.json").read_text())["provenance"]

    key = "compiled_with_most_xla_optimisations_off"
    assert provenance("scale_factor_identification")[key] == (
        "stop identification, decompositions, gradient checks, fit comparison"
    )
    assert provenance("noise_identification")[key] == (
        "structure selection, Kalman filter, Allan deviation, in-flight loop"
    )
    for name in ("vibration_compensation", "tolerance_limits", "sim_to_real_validation"):
        assert provenance(name)["xla_most_optimizations_off"] is True, name
    assert provenance("sensing_element_ml")["xla_most_optimizations_off"] is False
    assert jax.config.read("jax_disable_most_optimizations") is False  # nothing leaks


def test_report_refuses_bad_option():
    result = CliRunner().invoke(main, ["report", "--quick", "--out"])
    assert result.exit_code == 2
    assert "requires an argument" in result.output


def test_each_study_script_runs_alone_to_completion(report_dir):
    """Every study, run as a user would (`python studies/<name>.py --quick --out DIR` in a
    fresh process, XLA_FLAGS unset: the deadlock workaround comes from `import accel_jax`),
    finishes within the fixture's time limit, and the report then reuses its result."""
    from accel_jax.report._studies import STUDIES

    status = json.loads((report_dir.parent.parent / "quick_report.done").read_text())
    scripts = status["study_scripts"]
    assert sorted(scripts) == sorted(STUDIES)
    for name, run in scripts.items():
        assert run["returncode"] == 0, (name, run["seconds"], run["output"])
        assert "written:" in run["output"], name
        assert f"[{name}] up to date" in status["output"], name


@pytest.mark.slow
def test_quick_report_studies_ran_on_their_own_cpu_shares(report_dir):
    """Side by side, each study process is pinned to its share of the CPUs (one core each
    on a 2-core machine) and its provenance says how many it had. (The fixture runs the
    study scripts two at a time with the report's own `worker_cpus` shares.)"""
    from accel_jax._runtime import usable_cpus
    from accel_jax.report._run import default_jobs

    n, jobs = len(usable_cpus()), default_jobs(7)
    shares = {n // jobs, -(-n // jobs)} if jobs > 1 else {n}
    for folder in report_dir.parent.iterdir():
        result = folder / "result.json"
        if folder.is_dir() and result.exists():
            assert json.loads(result.read_text())["provenance"]["cpus"] in shares, folder.name


def test_quick_report_ran_where_xla_rejects_one_of_the_options(report_dir):
    """The fixture's processes run on a jaxlib that rejects one of the package's options
    (simulated: tests/xla_rejects). Every study finished (the tests above), the option was
    skipped and named in each study's provenance, the options XLA accepts were applied,
    and every study records where its work ran."""
    from accel_jax._runtime import CPU_SCHEDULER_FLAG, FAST_COMPILE_FLAGS
    from accel_jax.report._studies import STUDIES

    unknown = "--xla_accel_jax_simulated_unknown_option=false"
    for name in STUDIES:
        provenance = json.loads((report_dir.parent / name / "result.json").read_text())[
            "provenance"
        ]
        assert list(provenance["xla_options_skipped"]) == [unknown], name
        flags = provenance["xla_flags"].split()
        assert unknown not in flags and CPU_SCHEDULER_FLAG in flags, name
        assert FAST_COMPILE_FLAGS[0] in flags, name  # --quick
        assert provenance["placement"]["device"] == "auto", name
        assert provenance["placement"]["unsharded_work_on"].startswith("cpu"), name


def test_study_script_bad_option_or_foreign_folder_is_one_line_and_exit_2(tmp_path):
    """A study's command line: a bad option value, or an --out folder that holds something
    else, is one line on stderr, exit status 2, no traceback, nothing written."""
    import subprocess
    import sys

    root = Path(__file__).resolve().parent.parent / "studies"

    def run(script, *args):
        return subprocess.run(
            [sys.executable, str(root / script), *args],
            capture_output=True,
            text=True,
            timeout=300,
        )

    out = run("sim_to_real_validation.py", "--kinds", "bogus", "--out", str(tmp_path / "v"))
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert "unknown kind(s) ['bogus']" in out.stderr and not (tmp_path / "v").exists()
    foreign = tmp_path / "t5"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    out = run("table5_gap.py", "--out", str(foreign))
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert "not written by accel-jax report" in out.stderr
    assert sorted(p.name for p in foreign.iterdir()) == ["notes.txt"]


def test_no_study_starts_jax_at_import():
    """A study script must not start JAX's backend when imported: its XLA options (the
    quick run's, the checked ones) and `--device` are set after the import and before the
    backend starts. (vibration_compensation built a transfer function at import, so its
    quick run never had the fast-compile emitters and `--device cpu` could not apply.)"""
    import subprocess
    import sys

    from accel_jax.report._studies import STUDIES

    program = (
        "import importlib.util, sys\n"
        "from jax._src import xla_bridge\n"
        "for path in sys.argv[1:]:\n"
        "    spec = importlib.util.spec_from_file_location('study', path)\n"
        "    spec.loader.exec_module(importlib.util.module_from_spec(spec))\n"
        "    print(path, xla_bridge.backends_are_initialized())\n"
    )
    paths = [str(ROOT / "studies" / f"{name}.py") for name in STUDIES]
    out = subprocess.run(
        [sys.executable, "-c", program, *paths], capture_output=True, text=True, timeout=300
    )
    assert out.returncode == 0, out.stderr
    started = [line.split()[0] for line in out.stdout.splitlines() if line.endswith("True")]
    assert not started, started
