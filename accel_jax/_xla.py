"""Process-level XLA settings for the entry points (CLI, studies run as scripts, tests).

XLA:CPU in jaxlib 0.10.2 deadlocks intermittently — every thread idle, the caller waiting
forever — when it runs a vmapped batch of nested `while` loops (a Levenberg–Marquardt fit
whose residual solves an adaptive diffrax ODE, as in the sensing-element study) with its
concurrency-optimised scheduler. Seen on the 2-core CPU machine: chunks of 8 to 32 such
fits hung after compiling in about half of the runs; with the scheduler off, 16 repeated
runs completed (32 fits in 9 s). The flag only changes how XLA orders independent
instructions, not what it computes.

The library never changes global settings on import; the entry points call
`apply_cpu_workarounds()` before JAX starts its backend. A user who runs the batched fits
from their own script should set the flag themselves (`XLA_FLAGS`).
"""

from __future__ import annotations

import os

CPU_SCHEDULER_FLAG = "--xla_cpu_enable_concurrency_optimized_scheduler=false"


def apply_cpu_workarounds() -> bool:
    """Add `CPU_SCHEDULER_FLAG` to `XLA_FLAGS` unless the user set that option already.

    Effective only before JAX initialises its CPU backend (the first computation); returns
    whether the environment was changed.
    """
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_cpu_enable_concurrency_optimized_scheduler" in flags:
        return False
    os.environ["XLA_FLAGS"] = f"{flags} {CPU_SCHEDULER_FLAG}".strip()
    return True
