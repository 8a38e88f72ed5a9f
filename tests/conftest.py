"""Test configuration: the tests run in float64 (the effects measured — δK_a at 0.1 %,
machine-precision agreement between simulators — need it). This is the test suite's
choice; the library itself never changes JAX's global settings."""

import jax

jax.config.update("jax_enable_x64", True)
