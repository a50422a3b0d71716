"""Kinetix's hand-designed levels that ship with kforge as package data, named "SIZE/NAME" (e.g. "l/h4_cartpole")."""

from __future__ import annotations

import difflib
from pathlib import Path

LEVELS_DIR = Path(__file__).resolve().parent / "levels"
"""The bundled level files: LEVELS_DIR/<size>/<name>.json."""

BUNDLED_SIZES = ("s", "m", "l")
CLOSE_NAMES = 3
"""How many similar names an unknown name's error suggests."""


def list_levels(size: str | None = None) -> list[str]:
    """Names of the bundled levels ("s/h0_weak_thrust", ...), of one size or of all, sorted by size then name."""
    if size is not None and size not in BUNDLED_SIZES:
        raise ValueError(f"unknown size {size!r}; expected one of {', '.join(BUNDLED_SIZES)}")
    sizes = BUNDLED_SIZES if size is None else (size,)
    return [f"{s}/{path.stem}" for s in sizes for path in sorted((LEVELS_DIR / s).glob("*.json"))]


def bundled_level_path(name: str) -> Path | None:
    """The file of bundled level `name` ("SIZE/NAME", with or without .json), or None if there is no such level."""
    name = name.removesuffix(".json")
    return LEVELS_DIR / f"{name}.json" if name in list_levels() else None


def close_level_names(name: str) -> list[str]:
    """Bundled level names that look like `name`, for an error message."""
    return difflib.get_close_matches(name.removesuffix(".json"), list_levels(), n=CLOSE_NAMES)
