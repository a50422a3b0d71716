"""Shared fixtures for the env tests: the Kinetix level files in the shared folder beside the project root.

A test with a `fixture_file` argument runs once per level file (s and m); tests that need the folder itself take
the `shared_levels_dir` fixture. Without the shared folder those tests are skipped.
"""

from __future__ import annotations

from pathlib import Path

import pytest

SHARED_LEVELS_DIR = Path(__file__).resolve().parents[2].parent / "shared" / "levels" / "kinetix"
"""`../shared/levels/kinetix` relative to the project root: one sub-folder per size with Kinetix level JSON files."""

FIXTURE_SIZES = ("s", "m")
"""Sizes with level files in the shared folder."""


def fixture_files(size: str | None = None) -> list[Path]:
    """Sorted level files of one size, or of every size in `FIXTURE_SIZES`."""
    sizes = FIXTURE_SIZES if size is None else (size,)
    return [path for s in sizes for path in sorted((SHARED_LEVELS_DIR / s).glob("*.json"))]


def fixture_id(path: Path) -> str:
    """Short test id of a level file, e.g. 's/h4_thrust_aim'."""
    return f"{path.parent.name}/{path.stem}"


@pytest.fixture(scope="session")
def shared_levels_dir() -> Path:
    if not SHARED_LEVELS_DIR.is_dir():
        pytest.skip(f"shared level folder not found: {SHARED_LEVELS_DIR}")
    return SHARED_LEVELS_DIR


def pytest_generate_tests(metafunc):
    """Parametrise `fixture_file` over every level file (an empty set skips the test)."""
    if "fixture_file" in metafunc.fixturenames:
        files = fixture_files()
        metafunc.parametrize("fixture_file", files, ids=[fixture_id(path) for path in files])
