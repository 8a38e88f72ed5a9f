"""Shared test utilities."""

import jax
import jax.numpy as jnp
import numpy as np

import accel_jax


def tree_allclose(x, y, *, rtol=1e-5, atol=1e-8):
    """True when two pytrees have the same structure and all leaves are close."""
    same_structure = jax.tree_util.tree_structure(x) == jax.tree_util.tree_structure(y)
    if not same_structure:
        return False
    leaves = zip(jax.tree_util.tree_leaves(x), jax.tree_util.tree_leaves(y), strict=True)
    return all(np.allclose(np.asarray(a), np.asarray(b), rtol=rtol, atol=atol) for a, b in leaves)


def central_difference(f, x, rel_step=1e-6):
    """Central finite difference of a scalar function of a scalar, in float64."""
    x = jnp.asarray(x, dtype=jnp.float64)
    h = rel_step * jnp.maximum(jnp.abs(x), 1e-300)
    return (f(x + h) - f(x - h)) / (2 * h)


def study_result(report_dir, study: str):
    """(folder, parsed result.json) of one study of the shared quick report (the
    `quick_report` fixture of conftest.py)."""
    import json
    from pathlib import Path

    folder = Path(report_dir).parent / study
    return folder, json.loads((folder / "result.json").read_text())


def drawn_devices(size, seed):
    """A batch of `ServoParams`: devices with J, μ, c, k_dm, T_dm, T_f drawn ±3 % (1σ) around the reference."""
    reference = accel_jax.ServoParams.reference()
    rng = np.random.default_rng(seed)
    fields = {name: np.full(size, value) for name, value in accel_jax.REFERENCE_VALUES.items()}
    for name in (
        "moment_of_inertia",
        "damping",
        "stiffness",
        "torquer_gain",
        "torquer_time_constant",
        "filter_time_constant",
    ):
        fields[name] = fields[name] * (1 + 0.03 * rng.standard_normal(size))
    del reference
    return accel_jax.ServoParams(**{k: jnp.asarray(v) for k, v in fields.items()})


def run_on_simulated_cpu_devices(code: str, count: int):
    """Run `code` in a fresh interpreter that sees `count` CPU devices (the device count is
    fixed when JAX starts); returns the completed process (stdout, stderr as text)."""
    import os
    import subprocess
    import sys

    env = dict(
        os.environ,
        XLA_FLAGS=f"--xla_force_host_platform_device_count={count}",
        JAX_PLATFORMS="cpu",
    )
    return subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300
    )
