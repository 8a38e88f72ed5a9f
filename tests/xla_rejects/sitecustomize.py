"""Simulates a jaxlib whose XLA rejects one of accel_jax's options, for every Python process
started with this folder on PYTHONPATH (the study scripts of the quick report, the blind
diagnosis they start, the CLI commands of tests/test_xla_options.py).

A real XLA aborts the whole process on an option its build does not know (jaxlib 0.11
dropped `--xla_cpu_use_fusion_emitters`). The pinned jaxlib knows every option the package
sets, so this gives the package one more, which no XLA knows, before `import accel_jax`
runs: `accel_jax._runtime` is loaded here from its file with that option appended to
`FAST_COMPILE_FLAGS`, and the package then imports this module object. Nothing else
changes: without the probe, XLA would abort at its start (a fatal "Unknown flag in
XLA_FLAGS"); with it, the option is skipped and recorded in the provenance.
"""

import importlib.util
import sys
from pathlib import Path

UNKNOWN_OPTION = "--xla_accel_jax_simulated_unknown_option=false"

_path = Path(__file__).resolve().parents[2] / "accel_jax" / "_runtime.py"
_spec = importlib.util.spec_from_file_location("accel_jax._runtime", _path)
_runtime = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_runtime)
_runtime.FAST_COMPILE_FLAGS = (*_runtime.FAST_COMPILE_FLAGS, UNKNOWN_OPTION)
sys.modules["accel_jax._runtime"] = _runtime
