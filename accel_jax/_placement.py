"""Where a process's work runs (`--device auto|cpu|gpu`): `plan_placement` decides,
`apply_device` applies it before JAX starts its backend, `placement_record` says for the
provenance where plain `jit` calls and the sweeps ran. A process setting, as `_runtime`'s:
entry points call it, the library does not.
"""

from __future__ import annotations

import os

from ._runtime import _backend_started

DEVICE_CHOICES = ("auto", "cpu", "gpu")
DEVICE_ENV = "ACCEL_JAX_DEVICE"
"""The `--device` choice, inherited by the processes an entry point starts."""

_PLACEMENT_ENV = "_ACCEL_JAX_PLACEMENT"  # this process's placement (JSON), for provenance


class DeviceError(ValueError):
    """The device asked for is not there (e.g. `--device gpu` on a machine without one)."""


def plan_placement(choice: str, accelerator: str | None, *, latency_bound: bool) -> dict:
    """Where one entry point's work runs; a pure function of the choice and the machine.

    `choice`: `auto`, `cpu` or `gpu`; `accelerator`: the platform JAX's default backend
    has besides the CPU (`"gpu"`, `"tpu"`) or None; `latency_bound`: the entry point's work
    is latency-bound throughout (a single-record `diagnose`, `identify` or `noise`: small
    programs, adaptive ODE fits with small while loops, each run once).

    Returns `{"device": choice, "unsharded": "cpu"|"accelerator", "sweeps":
    "cpu"|"accelerator", "cpu_only": bool}`: `unsharded` is where plain `jit` calls run
    (JAX's default device), `sweeps` where the throughput kernels (`sweep`,
    `monte_carlo_oscillatory`, which shard over `jax.devices()`) run, and `cpu_only` that
    the accelerator is not to be started at all (`JAX_PLATFORMS=cpu`). `auto` puts
    latency-bound work on the CPU and the sweeps on the accelerator; `gpu` puts everything
    on the accelerator (an error without one); `cpu` everything on the CPU."""
    if choice not in DEVICE_CHOICES:
        raise DeviceError(f"device must be one of {', '.join(DEVICE_CHOICES)}; got {choice!r}")
    if choice == "gpu" and accelerator is None:
        raise DeviceError(
            "--device gpu: JAX sees no GPU on this machine (only its CPU); install a "
            "CUDA-enabled jaxlib, or use --device auto or cpu."
        )
    if choice == "cpu" or accelerator is None or (choice == "auto" and latency_bound):
        return {"device": choice, "unsharded": "cpu", "sweeps": "cpu", "cpu_only": True}
    if choice == "gpu":
        return {"device": choice, "unsharded": "accelerator", "sweeps": "accelerator",
                "cpu_only": False}
    return {"device": choice, "unsharded": "cpu", "sweeps": "accelerator", "cpu_only": False}


def apply_device(choice: str | None = None, *, latency_bound: bool, shared: bool = False):
    """Place this process's work as `plan_placement` says, before JAX starts its backend.

    `choice` (default `$ACCEL_JAX_DEVICE`, else `auto`) is kept in the environment for the
    processes this one starts. Latency-bound work with `auto`, and `cpu`, set
    `JAX_PLATFORMS=cpu` (the accelerator is never started: a GPU's start-up alone takes
    seconds). Otherwise JAX's default backend is started here: with an accelerator and
    `auto`, JAX's default device becomes the host CPU (`jax_default_device`), so that
    plain `jit` calls run there while `sweep` and `monte_carlo_oscillatory`, which shard
    over `jax.devices()`, run on the accelerator. `shared`: several processes will use the
    accelerator at once (the report's studies side by side), so none may claim its memory
    up front (`XLA_PYTHON_CLIENT_PREALLOCATE=false` unless the user set it).

    Returns the placement, also recorded for `provenance`. Raises `DeviceError` for
    `gpu` without one, or for `cpu` once JAX's backend has already started on an
    accelerator (the choice can no longer be made)."""
    import json

    choice = (choice or os.environ.get(DEVICE_ENV) or "auto").strip().lower()
    if choice not in DEVICE_CHOICES:
        raise DeviceError(f"device must be one of {', '.join(DEVICE_CHOICES)}; got {choice!r}")
    platforms = os.environ.get("JAX_PLATFORMS", "").strip().lower()
    import jax

    if (choice == "cpu" or (choice == "auto" and latency_bound)) and not _backend_started():
        if platforms in ("", "cpu") or choice == "cpu":
            # JAX read JAX_PLATFORMS when it was imported (the package imports it), so the
            # variable alone reaches only the processes this one starts: set the option too.
            # (Without it, found on an H200 host, `--device cpu` met a started GPU.)
            os.environ["JAX_PLATFORMS"] = "cpu"
            jax.config.update("jax_platforms", "cpu")
    if shared and choice != "cpu":
        os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

    backend = jax.default_backend()
    accelerator = None if backend == "cpu" else backend
    if choice == "cpu" and accelerator is not None:
        raise DeviceError(
            "--device cpu: JAX had already started on the accelerator in this process; "
            "set JAX_PLATFORMS=cpu before starting Python."
        )
    placement = plan_placement(choice, accelerator, latency_bound=latency_bound)
    if accelerator is not None and placement["unsharded"] == "cpu":
        jax.config.update("jax_default_device", jax.devices("cpu")[0])
    placement["accelerator"] = accelerator
    os.environ[DEVICE_ENV] = choice  # only once placed: a refused choice is not inherited
    os.environ[_PLACEMENT_ENV] = json.dumps(placement, sort_keys=True)
    return placement


def placement_record() -> dict:
    """Where this process's work ran, for the provenance: the `--device` choice, where
    plain `jit` calls ran (JAX's default device) and where the sweeps ran (the devices
    they shard over); `{"device": "not set"}` where no entry point placed it."""
    import json

    import jax

    try:
        placement = json.loads(os.environ.get(_PLACEMENT_ENV, "") or "{}")
    except ValueError:
        placement = {}
    placed = jax.config.jax_default_device  # pyright: ignore[reportAttributeAccessIssue]  # dynamic
    default = placed or jax.devices()[0]
    devices = jax.devices()
    return {
        "device": placement.get("device", "not set"),
        "unsharded_work_on": str(default),
        "sweeps_on": f"{devices[0].platform} ×{len(devices)}",
    }
