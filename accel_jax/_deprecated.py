"""Names that moved, kept at their old place for one release with a warning.

A module whose names moved ends with

    __getattr__ = moved_names(__name__, {"old_name": "accel_jax.new.module", ...})

Reading `old_module.old_name` then warns (`DeprecationWarning`, naming the new place) and
returns the object from its new module; `CHANGELOG.md` lists every move.
"""

from __future__ import annotations

import importlib
import warnings
from collections.abc import Callable, Mapping


def moved_names(module: str, moves: Mapping[str, str]) -> Callable[[str], object]:
    """A module-level `__getattr__` for `module` that forwards each name of `moves` (old name
    → the module that now holds it, under the same name) with a `DeprecationWarning`."""

    def __getattr__(name: str) -> object:
        target = moves.get(name)
        if target is None:
            raise AttributeError(f"module {module!r} has no attribute {name!r}")
        warnings.warn(
            f"{module}.{name} has moved to {target}.{name}; the old name will be removed in "
            "the next release (see CHANGELOG.md)",
            DeprecationWarning,
            stacklevel=2,
        )
        return getattr(importlib.import_module(target), name)

    return __getattr__
