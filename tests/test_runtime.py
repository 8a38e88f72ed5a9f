"""Process-level settings (accel_jax/_runtime.py): the XLA:CPU deadlock workaround that
`import accel_jax` applies, the compile-time options of the quick runs, and the persistent
compilation cache the report uses. Each case runs in a fresh interpreter, because these
settings are process-global."""

import os
import subprocess
import sys

import pytest

from accel_jax._cache import compilation_cache_dir
from accel_jax._runtime import (
    CPU_SCHEDULER_FLAG,
    FAST_COMPILE_FLAGS,
    OPT_OUT_ENV,
)

_PROGRAM = """
import sys
from accel_jax._cache import enable_compilation_cache
folder = enable_compilation_cache(sys.argv[1] if len(sys.argv) > 1 else None)
import jax, jax.numpy as jnp
f = jax.jit(lambda x: jnp.sin(x) @ jnp.cos(x).T + jnp.linalg.inv(x @ x.T + 3.0 * jnp.eye(8)))
print(float(f(jnp.ones((8, 8))).sum()))
print(folder)
"""


def _run(args, **env):
    environment = {**os.environ, "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0", **env}
    environment.pop("JAX_COMPILATION_CACHE_DIR", None)
    out = subprocess.run(
        [sys.executable, "-c", _PROGRAM, *args],
        capture_output=True,
        text=True,
        env=environment,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr
    return out.stdout.split()


def test_cache_is_written_and_reused(tmp_path):
    folder = tmp_path / "xla"
    first = _run([str(folder)])
    entries = sorted(p.name for p in folder.rglob("*") if p.is_file())
    assert entries, "no compiled program was written to the cache"
    second = _run([str(folder)])
    assert second[0] == first[0]  # same result from the cached program
    assert sorted(p.name for p in folder.rglob("*") if p.is_file()) == entries  # a hit


def test_cache_folder_from_environment(tmp_path):
    folder = tmp_path / "from_env"
    assert _run([], ACCEL_JAX_CACHE_DIR=str(folder))[1] == str(folder)
    assert any(folder.rglob("*"))


@pytest.mark.parametrize("value", ["off", "0", ""])
def test_cache_disabled(monkeypatch, value):
    monkeypatch.setenv("ACCEL_JAX_CACHE_DIR", value)
    assert compilation_cache_dir() is None


def test_cache_default_folder(monkeypatch, tmp_path):
    monkeypatch.delenv("ACCEL_JAX_CACHE_DIR", raising=False)
    monkeypatch.delenv("JAX_COMPILATION_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert compilation_cache_dir() == tmp_path / "accel_jax" / "xla"


def test_unwritable_cache_folder_runs_without_it(tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    assert _run([str(blocker / "xla")])[1] == "None"


_IMPORT_PROGRAM = """
import os, sys, warnings
warnings.simplefilter("error")  # a warning fails the program (exit 1, message on stderr)
if sys.argv[1] == "late":
    import jax.numpy as jnp
    jnp.ones(1).block_until_ready()  # JAX's backend starts before accel_jax is imported
import accel_jax
print(accel_jax._XLA_WORKAROUND, os.environ.get("XLA_FLAGS", "-") or "-")
"""


def _import(mode="early", **env):
    environment = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", OPT_OUT_ENV)}
    out = subprocess.run(
        [sys.executable, "-c", _IMPORT_PROGRAM, mode],
        capture_output=True,
        text=True,
        env={**environment, **env},
        timeout=120,
    )
    return out.returncode, out.stdout.split(" ", 1), out.stderr


def test_import_sets_the_deadlock_workaround_before_the_backend_starts():
    code, (what, flags), _ = _import()
    assert code == 0 and what == "applied"
    assert CPU_SCHEDULER_FLAG in flags.split()


def test_import_respects_the_users_setting_and_the_opt_out():
    user = "--xla_cpu_enable_concurrency_optimized_scheduler=true --other=1"
    code, (what, flags), _ = _import(XLA_FLAGS=user)
    assert code == 0 and what == "user" and flags.strip() == user
    code, (what, flags), _ = _import(**{OPT_OUT_ENV: "off"})
    assert code == 0 and what == "user" and flags.strip() == "-"


def test_import_after_the_backend_started_warns_instead():
    """Too late to set the flag: one RuntimeWarning that says why and what to do."""
    import jax

    if jax.default_backend() != "cpu":
        pytest.skip("the deadlock and the warning concern XLA:CPU only")
    code, _, stderr = _import("late")
    assert code == 1
    assert "RuntimeWarning" in stderr and "could not set" in stderr and OPT_OUT_ENV in stderr
    code, (what, _), _ = _import("late", **{OPT_OUT_ENV: "0"})
    assert code == 0 and what == "user"


def test_fast_compile_flags_added_once_respecting_the_user(monkeypatch):
    import accel_jax._runtime as xla

    monkeypatch.setattr(xla, "_backend_started", lambda: False)
    monkeypatch.setattr(xla, "_gpu_plugin_installed", lambda: False)
    both = ["--xla_cpu_use_fusion_emitters=false", "--xla_backend_optimization_level=2"]
    monkeypatch.setenv("XLA_FLAGS", "--other=1")
    assert xla.apply_fast_compile() == both
    assert xla.apply_fast_compile() == []
    assert os.environ["XLA_FLAGS"].split() == ["--other=1", *both]
    # The user's own setting of an option wins.
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_use_fusion_emitters=true")
    assert xla.apply_fast_compile() == both[1:]
    assert os.environ["XLA_FLAGS"].split() == ["--xla_cpu_use_fusion_emitters=true", both[1]]
    # Where a GPU backend plugin is installed, the optimisation level (CPU-measured only)
    # is left at XLA's default.
    monkeypatch.setattr(xla, "_gpu_plugin_installed", lambda: True)
    monkeypatch.setenv("XLA_FLAGS", "")
    assert xla.apply_fast_compile() == both[:1]
    monkeypatch.setattr(xla, "_gpu_plugin_installed", lambda: False)
    # Once the backend has started, the flags could not apply: nothing is added.
    monkeypatch.setattr(xla, "_backend_started", lambda: True)
    monkeypatch.setenv("XLA_FLAGS", "")
    assert xla.apply_fast_compile() == []
    assert os.environ["XLA_FLAGS"] == ""


_FAST_PROGRAM = """
import sys
from accel_jax._runtime import apply_fast_compile, fast_compile
from accel_jax.report import provenance
if sys.argv[1] == "fast":
    assert apply_fast_compile()
import jax, jax.numpy as jnp
jax.config.update("jax_enable_x64", True)
x = jnp.linspace(0.0, 3.0, 64).reshape(8, 8)
f = lambda x: jnp.sin(x) @ jnp.cos(x).T + jnp.linalg.inv(x @ x.T + 3.0 * jnp.eye(8))
with fast_compile(sys.argv[1] == "fast"):
    value = float(jax.jit(f)(x).sum())
    block = provenance(precision="float64")
after = provenance(precision="float64")["xla_most_optimizations_off"]
flags = ",".join(block["xla_flags"].split()) or "-"
print(repr(value), block["xla_most_optimizations_off"], after, flags)
"""


def test_fast_compile_gives_the_same_results_and_is_recorded():
    def run(mode):
        env = {**os.environ, "ACCEL_JAX_CACHE_DIR": "off", "XLA_FLAGS": "", OPT_OUT_ENV: "off"}
        out = subprocess.run(
            [sys.executable, "-c", _FAST_PROGRAM, mode],
            capture_output=True,
            text=True,
            env=env,
            timeout=120,
        )
        assert out.returncode == 0, out.stderr
        value, inside, after, flags = out.stdout.split()
        return float(value), inside, after, flags

    default = run("default")
    fast = run("fast")
    assert default[1:] == ("False", "False", "-")
    # Recorded in the provenance while on, and switched back off after the block.
    assert fast[1:] == ("True", "False", ",".join(FAST_COMPILE_FLAGS))
    assert fast[0] == pytest.approx(default[0], rel=1e-12)


_CLI_PROGRAM = """
import os, sys
from accel_jax.cli import main
try:
    main([sys.argv[1], "--help"])
except SystemExit:
    pass
print("FLAGS", os.environ.get("XLA_FLAGS", "-"))
"""


@pytest.mark.parametrize("command", ["diagnose", "report"])
def test_single_record_commands_compile_with_the_fast_flags(command):
    # `diagnose` / `identify` / `noise` are compile-bound: the CLI adds FAST_COMPILE_FLAGS
    # before the backend starts; `report` decides for itself (its --quick run adds them).
    environment = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", OPT_OUT_ENV)}
    out = subprocess.run(
        [sys.executable, "-c", _CLI_PROGRAM, command],
        capture_output=True,
        text=True,
        env={**environment, "ACCEL_JAX_CACHE_DIR": "off"},
        timeout=120,
    )
    flags = out.stdout.rsplit("FLAGS", 1)[1].split()
    assert ("--xla_cpu_use_fusion_emitters=false" in flags) == (command != "report"), flags


def test_thread_map_keeps_order_x64_and_the_first_error(monkeypatch):
    """`thread_map`: the results in the items' order, each worker under the caller's x64
    setting (thread-local in JAX), the same results on one CPU (no threads) as on several,
    and an exception raised in a worker raised to the caller."""
    import threading
    import time

    import jax
    import jax.numpy as jnp
    import numpy as np

    from accel_jax import _runtime

    @jax.jit
    def f(x):
        return jnp.cumsum(x * x) / 3.0

    def work(i):
        time.sleep(0.01 * (5 - i))  # later items finish first
        return threading.get_ident(), np.asarray(f(jnp.arange(i + 3.0)))

    found = {}
    for cpus in (1, 4):
        monkeypatch.setattr(_runtime, "usable_cpus", lambda cpus=cpus: list(range(cpus)))
        with jax.enable_x64(True):
            found[cpus] = _runtime.thread_map(work, range(5))
    assert len({ident for ident, _ in found[1]}) == 1  # one CPU: all in the caller
    assert len({ident for ident, _ in found[4]}) > 1
    for (_, one), (_, many) in zip(found[1], found[4], strict=True):
        assert one.dtype == many.dtype == np.float64
        assert np.array_equal(one, many)
    assert [r.size for _, r in found[4]] == [3, 4, 5, 6, 7]
    with jax.enable_x64(False):
        assert _runtime.thread_map(lambda i: f(jnp.arange(3.0)).dtype, range(2)) == [
            jnp.float32
        ] * 2

    def fails(i):
        if i == 2:
            raise ValueError("item 2")
        return i

    with pytest.raises(ValueError, match="item 2"):
        _runtime.thread_map(fails, range(4))


def test_thread_map_drops_the_calls_not_started_after_an_error(monkeypatch):
    """After the first error (or an interrupt) the caller gets it at once: the calls not
    yet started are dropped, not run first (a `with` block ran every one of them), and the
    threads still running a call are seen by `background_running` until it ends."""
    import threading

    from accel_jax import _runtime

    monkeypatch.setattr(_runtime, "usable_cpus", lambda: [0, 1])
    started, release = [], threading.Event()

    def work(i):
        started.append(i)
        if i == 0:
            raise ValueError("item 0")
        release.wait(30)  # the running call: ends when the test releases it
        return i

    with pytest.raises(ValueError, match="item 0"):
        _runtime.thread_map(work, range(20))
    assert _runtime.background_running()  # item 1 (and at most one more) still running
    release.set()
    for thread in threading.enumerate():
        if thread.name.startswith(_runtime.BACKGROUND_THREADS):
            thread.join(30)
    assert not _runtime.background_running()
    assert len(started) <= 3, started  # not the 20: the rest were dropped


_EXIT_PROGRAM = """
import sys, time
from accel_jax import _runtime, cli
_runtime.in_background(lambda: time.sleep(120))  # e.g. a later stage compiled ahead
sys.argv = ["accel-jax", *sys.argv[1:]]
cli.run()
"""


@pytest.mark.parametrize(
    ("args", "status"), [(["diagnose", "no_such_record.csv"], 1), (["--version"], 0)]
)
def test_the_command_exits_with_its_status_without_waiting_for_background_work(
    tmp_path, args, status
):
    """`accel-jax` (`cli.run`) ending while a call it started in the background still runs
    (an interrupted or failed diagnosis) exits at once with the command's status, not after
    that call (the 120 s here; a compilation ahead took up to 11 s after a Ctrl-C)."""
    out = subprocess.run(
        [sys.executable, "-c", _EXIT_PROGRAM, *args],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env={**os.environ, "ACCEL_JAX_CACHE_DIR": "off"},
        timeout=60,  # waiting for the background call would exceed it
    )
    assert out.returncode == status, out.stderr
    if status:
        assert "no_such_record.csv" in out.stderr and "Traceback" not in out.stderr
    else:
        assert "version" in out.stdout


def test_report_cpus_are_the_reports_before_its_pinning(monkeypatch):
    """`report_cpus`: the CPUs the report set for its studies (`ACCEL_JAX_REPORT_CPUS`,
    comma-separated), else the process's own; a malformed value is ignored. A report worker
    (`_init_worker`) sets it to the CPUs it had before pinning itself to its share."""
    from accel_jax import _runtime
    from accel_jax.report import _run

    monkeypatch.setattr(_runtime, "usable_cpus", lambda: [3])
    monkeypatch.delenv(_runtime.REPORT_CPUS_ENV, raising=False)
    assert _runtime.report_cpus() == [3]
    for text, cpus in (("0,1", [0, 1]), (" 2, 0,2 ", [0, 2]), ("x", [3]), ("-1", [3]), ("", [3])):
        monkeypatch.setenv(_runtime.REPORT_CPUS_ENV, text)
        assert _runtime.report_cpus() == cpus, text
    monkeypatch.delenv(_runtime.REPORT_CPUS_ENV)
    pinned = []
    monkeypatch.setattr(_run, "usable_cpus", lambda: [0, 1])
    monkeypatch.setattr(_run.os, "sched_setaffinity", lambda pid, cpus: pinned.append(cpus))
    monkeypatch.setattr(_run, "apply_device", lambda **options: None)
    monkeypatch.setattr(_run.jax.config, "update", lambda *args: None)
    monkeypatch.setattr("tqdm.auto.tqdm.set_lock", lambda lock: None)
    _run._init_worker(True, None, 2, 2)
    assert pinned == [[1]] and os.environ[_runtime.REPORT_CPUS_ENV] == "0,1"


def test_spare_cpu_and_background_calls(monkeypatch):
    """`spare_cpu`: two CPUs or more and fewer runnable threads than CPUs (the caller's
    counts), or without /proc/loadavg a load below their count minus a half;
    `in_background`: the calls in turn on one other thread,
    under the caller's x64 setting, their futures in order."""
    import threading

    import jax
    import jax.numpy as jnp

    from accel_jax import _runtime

    assert isinstance(_runtime._running_threads(), int)  # this machine: Linux
    for cpus, running, spare in ((1, 1, False), (2, 1, True), (2, 2, False), (4, 3, True)):
        monkeypatch.setattr(_runtime, "usable_cpus", lambda cpus=cpus: list(range(cpus)))
        monkeypatch.setattr(_runtime, "_running_threads", lambda running=running: running)
        assert _runtime.spare_cpu() is spare, (cpus, running)
    # Without /proc/loadavg, the one-minute load average.
    monkeypatch.setattr(_runtime, "_running_threads", lambda: None)
    for cpus, load, spare in ((1, 0.0, False), (2, 0.9, True), (2, 1.6, False), (4, 3.0, True)):
        monkeypatch.setattr(_runtime, "usable_cpus", lambda cpus=cpus: list(range(cpus)))
        monkeypatch.setattr(_runtime.os, "getloadavg", lambda load=load: (load, load, load))
        assert _runtime.spare_cpu() is spare, (cpus, load)
    order = []

    def call(i):
        def run():
            order.append(i)
            return threading.get_ident(), jnp.arange(2.0).dtype

        return run

    with jax.enable_x64(True):
        futures = _runtime.in_background(*(call(i) for i in range(3)))
    results = [f.result(timeout=60) for f in futures]
    assert order == [0, 1, 2]
    assert len({ident for ident, _ in results}) == 1
    assert results[0][0] != threading.get_ident()
    assert all(dtype == jnp.float64 for _, dtype in results)


def test_beside_runs_on_another_thread_or_here(monkeypatch):
    """`beside`: on two CPUs or more the calls run in turn on one other thread (their
    futures in order, an error kept in its future); on one CPU they run here, in turn, at
    once, and an error is raised here, as the call itself would raise it."""
    import threading

    from accel_jax import _runtime

    def call(i, order):
        def run():
            order.append(i)
            if i == 1:
                raise ValueError("call 1")
            return threading.get_ident()

        return run

    monkeypatch.setattr(_runtime, "usable_cpus", lambda: [0, 1])
    order = []
    futures = _runtime.beside(*(call(i, order) for i in (0, 1, 2)))
    assert futures[0].result(timeout=60) != threading.get_ident()
    with pytest.raises(ValueError, match="call 1"):
        futures[1].result(timeout=60)
    assert futures[2].result(timeout=60) == futures[0].result()
    assert order == [0, 1, 2]

    monkeypatch.setattr(_runtime, "usable_cpus", lambda: [0])
    order = []
    futures = _runtime.beside(call(0, order), call(2, order))
    assert order == [0, 2]  # run before `beside` returned
    assert [f.result(timeout=0) for f in futures] == [threading.get_ident()] * 2
    order = []
    with pytest.raises(ValueError, match="call 1"):
        _runtime.beside(call(0, order), call(1, order), call(2, order))
    assert order == [0, 1]  # the call after the failed one is not run
