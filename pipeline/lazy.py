"""Package surfaces whose names import their modules when first used (PEP 562 module `__getattr__`), so that a light
name, such as a config loader, does not import JAX, Ray or wandb with its package."""

from __future__ import annotations

import importlib
from collections.abc import Callable


def lazy_surface(package: str, sources: dict[str, str]) -> tuple[Callable[[str], object], list[str]]:
    """`(__getattr__, __all__)` for `package`: `sources` maps a module to its public names (separated by spaces), each
    imported from that module when first used."""
    module_of = {name: module for module, names in sources.items() for name in names.split()}

    def __getattr__(name: str):
        if name not in module_of:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        return getattr(importlib.import_module(module_of[name]), name)

    return __getattr__, sorted(module_of)
