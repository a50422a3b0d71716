"""Fixtures for the env tests: Kinetix's hand-designed level files, bundled with `env` as package data.

A test with a `fixture_file` argument runs once per level file (s, m and l); tests that need the folder itself take
the `levels_dir` fixture. A missing folder fails them: it is part of the package.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from kforge.env import BUNDLED_SIZES
from kforge.env.bundled_levels import LEVELS_DIR


def fixture_files(size: str | None = None) -> list[Path]:
    """Sorted bundled level files of one size, or of every size."""
    sizes = BUNDLED_SIZES if size is None else (size,)
    return [path for s in sizes for path in sorted((LEVELS_DIR / s).glob("*.json"))]


def fixture_id(path: Path) -> str:
    """Short test id of a level file, e.g. 's/h4_thrust_aim'."""
    return f"{path.parent.name}/{path.stem}"


@pytest.fixture(scope="session")
def levels_dir() -> Path:
    if not all((LEVELS_DIR / size).is_dir() for size in BUNDLED_SIZES):
        pytest.fail(f"the bundled level folder is missing or incomplete: {LEVELS_DIR}")
    return LEVELS_DIR


def pytest_generate_tests(metafunc):
    """Parametrise `fixture_file` over every bundled level file; none at all is an error, not a skip."""
    if "fixture_file" in metafunc.fixturenames:
        files = fixture_files()
        if not files:
            raise pytest.UsageError(f"no bundled level files under {LEVELS_DIR}")
        metafunc.parametrize("fixture_file", files, ids=[fixture_id(path) for path in files])
