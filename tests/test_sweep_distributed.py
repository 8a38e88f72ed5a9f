"""Sweeps and the Monte Carlo kernel under JAX's multi-process runtime (`jax.distributed`):
two local CPU processes with two simulated devices each, the batch split over all four,
every process holding the whole result, equal to one process's."""

import os
import socket
import subprocess
import sys
import textwrap

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import accel_jax as aj
from accel_jax._sweep import gather_processes

pytestmark = pytest.mark.slow

N_SWEEP = 13  # not a multiple of the 4 global devices: exercises the padding
N_MC = 4  # a multiple: the kernel's output stays split over the processes (no padding)

_WORKER = textwrap.dedent(
    """
    import sys
    import jax
    jax.config.update("jax_enable_x64", True)
    # CPU hosts exchange the shards through gloo (GPUs through NCCL, JAX's default there).
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    coordinator, pid, out = sys.argv[1], int(sys.argv[2]), sys.argv[3]
    jax.distributed.initialize(coordinator, num_processes=2, process_id=pid)
    import equinox as eqx, jax.numpy as jnp, numpy as np
    import accel_jax as aj
    assert jax.process_count() == 2 and jax.device_count() == 4, jax.devices()
    assert len(jax.local_devices()) == 2
    mus = jnp.linspace(1e-5, 2e-4, {n_sweep})
    batch = eqx.filter_vmap(lambda mu: aj.ServoParams.reference(damping=mu))(mus)
    f = lambda p: aj.scale_factor(p) * aj.damping_ratio(p)
    whole = aj.sweep(f, batch)
    chunked = aj.sweep(f, batch, chunk_size=5)
    # 12 of the 13: no padding, so the output stays split over the processes unless gathered.
    even = aj.sweep(f, jax.tree_util.tree_map(lambda x: x[:12], batch))
    p = aj.ServoParams.reference()
    devices = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, ({n_mc},) + jnp.shape(x)), p)
    keys = jax.random.split(jax.random.key(7), {n_mc})
    ts = jnp.linspace(0.0, 10e-3, 1001)
    est = aj.monte_carlo_oscillatory(
        devices, keys, ts, pickoff_amplifier_gain=jnp.full({n_mc}, 2.125e6),
        shape_factor=jnp.full({n_mc}, float(aj.shape_factor(p))), chunk_size=1,
    )
    # Whole on this process: readable as NumPy (a global array's remote shards are not).
    ok = est.result == aj.IdentificationResult.successful
    np.savez(out, whole=np.asarray(whole), chunked=np.asarray(chunked), even=np.asarray(even),
             k=np.asarray(est.scale_factor), ok=np.asarray(ok))
    jax.distributed.shutdown()
    print("OK", pid)
    """
).format(n_sweep=N_SWEEP, n_mc=N_MC)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _one_process():
    """The same computations in this process (one device)."""
    mus = jnp.linspace(1e-5, 2e-4, N_SWEEP)
    batch = eqx.filter_vmap(lambda mu: aj.ServoParams.reference(damping=mu))(mus)
    whole = aj.sweep(lambda p: aj.scale_factor(p) * aj.damping_ratio(p), batch)
    p = aj.ServoParams.reference()
    devices = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (N_MC,) + jnp.shape(x)), p)
    est = aj.monte_carlo_oscillatory(
        devices,
        jax.random.split(jax.random.key(7), N_MC),
        jnp.linspace(0.0, 10e-3, 1001),
        pickoff_amplifier_gain=jnp.full(N_MC, 2.125e6),
        shape_factor=jnp.full(N_MC, float(aj.shape_factor(p))),
        chunk_size=1,
    )
    ok = est.result == aj.IdentificationResult.successful
    return np.asarray(whole), np.asarray(est.scale_factor), np.asarray(ok)


def test_two_processes_give_every_process_the_one_process_result(tmp_path):
    script = tmp_path / "worker.py"
    script.write_text(_WORKER)
    coordinator = f"127.0.0.1:{_free_port()}"
    env = dict(os.environ)
    env["XLA_FLAGS"] = (
        env.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2"
    ).strip()
    env["JAX_PLATFORMS"] = "cpu"
    procs = [
        subprocess.Popen(
            [sys.executable, str(script), coordinator, str(pid), str(tmp_path / f"out{pid}.npz")],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for pid in (0, 1)
    ]
    outputs = []
    try:
        for proc in procs:
            out, err = proc.communicate(timeout=400)
            outputs.append((proc.returncode, out, err))
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
    for pid, (code, out, err) in enumerate(outputs):
        assert code == 0 and out.strip().endswith(f"OK {pid}"), err[-3000:]
    whole, k, ok = _one_process()
    assert ok.all()
    got = [np.load(tmp_path / f"out{pid}.npz") for pid in (0, 1)]
    for g in got:
        # The sweep: the same per-element program, so the same numbers.
        np.testing.assert_array_equal(g["whole"], whole)
        np.testing.assert_array_equal(g["chunked"], whole)
        np.testing.assert_array_equal(g["even"], whole[:12])
        # The kernel: each device compiles its share on its own (it fuses differently).
        np.testing.assert_array_equal(g["ok"], ok)
        np.testing.assert_allclose(g["k"], k, rtol=1e-12)
    np.testing.assert_array_equal(got[0]["k"], got[1]["k"])


def test_gather_is_a_no_op_on_one_process():
    tree = {"a": jnp.arange(3.0), "b": "static"}
    assert gather_processes(tree) is tree
