"""Lazy public names for a package's `__init__`: `from sfm import register` imports only the module defining it.

Packages keep their `__init__` light (importing `dynrecon.errors` must not pull pycolmap or the solver), yet offer
one flat public API; each maps its public names to (module, attribute) and takes its `__getattr__` and `__dir__`
from here.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable
from typing import Any


def lazy_exports(
    package: str, names: dict[str, tuple[str, str]]
) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """The module-level `__getattr__` and `__dir__` of `package`, whose public `names` map to (module, attribute)."""

    def getattr_(name: str) -> Any:
        if name not in names:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        module, attribute = names[name]
        value = getattr(importlib.import_module(module), attribute)
        vars(sys.modules[package])[name] = value  # later look-ups skip this function
        return value

    def dir_() -> list[str]:
        return sorted(set(vars(sys.modules[package])) | set(names))

    return getattr_, dir_


__all__ = ["lazy_exports"]
