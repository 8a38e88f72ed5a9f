"""Input checks shared by the simulators and the identification methods."""

from __future__ import annotations

import jax
import numpy as np

from ._params import _concrete


def require_float64(who: str, why: str) -> None:
    """Raise the one clear `ValueError` a float64-only computation gives when JAX's x64
    is off: "`who` needs float64: call … first (`why`: what float32 would lose)"."""
    if jax.dtypes.canonicalize_dtype(np.float64) != np.float64:
        raise ValueError(
            f"{who} needs float64: call jax.config.update('jax_enable_x64', True) first ({why})."
        )


def check_uniform_grid(ts, what: str, remedy: str = "Resample the record onto one.") -> None:
    """Raise a `ValueError` unless the sample times are strictly increasing and uniform.

    Under tracing (jit, vmap) the grid is not known and is assumed uniform. Deviations up to
    1e-6 of the mean spacing plus the rounding of the stored times themselves (8 ulp of the
    largest time: t = i·dt in float32 is not exactly uniform) are accepted.
    """
    concrete = _concrete(ts)
    if concrete is None or not np.all(np.isfinite(concrete)):
        return  # traced, or non-finite (reported by the caller's own finiteness check)
    step = (concrete[-1] - concrete[0]) / (len(concrete) - 1)
    if not step > 0:
        raise ValueError(
            f"{what}: ts must be strictly increasing; got ts[0] = {concrete[0]!r} s and "
            f"ts[-1] = {concrete[-1]!r} s."
        )
    floating = np.issubdtype(concrete.dtype, np.floating)
    eps = np.finfo(concrete.dtype).eps if floating else 0.0
    tolerance = 1e-6 * step + 8 * eps * np.max(np.abs(concrete))
    spacings = np.diff(concrete.astype(np.float64))
    deviation = np.abs(spacings - step)
    worst = int(np.argmax(deviation))
    if deviation[worst] > tolerance:
        raise ValueError(
            f"{what} needs a uniform time grid; got spacing ts[{worst + 1}] − ts[{worst}] = "
            f"{spacings[worst]!r} s, but the mean spacing is {step!r} s. {remedy}"
        )
