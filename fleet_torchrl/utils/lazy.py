"""Package namespaces that import their heavy modules on first use (PEP 562).

A package's ``__init__`` names what it offers; importing the package, or one of its light
modules (a schema in ``<package>/config.py``), must not import torch or TorchRL: composing a
config for ``--help`` or tab completion reaches every schema module, and torch plus TorchRL
take seconds to import. ``from fleet_torchrl.sim import Site`` still works: the first access
imports ``sim/site.py``.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any


def lazy_exports(package: str, exports: dict[str, str]
                 ) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """``__getattr__`` and ``__dir__`` for ``package``: ``exports`` maps a public name to the
    submodule (relative, e.g. ``".site"``) that defines it."""

    def __getattr__(name: str) -> Any:
        module = exports.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(module, package), name)
        globals_of(package)[name] = value  # later lookups skip this function
        return value

    def __dir__() -> list[str]:
        return sorted({*globals_of(package), *exports})

    return __getattr__, __dir__


def globals_of(package: str) -> dict[str, Any]:
    import sys

    return vars(sys.modules[package])


def lazy_module(package: str, module: str
                ) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """``__getattr__`` and ``__dir__`` for ``package`` that offer every public name of its
    submodule ``module`` (relative, e.g. ``".learner"``), imported on first access: a
    package whose light modules (its schema) import at once and whose heavy one waits."""

    def __getattr__(name: str) -> Any:
        if name.startswith("__"):
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        try:
            value = getattr(importlib.import_module(module, package), name)
        except AttributeError:
            raise AttributeError(f"module {package!r} has no attribute {name!r}") from None
        globals_of(package)[name] = value
        return value

    def __dir__() -> list[str]:
        return sorted(globals_of(package))

    return __getattr__, __dir__
