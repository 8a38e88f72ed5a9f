"""Test configuration: the tests run in float64 (the effects measured — δK_a at 0.1 %,
machine-precision agreement between simulators — need it). This is the test suite's
choice; the library itself never changes JAX's global settings."""

import os  # noqa: E402

import accel_jax  # noqa: F401  (applies the XLA:CPU deadlock workaround; see _runtime.py)
from accel_jax._runtime import apply_fast_compile  # noqa: E402

# The suite compiles thousands of small programs and runs most of them a few times: it
# compiles as the CLI does, with XLA:CPU's older loop emitters (`FAST_COMPILE_FLAGS`; set
# before JAX starts its backend, unless the caller's XLA_FLAGS chose the option). Measured
# on the 2-core CPU, `pytest -n 2`: tests/test_diagnose_step_set.py's four stop-level and
# tie tests 87 → 55 s, tests/test_noise_sensor.py (run-bound) 150 → 132 s. The study
# scripts the quick report runs get the user's environment, not this.
apply_fast_compile()

# A persistent compilation cache of this test session alone: empty when the session starts
# (every program compiled cold, as on a user's first run; nothing carried from an earlier
# session), then shared by both pytest-xdist workers and every process they start (the CLI
# tests, the quick report's studies and its blind diagnosis), so that a program is compiled
# once per session instead of once per process. The controller makes it (its workers
# inherit the variable) and removes it at the end (`pytest_unconfigure`).
# `ACCEL_JAX_TEST_CACHE=keep`: a cache kept between sessions instead, in
# `$XDG_CACHE_HOME/accel_jax/test-xla` (`~/.cache/...`), pruned by the controller before its
# workers start (`cache_pruning.prune_test_cache`: entries unused for 30 days, then the
# least recently used beyond 2 GiB) — for a developer rerunning a few files (one step file
# alone: 362.9 s cold, 269.6 s warm); the whole suite measured no faster with it
# (docs/performance.md), so `make test` keeps the session's own. A folder the caller chose
# (`ACCEL_JAX_CACHE_DIR`, `off` for none) is used as it is. tests/test_runtime.py and
# tests/test_cli.py check the cache itself in fresh processes, each with its own folder.
if "ACCEL_JAX_CACHE_DIR" not in os.environ:
    import tempfile  # noqa: E402
    from pathlib import Path  # noqa: E402

    _folder = None
    if os.environ.get("ACCEL_JAX_TEST_CACHE", "").strip().lower() == "keep":
        from accel_jax._cache import cache_home  # noqa: E402

        _folder = cache_home() / "test-xla"
        try:
            _folder.mkdir(parents=True, exist_ok=True)
            if "PYTEST_XDIST_WORKER" not in os.environ:
                from cache_pruning import prune_test_cache  # noqa: E402

                prune_test_cache(_folder)
        except OSError:  # a read-only home: a cache of this session alone
            _folder = None
    if _folder is None:
        _folder = Path(tempfile.mkdtemp(prefix="accel_jax_test_xla_"))
        os.environ["_ACCEL_JAX_TEST_CACHE_OWNER"] = str(os.getpid())
    os.environ["ACCEL_JAX_CACHE_DIR"] = str(_folder)

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

from accel_jax._cache import enable_compilation_cache  # noqa: E402

enable_compilation_cache()  # this process's own calls too, not only the CLI's

import fcntl  # noqa: E402
import inspect  # noqa: E402
import shutil  # noqa: E402
import tempfile  # noqa: E402
import json  # noqa: E402
from pathlib import Path  # noqa: E402

import pytest  # noqa: E402

from accel_jax._cache import bound_compiled_programs  # noqa: E402


_TESTS = Path(__file__).resolve().parent
_GROUPS = "ACCEL_JAX_TEST_GROUPS"  # the file where the workers leave the groups (below)


def pytest_configure(config):
    if config.getoption("dist", "no") != "no" and "PYTEST_XDIST_WORKER" not in os.environ:
        # The controller names the file before it starts the workers (they inherit it).
        folder = Path(tempfile.mkdtemp(prefix="accel_jax_groups_"))
        os.environ[_GROUPS] = str(folder / "groups.json")


def pytest_unconfigure(config):
    target = os.environ.get(_GROUPS)
    if target and "PYTEST_XDIST_WORKER" not in os.environ:
        shutil.rmtree(Path(target).parent, ignore_errors=True)
    if os.environ.get("_ACCEL_JAX_TEST_CACHE_OWNER") == str(os.getpid()):
        shutil.rmtree(os.environ["ACCEL_JAX_CACHE_DIR"], ignore_errors=True)


def pytest_collection_modifyitems(config, items):
    """Tests that share a module- or session-scoped fixture of this folder run on one
    pytest-xdist worker (`make test`: `--dist loadgroup`, scheduled by
    `pytest_xdist_make_scheduler` below): each worker computes the fixtures its own tests
    need, so a module fixture whose tests were dealt to both workers was computed twice —
    a diagnosis of a dozen step records (~2 min), a noise analysis — on both cores at once.
    A test marked `worker_of(name)` joins the group of the session fixture `name` (its
    records' compiled programs are in that worker's process: docs/performance.md).
    Every other test is dealt on its own. The quick report's tests come first (the longest
    fixture, about seven minutes, made by two study processes while the other worker runs
    the rest: made late, the other worker reaching a study's test waited idle for it, 84 s
    in one fresh-clone run); the rest follow in the files' order (`pytest_xdist_make_scheduler`).

    pytest-xdist's own `xdist_group` mark does not group under pytest 9 (it renames the
    node id through an attribute pytest 9 no longer reads), so the workers write the groups
    to a file that the controller's scheduler reads."""
    groups: dict[str, str] = {}
    for item in items:
        # `@pytest.mark.worker_of("step_cases")`: on the worker that makes that session
        # fixture, whose records share the test's layout (`RecordShape`), so that its
        # programs are traced and compiled once in that process, not again in the other.
        mark = item.get_closest_marker("worker_of")
        if mark is not None:
            groups[item.nodeid] = mark.args[0]
            continue
        info = getattr(item, "_fixtureinfo", None)
        if info is None:
            continue
        shared = [
            name
            for name in item.fixturenames
            if (defs := info.name2fixturedefs.get(name))
            and defs[-1].scope in ("module", "session")
            and Path(inspect.getfile(defs[-1].func)).parent == _TESTS
        ]
        if shared:
            module = getattr(item.module, "__name__", "?")
            # A session fixture's users share one worker, whatever their module (the
            # fixture is then made once: `quick_report`, `step_cases`).
            session = [
                name for name in shared if info.name2fixturedefs[name][-1].scope == "session"
            ]
            groups[item.nodeid] = session[0] if session else module
    items.sort(key=lambda item: groups.get(item.nodeid) != "quick_report")  # stable
    target = os.environ.get(_GROUPS)
    if target and "PYTEST_XDIST_WORKER" in os.environ:
        partial = Path(f"{target}.{os.environ['PYTEST_XDIST_WORKER']}")
        partial.write_text(json.dumps(groups))
        partial.replace(target)  # every worker collects the same tests: the same groups


@pytest.hookimpl(optionalhook=True)  # a pytest-xdist hook: the suite also runs without it
def pytest_xdist_make_scheduler(config, log):
    if config.getoption("dist") != "loadgroup":
        return None
    from xdist.scheduler import LoadScopeScheduling

    # The work units in the files' order, not pytest-xdist's default of the largest group
    # first: that put the `step_cases` group (test_diagnose_step*.py, ~7 min) first on the
    # worker beside the quick report, compiling the step fit's programs at the same moment
    # as the quick report's blind diagnosis compiles the same ones (same record layout)
    # in its own process. The persistent compilation cache of the session shares them
    # across processes when one finishes first (checked: a step record diagnosed in this
    # suite's environment, then one of the same layout by the blind diagnosis's child in
    # the quick report's environment, `tests/xla_rejects` included: 31 cached programs, none
    # added by the second, which took 14.1 s against 23.5 s). In the files' order the
    # worker first runs the CLI, contact-truth and noise-diagnosis tests (~5 min), and the
    # step records then find the programs compiled.
    config.option.loadscopereorder = False

    class SharedFixtureScheduling(LoadScopeScheduling):
        """A test's work unit: its group (the tests sharing a fixture), else itself."""

        _groups: dict | None = None

        def _split_scope(self, nodeid: str) -> str:
            if self._groups is None:
                path = Path(os.environ.get(_GROUPS, "-"))
                self._groups = json.loads(path.read_text()) if path.is_file() else {}
            return self._groups.get(nodeid, nodeid)

    return SharedFixtureScheduling(config, log)


@pytest.fixture(autouse=True)
def _bounded_compiled_programs():
    # A pytest-xdist worker compiles thousands of programs: past vm.max_map_count LLVM
    # fails ('Cannot allocate memory') and the worker segfaults (`bound_compiled_programs`).
    yield
    bound_compiled_programs()


# Quick-run order of the study scripts: the longest first, so that two side by side finish
# close together (measured quick wall times on the 2-core CPU, one core each).
_QUICK_ORDER = (
    "sim_to_real_validation",
    "scale_factor_identification",
    "sensing_element_ml",
    "noise_identification",
    "vibration_compensation",
    "tolerance_limits",
    "table5_gap",
)
# A study that hangs (the XLA:CPU deadlock) fails instead. The quick blind validation, the
# longest, took 745–784 s in the four suite runs of 2026-12-03 (on a day the Monte Carlo
# benchmark's lfilter baseline ran at 1.15e3 traj/s against 1.4e3–2.4e3 before): 900 s
# left too little room for a slower machine, so a slow run is not taken for a hang.
_SCRIPT_TIMEOUT_S = 1500


def _popen_pinned(command, cpus, **options):
    """`subprocess.Popen` of a process pinned to `cpus` (None: not pinned). The child
    inherits the calling thread's CPU mask, set here for the call and restored after — not
    a `preexec_fn`, which would make Python fork a multithreaded (JAX) process."""
    import subprocess

    pinned = cpus is not None and hasattr(os, "sched_setaffinity")
    before = os.sched_getaffinity(0) if pinned else None
    if pinned:
        os.sched_setaffinity(0, cpus)
    try:
        return subprocess.Popen(command, stderr=subprocess.STDOUT, **options)
    finally:
        if pinned:
            os.sched_setaffinity(0, before)


def _run_study_scripts(root: Path, names, jobs: int = 2) -> dict:
    """Run each study as a user would — `python studies/<name>.py --quick --out ROOT/<name>`
    in a fresh process — `jobs` at a time, each pinned to its share of the CPUs as the
    report's workers are. Returns {name: {"returncode", "seconds", "output"}}."""
    import sys
    import time

    from accel_jax._runtime import usable_cpus
    from accel_jax.report._run import worker_cpus

    studies_dir = Path(__file__).resolve().parent.parent / "studies"
    # `ACCEL_JAX_REPORT_CPUS` is not set (the report's workers set it, `_init_worker`): here
    # the other pytest worker is the other CPU's user, so the blind validation keeps to its
    # study's share, one process, as before (side by side it took the suite's fresh-clone
    # run from 1,504 to 1,772 s, one run each; its own test covers that path).
    env = _user_environment()
    env.pop("ACCEL_JAX_REPORT_CPUS", None)
    status, running, queue = {}, {}, list(names)
    free = list(range(1, jobs + 1))
    while queue or running:
        while queue and free:
            name, slot = queue.pop(0), free.pop(0)
            share = worker_cpus(slot, jobs, usable_cpus())
            log = open(root / f"{name}.log", "w+")  # noqa: SIM115
            command = [sys.executable, str(studies_dir / f"{name}.py"), "--quick"]
            proc = _popen_pinned([*command, "--out", str(root / name)], share, stdout=log, env=env)
            running[name] = (proc, slot, log, time.monotonic())
        time.sleep(0.5)
        for name, (proc, slot, log, started) in list(running.items()):
            elapsed = time.monotonic() - started
            if proc.poll() is None and elapsed < _SCRIPT_TIMEOUT_S:
                continue
            if proc.poll() is None:
                proc.kill()
                proc.wait()
            log.seek(0)
            status[name] = {
                "returncode": proc.returncode,
                "seconds": round(elapsed, 1),
                "output": log.read()[-4000:],
            }
            log.close()
            del running[name]
            free.append(slot)
    return status


REJECTS_AN_OPTION = Path(__file__).resolve().parent / "xla_rejects"
"""On PYTHONPATH, every Python process runs as on a jaxlib whose XLA rejects one of the
package's options (see its sitecustomize.py)."""


def _user_environment() -> dict:
    """The environment of the quick report's processes: a user's shell (no XLA_FLAGS from
    this test process), on a jaxlib that rejects one of the package's options (simulated,
    `REJECTS_AN_OPTION`): the option must be skipped, never abort a process, and change no
    result the studies' tests check."""
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    env.pop("_ACCEL_JAX_XLA_SKIPPED", None)
    env["PYTHONPATH"] = os.pathsep.join(
        [str(REJECTS_AN_OPTION), *filter(None, [os.environ.get("PYTHONPATH")])]
    )
    return env


@pytest.fixture(scope="session")
def step_cases():
    """The step records of `test_diagnose_step.CASES` (the independent simulator: one
    device, one test sequence, one effect each), diagnosed once per session in one call
    (`recommend=False`): {case: (record, result)}. test_diagnose_step.py reads every case,
    test_diagnose_step_measured.py the clean twins of its measured inputs; both modules'
    users of it run on one worker (`pytest_collection_modifyitems`), so it is made once
    (~5 min on the 2-core CPU; each module made its own before)."""
    from accel_jax.diagnose import diagnose_many
    from test_diagnose_step import CASES, _record

    names = list(CASES)
    records = [_record(10 + i, **CASES[name]) for i, name in enumerate(names)]
    results = diagnose_many(records, recommend=False)
    return {name: (data, result) for name, data, result in zip(names, records, results, strict=True)}


@pytest.fixture(scope="session")
def quick_report(tmp_path_factory, worker_id):
    """The quick report, made once per test session and shared by every test (and every
    pytest-xdist worker: the first to arrive makes it under a file lock, the others wait
    and reuse it). Returns the report folder; each study's output is beside it.

    Made as a user would: each study script runs alone in a fresh process (`--quick`,
    `_run_study_scripts`), then `accel-jax report --quick` assembles the report in a fresh
    process, reusing those runs (same folder, marker and cache key) — every process on a
    jaxlib that rejects one of the package's options (`_user_environment`). The studies'
    own tests read their results from here instead of running each study a second time;
    the script runs' exit codes and times are in `study_scripts` of `quick_report.done`."""
    import subprocess
    import sys

    from accel_jax.report._studies import STUDIES

    base = tmp_path_factory.getbasetemp()
    shared = base.parent if worker_id != "master" else base
    out = shared / "quick_report" / "report"
    done = shared / "quick_report.done"
    with open(shared / "quick_report.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            if not done.exists():
                out.parent.mkdir(parents=True, exist_ok=True)
                names = [n for n in _QUICK_ORDER if n in STUDIES]
                names += [n for n in STUDIES if n not in names]
                scripts = _run_study_scripts(out.parent, names)
                report = ["report", "--quick", "--no-progress", "--out", str(out)]
                result = subprocess.run(
                    [sys.executable, "-c", "from accel_jax.cli import main; main()", *report],
                    capture_output=True,
                    text=True,
                    env=_user_environment(),
                    timeout=_SCRIPT_TIMEOUT_S,
                )
                done.write_text(
                    json.dumps(
                        {
                            "exit_code": result.returncode,
                            "output": result.stdout + result.stderr,
                            "study_scripts": scripts,
                        }
                    )
                )
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)
    status = json.loads(done.read_text())
    assert status["exit_code"] == 0, status["output"]
    return out
