"""Right on every machine: XLA options that cannot abort a process, and work placed by
`--device` (accel_jax/_runtime.py, accel_jax/_placement.py).

XLA aborts the whole process on an option its build does not know. The pinned jaxlib knows
every option the package sets, so a jaxlib that rejects one is simulated: with
tests/xla_rejects on PYTHONPATH the package carries one more option that no XLA knows (see
its sitecustomize.py; on the code before the probe, `identify` died at XLA's start with
"Unknown flag in XLA_FLAGS"). No GPU is here: the placement decisions are tested as the
pure function they are, and the CPU paths end to end."""

import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

import accel_jax as aj
from accel_jax import _cache, _runtime
from accel_jax._placement import DeviceError, plan_placement
from accel_jax._runtime import (
    CPU_SCHEDULER_FLAG,
    FAST_COMPILE_FLAGS,
    accepted_xla_flags,
)

REJECTS = Path(__file__).resolve().parent / "xla_rejects"
UNKNOWN = "--xla_accel_jax_simulated_unknown_option=false"


@pytest.fixture
def fresh_decisions(monkeypatch, tmp_path):
    """No decision remembered in this process, the cache file under tmp_path, and the
    skipped-option record restored afterwards."""
    monkeypatch.setattr(_runtime, "_decided", {})
    monkeypatch.setenv(_runtime._SKIPPED_ENV, "{}")
    monkeypatch.delenv(_cache.CACHE_ENV, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    return tmp_path / "accel_jax" / "xla_options.json"


def test_an_option_xla_rejects_is_skipped_recorded_and_cached(fresh_decisions, monkeypatch):
    cache = fresh_decisions
    fast = FAST_COMPILE_FLAGS[0]
    # The real probe (a subprocess starting XLA): the unknown option is refused, the known
    # one accepted, in the caller's order.
    monkeypatch.setattr(_runtime, "XLA_OPTIONS_SEEN_ACCEPTED", {})
    assert accepted_xla_flags([UNKNOWN, fast]) == [fast]
    skipped = _runtime.skipped_xla_flags()
    assert list(skipped) == [UNKNOWN] and skipped[UNKNOWN].startswith("not accepted by")
    version = _runtime.jaxlib_version()
    assert json.loads(cache.read_text())[version] == {
        _runtime.xla_option_name(UNKNOWN): False,
        _runtime.xla_option_name(fast): True,
    }

    # A second process (no in-memory decision) reads the cache: no probe.
    def no_probe(flags):
        raise AssertionError(f"probed {flags}")

    monkeypatch.setattr(_runtime, "_decided", {})
    monkeypatch.setattr(_runtime, "_probe_xla_flags", no_probe)
    assert accepted_xla_flags([fast, UNKNOWN]) == [fast]


def test_the_pinned_jaxlib_needs_no_probe(fresh_decisions, monkeypatch):
    version = _runtime.jaxlib_version()
    if version not in _runtime.XLA_OPTIONS_SEEN_ACCEPTED:
        pytest.skip(f"jaxlib {version} is not in the table (it is probed instead)")

    def no_probe(flags):
        raise AssertionError(f"probed {flags}")

    monkeypatch.setattr(_runtime, "_probe_xla_flags", no_probe)
    flags = [CPU_SCHEDULER_FLAG, *FAST_COMPILE_FLAGS]
    assert accepted_xla_flags(flags) == flags
    assert not fresh_decisions.exists()  # nothing to remember


def test_an_option_that_cannot_be_checked_is_skipped_and_not_cached(fresh_decisions, monkeypatch):
    monkeypatch.setattr(_runtime, "_probe_xla_flags", lambda flags: None)  # e.g. timed out
    assert accepted_xla_flags([UNKNOWN]) == []
    assert "could not be checked" in _runtime.skipped_xla_flags()[UNKNOWN]
    assert not fresh_decisions.exists()


def test_caches_off_decide_in_each_process(fresh_decisions, monkeypatch):
    monkeypatch.setenv(_cache.CACHE_ENV, "off")
    monkeypatch.setattr(_runtime, "XLA_OPTIONS_SEEN_ACCEPTED", {})
    calls = []
    monkeypatch.setattr(_runtime, "_probe_xla_flags", lambda flags: calls.append(flags) or False)
    assert accepted_xla_flags([UNKNOWN]) == [] and calls == [[UNKNOWN]]
    assert accepted_xla_flags([UNKNOWN]) == [] and len(calls) == 1  # remembered in-process
    assert not fresh_decisions.exists()


def test_several_unknown_options_are_probed_one_by_one_when_together_they_fail(
    fresh_decisions, monkeypatch
):
    monkeypatch.setattr(_runtime, "XLA_OPTIONS_SEEN_ACCEPTED", {})
    good, bad = "--xla_good_one=1", "--xla_bad_one=1"
    calls = []

    def probe(flags):
        calls.append(list(flags))
        return bad not in flags

    monkeypatch.setattr(_runtime, "_probe_xla_flags", probe)
    assert accepted_xla_flags([good, bad]) == [good]
    assert calls == [[good, bad], [good], [bad]]


_SCHEDULER_REJECTED = f"""
import importlib.util, os, sys
spec = importlib.util.spec_from_file_location("accel_jax._runtime", {str(Path(_runtime.__file__))!r})
runtime = importlib.util.module_from_spec(spec)
spec.loader.exec_module(runtime)
runtime.CPU_SCHEDULER_FLAG = {UNKNOWN!r}  # the deadlock workaround's option, unknown here
sys.modules["accel_jax._runtime"] = runtime
import accel_jax, jax
print(accel_jax._XLA_WORKAROUND, float(jax.jit(lambda x: x + 1)(1.0)))
print(os.environ.get("XLA_FLAGS", "-") or "-")
print(sorted(runtime.skipped_xla_flags()))
"""


def test_import_skips_the_deadlock_option_where_xla_rejects_it(tmp_path):
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", _runtime.OPT_OUT_ENV)}
    env.update(XDG_CACHE_HOME=str(tmp_path), ACCEL_JAX_CACHE_DIR="off")
    out = subprocess.run(
        [sys.executable, "-c", _SCHEDULER_REJECTED],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    assert lines[0] == "not_accepted 2.0"
    assert lines[1] == "-"  # nothing added to XLA_FLAGS
    assert lines[2] == repr([UNKNOWN])


# ---------------------------------------------------------------------------------------
# The commands on an XLA that rejects one of the package's options.


@pytest.fixture(scope="module")
def records(tmp_path_factory):
    """A small step record (the reference device, 1 MHz, 10 ms after a 1 V step) and a
    white static record (2,000 samples at 100 Hz)."""
    folder = tmp_path_factory.mktemp("records")
    params = aj.ServoParams.reference()
    ts, u = aj.step_response(
        params, duration=10e-3, sample_rate=1e6, test_voltage=1.0, key=jax.random.key(3)
    )
    ts, u = np.asarray(ts), np.asarray(u)
    pre = 200
    level = float(aj.step_response(params, duration=10e-3, sample_rate=1e6)[1][0])
    rest = level + 1e-5 * np.random.default_rng(0).standard_normal(pre)
    dt = ts[1] - ts[0]
    step = aj.StepData(
        np.concatenate([np.arange(pre) * dt, ts + pre * dt]),
        np.concatenate([np.zeros(pre), np.ones(len(ts))]),
        np.concatenate([rest, u]),
    )
    aj.write_csv(folder / "step.csv", step)
    x = 1e-3 * np.random.default_rng(1).standard_normal(2000)
    aj.write_csv(folder / "noise.csv", aj.NoiseData(np.arange(2000) * 0.01, x))
    return folder


def _cli(args, cwd, *, rejects: bool, **env):
    environment = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}  # a user's shell
    environment.pop(_runtime._SKIPPED_ENV, None)
    environment.update(ACCEL_JAX_CACHE_DIR="off", XDG_CACHE_HOME=str(cwd), **env)
    if rejects:
        environment["PYTHONPATH"] = os.pathsep.join(
            [str(REJECTS), *filter(None, [os.environ.get("PYTHONPATH")])]
        )
    return subprocess.run(
        [sys.executable, "-c", "from accel_jax.cli import main; main()", *args],
        capture_output=True,
        text=True,
        env=environment,
        cwd=cwd,
        timeout=600,
    )


def _without_provenance(doc: dict) -> dict:
    return {k: v for k, v in doc.items() if k != "provenance"}


@pytest.mark.slow
def test_identify_diagnose_and_noise_complete_where_xla_rejects_an_option(records, tmp_path):
    """Each command runs to the end (exit 0), the unknown option is skipped and named in
    the JSON's provenance, the options XLA accepts are still applied, and the results equal
    those of the same command on the plain stack."""
    commands = {
        "identify": ["identify", str(records / "step.csv")],
        "diagnose": ["diagnose", str(records / "noise.csv")],
        "noise": ["noise", str(records / "noise.csv")],
    }
    for name, args in commands.items():
        out = _cli([*args, "--json", "rejects.json"], tmp_path, rejects=True)
        assert out.returncode == 0, (name, out.stderr[-3000:])
        assert "Unknown flag" not in out.stderr and "Traceback" not in out.stderr, name
        doc = json.loads((tmp_path / "rejects.json").read_text())
        provenance = doc["provenance"]
        assert list(provenance["xla_options_skipped"]) == [UNKNOWN], name
        assert UNKNOWN not in provenance["xla_flags"]
        assert FAST_COMPILE_FLAGS[0] in provenance["xla_flags"].split()
        assert CPU_SCHEDULER_FLAG in provenance["xla_flags"].split()
        if name == "identify":  # the plain stack: the same numbers
            plain = _cli([*args, "--json", "plain.json"], tmp_path, rejects=False)
            assert plain.returncode == 0, plain.stderr[-3000:]
            reference = json.loads((tmp_path / "plain.json").read_text())
            assert reference["provenance"]["xla_options_skipped"] == {}
            assert _without_provenance(doc) == _without_provenance(reference)
        (tmp_path / "rejects.json").unlink()


# ---------------------------------------------------------------------------------------
# Where work runs.


def test_placement_decisions():
    """auto: latency-bound commands never start an accelerator; the report's studies run
    their plain jit calls on the CPU and their sweeps on the accelerator; gpu and cpu put
    everything in one place; gpu without one is an error."""
    cpu_only = {"unsharded": "cpu", "sweeps": "cpu", "cpu_only": True}
    for latency_bound in (True, False):
        for choice in ("auto", "cpu"):  # no accelerator: the CPU whatever the choice
            assert plan_placement(choice, None, latency_bound=latency_bound) == {
                "device": choice,
                **cpu_only,
            }
        with pytest.raises(DeviceError, match="no GPU"):
            plan_placement("gpu", None, latency_bound=latency_bound)
    # A GPU host.
    assert plan_placement("auto", "gpu", latency_bound=True) == {"device": "auto", **cpu_only}
    assert plan_placement("auto", "gpu", latency_bound=False) == {
        "device": "auto",
        "unsharded": "cpu",
        "sweeps": "accelerator",
        "cpu_only": False,
    }
    assert plan_placement("gpu", "gpu", latency_bound=True) == {
        "device": "gpu",
        "unsharded": "accelerator",
        "sweeps": "accelerator",
        "cpu_only": False,
    }
    assert plan_placement("cpu", "gpu", latency_bound=False) == {"device": "cpu", **cpu_only}
    with pytest.raises(DeviceError, match="one of auto, cpu, gpu"):
        plan_placement("tpu", "tpu", latency_bound=False)


_PLACE = """
import json, os, sys
from accel_jax._placement import apply_device, placement_record
placement = apply_device(sys.argv[1], latency_bound=sys.argv[2] == "latency", shared=True)
import jax
print(json.dumps({"placement": placement, "record": placement_record(),
                  "platforms": os.environ.get("JAX_PLATFORMS", ""),
                  "option": jax.config.jax_platforms or "",
                  "prealloc": os.environ.get("XLA_PYTHON_CLIENT_PREALLOCATE", ""),
                  "env": os.environ.get("ACCEL_JAX_DEVICE")}))
"""


@pytest.mark.parametrize("choice", ["auto", "cpu"])
@pytest.mark.parametrize("kind", ["latency", "sweeps"])
def test_apply_device_on_a_cpu_host(choice, kind):
    """On this (CPU) machine: the choice is kept for child processes, latency-bound work
    never lets JAX look for an accelerator, and the record names where the work ran."""
    env = {k: v for k, v in os.environ.items() if k not in ("JAX_PLATFORMS", "ACCEL_JAX_DEVICE")}
    env.pop("XLA_PYTHON_CLIENT_PREALLOCATE", None)
    out = subprocess.run(
        [sys.executable, "-c", _PLACE, choice, kind],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr
    doc = json.loads(out.stdout.splitlines()[-1])
    assert doc["env"] == choice
    assert doc["placement"]["unsharded"] == doc["placement"]["sweeps"] == "cpu"
    assert doc["record"]["device"] == choice
    assert doc["record"]["unsharded_work_on"].startswith("cpu")
    assert doc["record"]["sweeps_on"].startswith("cpu")
    assert doc["platforms"] == ("cpu" if kind == "latency" or choice == "cpu" else "")
    # JAX (imported with the package) read JAX_PLATFORMS before apply_device set it: the
    # option itself must say cpu, or on a GPU host the GPU starts (seen on an H200 host).
    assert doc["option"] == doc["platforms"]
    # Several processes may share an accelerator: none preallocates (unless --device cpu).
    assert doc["prealloc"] == ("" if choice == "cpu" else "false")


def test_device_gpu_without_one_is_one_line_and_exit_1(records, tmp_path):
    from click.testing import CliRunner

    from accel_jax.cli import main

    result = CliRunner().invoke(main, ["identify", str(records / "step.csv"), "--device", "gpu"])
    assert result.exit_code == 1
    assert "--device gpu: JAX sees no GPU" in result.output
    assert "Traceback" not in result.output
    bad = CliRunner().invoke(main, ["noise", str(records / "noise.csv"), "--device", "npu"])
    assert bad.exit_code == 2 and "--device" in bad.output


def test_the_device_is_recorded_in_a_commands_json(records, tmp_path):
    out = _cli(
        ["identify", str(records / "step.csv"), "--json", "id.json", "--device", "cpu"],
        tmp_path,
        rejects=False,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    placement = json.loads((tmp_path / "id.json").read_text())["provenance"]["placement"]
    assert placement == {"device": "cpu", "unsharded_work_on": "cpu:0", "sweeps_on": "cpu ×1"}
