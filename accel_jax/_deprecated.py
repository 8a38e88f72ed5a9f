"""Names that moved, kept at their old place for one release with a warning.

A module whose names moved ends with

    __getattr__ = moved_names(__name__, {"old_name": "accel_jax.new.module", ...})

or, compactly, with each new module followed by the names (space-separated) it now holds:

    __getattr__ = moved_names(__name__, "accel_jax.new.module", "old_name other_name")

Reading `old_module.old_name` then warns (`DeprecationWarning`, naming the new place) and
returns the object from its new module; `CHANGELOG.md` lists every move, and `MOVED` holds
each old module's moves once it is imported.

A typed result that replaced a plain dict inherits `LegacyItems`: the dict's access still
works for one release, with a warning naming the attribute that holds the value now.
"""

from __future__ import annotations

import importlib
import warnings
from collections.abc import Callable, Iterable, Mapping


MOVED: dict[str, dict[str, str]] = {}
"""The moves of every old module imported so far: old module → {name: its new module}."""


def moved_names(
    module: str, *moves: Mapping[str, str] | str | Iterable[str]
) -> Callable[[str], object]:
    """A module-level `__getattr__` for `module` that forwards each moved name (to the
    module that now holds it, under the same name) with a `DeprecationWarning`.

    `moves` is one mapping {old name: new module}, or pairs: a new module, then the names
    that moved there (one space-separated string, or an iterable of names), as often as
    there are new modules.
    """
    table = _move_table(moves)
    MOVED[module] = table

    def __getattr__(name: str) -> object:
        target = table.get(name)
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


def _move_table(moves: tuple[Mapping[str, str] | str | Iterable[str], ...]) -> dict[str, str]:
    """`moved_names`'s moves as {old name: new module}."""
    if len(moves) == 1 and isinstance(moves[0], Mapping):
        return dict(moves[0])
    if not moves or len(moves) % 2:
        raise TypeError("moved_names takes one mapping or pairs of (new module, names)")
    table: dict[str, str] = {}
    for target, names in zip(moves[::2], moves[1::2], strict=True):
        if not isinstance(target, str) or isinstance(names, Mapping):
            raise TypeError(f"moved_names: expected a module name and its names, got {target!r}")
        for name in names.split() if isinstance(names, str) else names:
            if name in table:
                raise ValueError(f"moved_names: {name!r} is listed twice")
            table[name] = target
    return table


class LegacyItems:
    """Mixin: the string-keyed access of the plain dict that a typed result replaced, kept
    for one release with a warning.

    `result["fit"]`, `result.get("fit")`, `"fit" in result`, `result.keys()`,
    `result.items()` and iteration behave as on the old dict and return what it held (a
    plain dict where a typed part now stands: `to_dict`'s value), each with a
    `DeprecationWarning` that names the attribute to use instead. A subclass defines
    `_legacy()`, the old dict (a fresh one); each old key is the attribute that now holds
    its value unless `_legacy_advice` says otherwise.
    """

    def _legacy(self) -> dict:
        raise NotImplementedError

    def _legacy_advice(self, key: str) -> str:
        """What to use instead of the old dict's `key`."""
        advice = f"use result.{key}"
        to_dict = getattr(self, "to_dict", None)
        if to_dict is not None and key in to_dict():
            advice += f" (or result.to_dict()[{key!r}])"
        return advice

    def _legacy_warning(self, used: str, key: str | None = None) -> None:
        name = type(self).__name__
        if key is None:
            advice = f"use the attributes of {name} (or result.to_dict())"
        else:
            advice = self._legacy_advice(key)
        warnings.warn(
            f"{used} is deprecated: {name} is a typed result, no longer a dict; {advice} — "
            "the dict access will be removed in the next release (see CHANGELOG.md)",
            DeprecationWarning,
            stacklevel=3,
        )

    def __getitem__(self, key: str):
        old = self._legacy()
        if key not in old:
            raise KeyError(key)
        self._legacy_warning(f"result[{key!r}]", key)
        return old[key]

    def get(self, key: str, default=None):
        old = self._legacy()
        if key not in old:
            return default
        self._legacy_warning(f"result.get({key!r})", key)
        return old[key]

    def __contains__(self, key: object) -> bool:
        self._legacy_warning(f"{key!r} in result")
        return key in self._legacy()

    def keys(self):
        self._legacy_warning("result.keys()")
        return self._legacy().keys()

    def items(self):
        self._legacy_warning("result.items()")
        return self._legacy().items()

    def __iter__(self):
        self._legacy_warning("iterating over result")
        return iter(self._legacy())
