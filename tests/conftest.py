"""Test configuration: the tests run in float64 (the effects measured — δK_a at 0.1 %,
machine-precision agreement between simulators — need it). This is the test suite's
choice; the library itself never changes JAX's global settings."""

from accel_jax._xla import apply_cpu_workarounds

apply_cpu_workarounds()  # XLA:CPU scheduler deadlock on batched nested loops (see _xla.py)

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
