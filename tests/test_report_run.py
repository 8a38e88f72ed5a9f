"""The report runner: caching/resume by inputs and code, and never deleting unasked."""

import html
import json
import textwrap
from pathlib import Path

import pytest

from accel_jax.report import write_json_atomic
from accel_jax.report._html import REPORT_MARKER
from accel_jax.report._run import ERROR_LOG, MARKER, ReportError, StudiesFailed, run_report

FAKE_STUDY = textwrap.dedent(
    """
    import json
    from pathlib import Path

    from accel_jax.report import write_json_atomic

    def run(out_dir, *, quick=False):
        out_dir = Path(out_dir)
        runs = out_dir.parent / "runs.log"          # counts how often the study really ran
        runs.write_text(runs.read_text() + "x" if runs.exists() else "x")
        if (out_dir.parent / "interrupt").exists():
            (out_dir / "partial.txt").write_text("half")
            raise KeyboardInterrupt
        write_json_atomic(out_dir / "result.json", {"title": "fake", "quick": quick})
        return {}
    """
)


@pytest.fixture
def setup(tmp_path):
    studies = tmp_path / "studies"
    studies.mkdir()
    (studies / "fake.py").write_text(FAKE_STUDY)
    out = tmp_path / "out" / "report"

    def run(**kw):
        return run_report(
            out, studies=("fake",), studies_dir=studies, progress=False, echo=lambda s: None, **kw
        )

    return tmp_path / "out", out, run


def runs(root):
    return len((root / "runs.log").read_text())


def test_second_run_is_cached_and_index_is_ours(setup):
    root, out, run = setup
    index = run()
    assert REPORT_MARKER in index.read_text()
    assert json.loads((root / "fake" / MARKER).read_text())["complete"] is True
    run()
    assert runs(root) == 1  # the second run reused the result
    run(force=True)
    assert runs(root) == 2


def test_other_options_are_not_overwritten_without_force(setup):
    root, out, run = setup
    run()
    before = (root / "fake" / "result.json").read_text()
    with pytest.raises(ReportError, match="different run.*--force"):
        run(quick=True)
    assert (root / "fake" / "result.json").read_text() == before  # nothing touched
    run(quick=True, force=True)
    assert json.loads((root / "fake" / "result.json").read_text())["quick"] is True


def test_interrupted_study_is_redone_on_resume(setup):
    root, out, run = setup
    (root).mkdir(parents=True, exist_ok=True)
    (root / "interrupt").write_text("")
    with pytest.raises(KeyboardInterrupt):
        run()
    assert json.loads((root / "fake" / MARKER).read_text())["complete"] is False
    (root / "interrupt").unlink()
    run()
    assert runs(root) == 2
    assert (root / "fake" / "result.json").exists()


def test_foreign_folders_and_files_are_left_alone(setup):
    root, out, run = setup
    (root / "fake").mkdir(parents=True)
    (root / "fake" / "mine.txt").write_text("user data")
    with pytest.raises(ReportError, match="not written by accel-jax"):
        run()
    assert (root / "fake" / "mine.txt").read_text() == "user data"
    (root / "fake" / "mine.txt").unlink()
    out.mkdir(parents=True)
    (out / "index.html").write_text("<html>someone else's page</html>")
    with pytest.raises(ReportError, match="index.html exists"):
        run()
    assert "someone else" in (out / "index.html").read_text()


PARAMS_STUDY = textwrap.dedent(
    """
    from pathlib import Path

    from accel_jax.report import write_json_atomic

    def run(out_dir, *, quick=False, params=None):
        damping = None if params is None else float(params.damping)
        write_json_atomic(Path(out_dir) / "result.json", {"title": "p", "damping": damping})
        return {}
    """
)


def test_user_device_reaches_studies_that_take_it_and_keys_the_cache(setup, tmp_path):
    import accel_jax as aj

    root, out, run = setup
    (tmp_path / "studies" / "withparams.py").write_text(PARAMS_STUDY)

    def run_both(**kw):
        return run_report(
            out,
            studies=("fake", "withparams"),
            studies_dir=tmp_path / "studies",
            progress=False,
            echo=lambda s: None,
            **kw,
        )

    run_both()
    assert json.loads((root / "withparams" / "result.json").read_text())["damping"] is None
    device = aj.ServoParams.reference(damping=3e-5)
    # Another device is another run: its results do not silently replace the reference's.
    with pytest.raises(ReportError, match="different run"):
        run_both(params=device)
    run_both(params=device, force=True)
    assert json.loads((root / "withparams" / "result.json").read_text())["damping"] == 3e-5
    assert runs(root) == 2  # the study without a params argument ran again, unchanged


WORKER_STUDY = textwrap.dedent(
    """
    import os
    from pathlib import Path

    import jax
    import jax.numpy as jnp

    from accel_jax.report import write_json_atomic

    def run(out_dir, *, quick=False, params=None):
        key = jax.random.key(len(Path(out_dir).name))  # the study seeds itself
        value = jnp.sum(jax.random.normal(key, (1000,), jnp.float64 if
                        jax.config.jax_enable_x64 else jnp.float32) ** 2)
        write_json_atomic(Path(out_dir) / "result.json", {
            "title": "w", "pid": os.getpid(), "x64": bool(jax.config.jax_enable_x64),
            "value": float(value), "damping": None if params is None else float(params.damping),
        })
        if (Path(out_dir).parent / f"fail_{Path(out_dir).name}").exists():
            raise ValueError("this study rejects its input")
        return {}
    """
)


def _worker_setup(tmp_path, names):
    studies = tmp_path / "studies"
    studies.mkdir(exist_ok=True)
    for name in names:
        (studies / f"{name}.py").write_text(WORKER_STUDY)
    return studies


def test_parallel_studies_run_in_their_own_processes_with_the_same_results(tmp_path):
    """jobs > 1: each study in a spawned process, with the parent's float64 setting and
    device, and results identical to running them one by one in this process."""
    import os

    import jax

    import accel_jax as aj

    names = ("a1", "bb2", "ccc3")
    studies = _worker_setup(tmp_path, names)
    device = aj.ServoParams.reference(damping=3e-5)
    results = {}
    for jobs in (1, 2):
        out = tmp_path / f"jobs{jobs}" / "report"
        messages = []
        run_report(
            out,
            studies=names,
            studies_dir=studies,
            progress=False,
            echo=messages.append,
            params=device,
            jobs=jobs,
        )
        results[jobs] = {n: json.loads((out.parent / n / "result.json").read_text()) for n in names}
        for n in names:
            assert json.loads((out.parent / n / MARKER).read_text())["complete"] is True
            assert any(m.startswith(f"[{n}] done in") for m in messages)
    assert {r["pid"] for r in results[1].values()} == {os.getpid()}
    pids = {r["pid"] for r in results[2].values()}
    assert os.getpid() not in pids and len(pids) == len(names)  # a process per study
    for n in names:
        assert results[2][n]["x64"] is bool(jax.config.jax_enable_x64)
        for field in ("value", "damping", "x64"):
            assert results[2][n][field] == results[1][n][field]
    assert results[2]["a1"]["damping"] == 3e-5


@pytest.mark.parametrize("jobs", [1, 2])
def test_a_failing_study_is_marked_failed_while_the_others_finish(tmp_path, jobs):
    """A study that raises does not take the report down: the others finish, the page is
    written with the study shown failed (its one-line reason, where its log is), the run
    ends in `StudiesFailed` naming it; a second run redoes only it."""
    names = ("a1", "bb2", "ccc3")
    studies = _worker_setup(tmp_path, names)
    out = tmp_path / "out" / "report"
    out.parent.mkdir(parents=True)
    (out.parent / "fail_bb2").write_text("")
    messages = []
    with pytest.raises(StudiesFailed) as caught:
        run_report(
            out, studies=names, studies_dir=studies, progress=False, echo=messages.append, jobs=jobs
        )
    assert caught.value.failures == {"bb2": "ValueError: this study rejects its input"}
    assert caught.value.index == out / "index.html"
    assert "1 study failed" in str(caught.value) and "bb2" in str(caught.value)
    marker = json.loads((out.parent / "bb2" / MARKER).read_text())
    assert marker["complete"] is False and marker["failed"].startswith("ValueError")
    log = (out.parent / "bb2" / ERROR_LOG).read_text()
    assert "Traceback" in log and "this study rejects its input" in log
    for name in ("a1", "ccc3"):  # the others ran to the end
        assert json.loads((out.parent / name / MARKER).read_text())["complete"] is True
    assert any(m.startswith("[bb2] FAILED: ValueError") for m in messages)
    page = (out / "index.html").read_text()
    assert "1 of the studies failed" in page
    section = page.split('<section id="bb2">')[1].split("</section>")[0]
    assert "failed" in section and "this study rejects its input" in section
    assert html.escape(str(out.parent / "bb2" / ERROR_LOG)) in section
    (out.parent / "fail_bb2").unlink()
    messages.clear()
    run_report(
        out, studies=names, studies_dir=studies, progress=False, echo=messages.append, jobs=jobs
    )  # resumes: redoes bb2 only
    assert json.loads((out.parent / "bb2" / MARKER).read_text())["complete"] is True
    assert sum("up to date" in m for m in messages) == 2
    assert "studies failed" not in (out / "index.html").read_text()


def test_cli_report_with_a_failing_study_writes_the_page_and_exits_1(tmp_path, monkeypatch):
    """`accel-jax report`: a failing study gives a summary on stderr and exit status 1,
    never a traceback, and the page is written."""
    from click.testing import CliRunner

    from accel_jax import cli

    names = ("a1", "bb2")
    studies = _worker_setup(tmp_path, names)
    out = tmp_path / "out" / "report"
    out.parent.mkdir(parents=True)
    (out.parent / "fail_bb2").write_text("")
    monkeypatch.setattr(cli, "STUDIES", names)
    monkeypatch.setattr(cli, "_studies_dir", lambda: studies)
    result = CliRunner().invoke(
        cli.main,
        ["report", "--out", str(out), "--no-progress", "--jobs", "1", "--no-compile-cache"],
    )
    assert result.exit_code == 1, result.output
    assert "Traceback" not in result.output
    assert f"report written: {out / 'index.html'}" in result.output
    assert "1 study failed" in result.output
    assert "bb2: ValueError: this study rejects its input (log: " in result.output
    assert (out / "index.html").exists()


@pytest.mark.parametrize("jobs", [0, -1, 1.5, "2"])
def test_bad_jobs_values_are_refused(setup, jobs):
    root, out, run = setup
    with pytest.raises(ReportError, match="jobs must be a positive whole number"):
        run(jobs=jobs)
    assert not root.exists()


def test_cli_report_rejects_a_bad_params_file(tmp_path):
    from click.testing import CliRunner

    from accel_jax.cli import main

    bad = tmp_path / "device.toml"
    bad.write_text("wobble = 3\n")
    result = CliRunner().invoke(
        main, ["report", "--out", str(tmp_path / "r"), "--params", str(bad), "--no-progress"]
    )
    assert result.exit_code == 1
    assert "unknown key" in result.output and "Traceback" not in result.output
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("jobs", ["0", "two"])
def test_cli_report_rejects_a_bad_jobs_value(tmp_path, jobs):
    from click.testing import CliRunner

    from accel_jax.cli import main

    result = CliRunner().invoke(main, ["report", "--out", str(tmp_path / "r"), "--jobs", jobs])
    assert result.exit_code == 2
    assert "--jobs" in result.output and "Traceback" not in result.output
    assert not (tmp_path / "r").exists()


def test_overview_collects_published_numbers_and_each_studys_own_tables(tmp_path):
    """The report renders every study's `overview` tables without knowing their schema."""
    from accel_jax.report._html import build_report

    def study(name, payload):
        folder = tmp_path / name
        write_json_atomic(folder / "result.json", {"title": name, **payload})
        return folder

    dirs = [
        study(
            "scale_factor_identification",
            {
                "summary": [
                    {"quantity": "δK_a oscillatory", "ours": "0.136", "paper": "0.141"},
                    {"quantity": "beyond the paper", "ours": "0.0", "paper": "—"},
                ]
            },
        ),
        study(
            "tolerance_limits",
            {
                "overview": [
                    {
                        "title": "Tolerance limits",
                        "note": "n",
                        "columns": ["example", "method", "A1 [ppm]"],
                        "rows": [
                            ["Cyclone-4", "paper, Table 2", 445],
                            ["tactical, short range", "p", 1],
                        ],
                    }
                ]
            },
        ),
        study(
            "sim_to_real_validation",
            {
                "overview": [
                    {
                        "title": "blind",
                        "columns": ["kind", "n", "acc"],
                        "rows": [["noise", 130, 0.967]],
                    }
                ]
            },
        ),
    ]
    page = build_report(dirs, tmp_path / "report" / "index.html", title="t").read_text()
    overview = page.split('id="overview"')[1].split('id="scale_factor_identification"')[0]
    assert "δK_a oscillatory" in overview and "0.141" in overview
    assert "beyond the paper" not in overview  # rows without a published value stay below
    assert "Cyclone-4" in overview and "445" in overview and "tactical, short range" in overview
    assert "0.967" in overview and "130" in overview


def test_side_by_side_the_longest_study_starts_first(tmp_path):
    from accel_jax.report._run import _longest_first, _write_marker

    names = ["a1", "bb2", "ccc3", "d4"]
    assert _longest_first(names, tmp_path, {}) == names  # nothing known: the given order
    typical = {"ccc3": 10.0, "a1": 1.0}
    assert _longest_first(names, tmp_path, typical) == ["ccc3", "a1", "bb2", "d4"]
    (tmp_path / "bb2").mkdir()
    _write_marker(tmp_path / "bb2", "key", complete=True, seconds=50.0)  # took 50 s last time
    assert _longest_first(names, tmp_path, typical) == ["bb2", "ccc3", "a1", "d4"]


def test_a_study_process_that_dies_is_reported_not_a_traceback(tmp_path):
    # A worker killed from outside (as by the kernel's out-of-memory killer): that study
    # marked failed with the signal named, the other study's results kept, the page written.
    studies = _worker_setup(tmp_path, ("a1",))
    (studies / "dies.py").write_text(
        "import os, signal\n"
        "def run(out_dir, *, quick=False):\n"
        "    os.kill(os.getpid(), signal.SIGKILL)\n"
    )
    out = tmp_path / "out" / "report"
    with pytest.raises(StudiesFailed, match="died before it finished") as caught:
        run_report(
            out,
            studies=("a1", "dies"),
            studies_dir=studies,
            progress=False,
            echo=lambda s: None,
            jobs=2,
        )
    assert "killed by signal 9" in caught.value.failures["dies"]
    assert json.loads((out.parent / "dies" / MARKER).read_text())["complete"] is False
    assert json.loads((out.parent / "a1" / MARKER).read_text())["complete"] is True
    assert "died before it finished" in (out.parent / "dies" / ERROR_LOG).read_text()
    assert (out / "index.html").exists()


def test_default_jobs_follow_cores_and_memory(monkeypatch):
    from accel_jax.report import _run

    monkeypatch.setattr(_run, "usable_cpus", lambda: list(range(16)))
    monkeypatch.setattr(_run, "_physical_memory", lambda: 64 * 2**30)
    assert _run.default_jobs(7) == 4  # at most 4
    assert _run.default_jobs(2) == 2  # no more than studies to run
    monkeypatch.setattr(_run, "_physical_memory", lambda: 9 * 2**30)
    assert _run.default_jobs(7) == 2  # 4 GiB each
    monkeypatch.setattr(_run, "_physical_memory", lambda: 2**30)
    assert _run.default_jobs(7) == 1
    monkeypatch.setattr(_run, "_physical_memory", lambda: None)
    monkeypatch.setattr(_run, "usable_cpus", lambda: [3])  # e.g. a process pinned to one CPU
    assert _run.default_jobs(7) == 1
    monkeypatch.setattr(_run.jax, "default_backend", lambda: "gpu")
    monkeypatch.setattr(_run, "usable_cpus", lambda: list(range(16)))
    # On a GPU host too: the studies' latency-bound work runs on the host's cores, and the
    # processes share the GPU without preallocating its memory (apply_device(shared=True)).
    assert _run.default_jobs(7) == 4


def test_side_by_side_workers_get_disjoint_cpu_shares():
    from accel_jax.report._run import worker_cpus

    # Two studies on two cores: one core each; four on 16: every fourth CPU each.
    assert [worker_cpus(slot, 2, [0, 1]) for slot in (1, 2)] == [[0], [1]]
    shares = [worker_cpus(slot, 4, list(range(16))) for slot in (1, 2, 3, 4)]
    assert shares[0] == [0, 4, 8, 12]
    assert sorted(sum(shares, [])) == list(range(16))  # disjoint, all used
    # The affinity mask's own numbering is kept (a container given CPUs 2, 5 and 7).
    assert worker_cpus(2, 2, [2, 5, 7]) == [5]
    # Not pinned: one job, fewer CPUs than jobs, a slot out of range.
    assert worker_cpus(1, 1, [0, 1]) is None
    assert worker_cpus(1, 3, [0, 1]) is None
    assert worker_cpus(0, 2, [0, 1]) is None


def test_usable_cpus_follow_the_affinity_mask(monkeypatch):
    from accel_jax import _runtime as _xla

    monkeypatch.setattr(_xla.os, "sched_getaffinity", lambda pid: {5, 2}, raising=False)
    assert _xla.usable_cpus() == [2, 5]
    monkeypatch.delattr(_xla.os, "sched_getaffinity", raising=False)
    monkeypatch.setattr(_xla.os, "cpu_count", lambda: None)
    assert _xla.usable_cpus() == [0]


def test_first_screen_status_quick_banner_and_glossary(tmp_path):
    """The first screen answers: each published number's status (reproduced / explained /
    differs, targets met / missed) with a count, the rows that differ listed; a quick run
    says so on top and on every figure; the glossary closes the page and the README
    carries every term of it."""
    from accel_jax.report._glossary import GLOSSARY
    from accel_jax.report._html import build_report, row_status

    assert row_status({"ours": 0.1358, "paper": "0.141"}) == "reproduced"  # within 5 %
    assert row_status({"ours": "0.2328 ± 0.0201", "paper": "0.141"}) == "differs"
    assert row_status({"ours": "1.09 ± 0.94", "paper": "0.682"}) == "reproduced"  # spread
    assert row_status({"ours": 0.23, "paper": 0.141, "explanation": "γ = 3/4"}) == "explained"
    assert row_status({"ours": 0.63, "paper": 0.9, "target": "≥"}) == "missed"
    assert row_status({"ours": 0.0, "paper": 0.05, "target": "≤"}) == "met"
    assert row_status({"ours": 1.0, "paper": "—"}) is None
    assert row_status({"ours": 0.3, "paper": "'practically all'", "status": "differs"}) == (
        "differs"
    )
    folder = tmp_path / "scale_factor_identification"
    (folder).mkdir()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots()
    ax.plot([0, 1])
    fig.savefig(folder / "f.png")
    plt.close(fig)
    write_json_atomic(
        folder / "result.json",
        {
            "title": "t",
            "summary": [
                {"quantity": "δK_a exact", "ours": 0.1358, "paper": "0.141"},
                {"quantity": "Table 3 mean |δ_V|", "ours": 0.245, "paper": 1.417},
                {"quantity": "strict naming", "ours": 0.63, "paper": 0.9, "target": "≥"},
                {"quantity": "false alarms", "ours": 0.0, "paper": 0.05, "target": "≤"},
                {"quantity": "γ = 3/4", "ours": 0.2328, "paper": 0.141, "explanation": "γ"},
            ],
            "figures": [{"file": "f.png", "caption": "a figure"}],
        },
    )
    page = build_report([folder], tmp_path / "r" / "index.html", title="t", quick=True)
    text = page.read_text()
    first = text.split("Published numbers and targets beside ours")[0]
    assert "Status of 5 published numbers and targets" in first
    for count in ("1 reproduced", "1 explained", "1 differs", "1 met", "1 missed"):
        assert count in first, count
    assert "Table 3 mean |δ_V|" in first and "strict naming" in first  # flagged rows
    assert "false alarms" not in first  # a met target is not flagged
    assert "Quick run" in text.split("<ul>")[0]  # the banner before the contents
    assert "[quick run: reduced statistics]</b> a figure" in text
    glossary = text.split('id="glossary"')[1]
    readme = (Path(__file__).resolve().parent.parent / "README.md").read_text()
    for term, _ in GLOSSARY:
        assert html.escape(term) in glossary and f"**{term}**" in readme, term
    full = build_report([folder], tmp_path / "r2" / "index.html", title="t").read_text()
    assert "Quick run" not in full and "[quick run" not in full


def test_a_study_script_that_raises_is_one_line_exit_1_and_a_log(tmp_path):
    """A study run alone (`python studies/<name>.py`): a study that raises is one line on
    stderr naming it and its log, exit status 1, no traceback on the terminal; the folder
    is marked failed as the report marks it."""
    import subprocess
    import sys

    script = tmp_path / "broken.py"
    script.write_text(
        textwrap.dedent(
            '''
            """A study that needs a package this machine lacks."""
            import sys

            from accel_jax.report._study import study_main, study_run

            @study_run()
            def run(out_dir, *, quick=False):
                raise ModuleNotFoundError("No module named 'an_optional_package'")

            if __name__ == "__main__":
                sys.exit(study_main(run, __file__, __doc__))
            '''
        )
    )
    out = tmp_path / "out"
    done = subprocess.run(
        [sys.executable, str(script), "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 1
    assert "Traceback" not in done.stderr and len(done.stderr.strip().splitlines()) == 1
    assert (
        "the study failed: ModuleNotFoundError: No module named 'an_optional_package' "
        f"(log: {out / ERROR_LOG})" in done.stderr
    )
    assert "Traceback" in (out / ERROR_LOG).read_text()
    marker = json.loads((out / MARKER).read_text())
    assert marker["complete"] is False and marker["failed"].startswith("ModuleNotFoundError")


def test_figures_keep_a_figures_own_layout_without_a_warning(tmp_path):
    """A figure made with a constrained layout (the identification figure) is saved with it,
    silently; one without a layout engine gets the tight layout."""
    import warnings

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from accel_jax.report._study import Figures

    figures = Figures(tmp_path)
    constrained = plt.figure(layout="constrained")
    constrained.add_subplot().plot([0, 1])
    plain = plt.figure()
    plain.add_subplot().plot([0, 1])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        figures.save(constrained, "constrained.png", "a constrained figure")
        figures.save(plain, "plain.png", "a plain figure")
    assert type(constrained.get_layout_engine()).__name__ == "ConstrainedLayoutEngine"
    # tight_layout moved the plain figure's axes off matplotlib's default placement.
    default = plt.figure().add_subplot().get_position().bounds
    assert plain.axes[0].get_position().bounds != pytest.approx(default)
    assert [e["file"] for e in figures.entries] == ["constrained.png", "plain.png"]
    assert (tmp_path / "constrained.png").stat().st_size > 0
    plt.close("all")
