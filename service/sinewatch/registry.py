"""Named plug-ins of one kind (estimators, scenarios), each family one module of a package.

A :class:`Registry` is filled by the modules of its package, which register their entries
when imported; the registry imports every public module (not ``base``, not ``_private``)
once, the first time it is asked for a name. Adding an estimator or a family of scenarios
is therefore adding one module.
"""

from __future__ import annotations

import importlib
import pkgutil
from collections.abc import Iterable
from typing import Generic, TypeVar

T = TypeVar("T")


class Registry(Generic[T]):
    def __init__(self, kind: str, package: str, path: Iterable[str], missing: type[Exception]) -> None:
        self.kind = kind
        self._package = package
        self._path = path
        self._missing = missing
        self._entries: dict[str, T] = {}
        self._loaded = False

    def add(self, name: str, entry: T) -> T:
        if name in self._entries and self._entries[name] is not entry:
            raise ValueError(f"{self.kind} name {name!r} registered twice")
        self._entries[name] = entry
        return entry

    def get(self, name: str) -> T:
        self._load_all()
        try:
            return self._entries[name]
        except KeyError:
            raise self._missing(f"{self.kind}: expected one of {sorted(self._entries)}, got {name!r}") from None

    def names(self) -> list[str]:
        self._load_all()
        return sorted(self._entries)

    def _load_all(self) -> None:
        if self._loaded:
            return
        for mod in sorted(pkgutil.iter_modules(list(self._path)), key=lambda m: m.name):
            if mod.name != "base" and not mod.name.startswith("_"):
                importlib.import_module(f"{self._package}.{mod.name}")
        self._loaded = True


__all__ = ["Registry"]
