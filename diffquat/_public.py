"""What ``dir()`` of a public module lists: its public API only (PEP 562's module ``__dir__``).

A public module imports what its code needs (``torch``, ``Tensor``, ``Any``, the private helpers that
bind the core), and those names would otherwise fill ``dir(diffquat.torch)`` and an editor's
completion beside the rotation functions. Each public module sets ``__dir__ = public_dir(globals())``;
``tests/test_api.py`` walks the package and checks every public module, present and future, lists
nothing else.
"""

from __future__ import annotations

import importlib
import pkgutil
from collections.abc import Callable
from types import ModuleType
from typing import Any


def public_dir(namespace: dict[str, Any]) -> Callable[[], list[str]]:
    """A module ``__dir__``: the module's ``__all__``, its public submodules that are imported, and
    the module's dunder attributes (``__doc__``, ``__file__``...), sorted."""

    def __dir__() -> list[str]:
        name = namespace["__name__"]
        submodules = [
            k
            for k, v in namespace.items()
            if isinstance(v, ModuleType) and v.__name__ == f"{name}.{k}" and not k.startswith("_")
        ]
        dunders = [k for k in namespace if k.startswith("__") and k.endswith("__")]
        return sorted({*namespace["__all__"], *submodules, *dunders})

    return __dir__


def public_modules() -> list[ModuleType]:
    """Every public module of diffquat, present and future: no part of its dotted name private (the
    API reference and tests/test_api.py walk these)."""
    import diffquat

    names = ["diffquat"] + [
        m.name
        for m in pkgutil.walk_packages(diffquat.__path__, "diffquat.")
        if not any(part.startswith("_") for part in m.name.split("."))
    ]
    return [importlib.import_module(n) for n in names]
