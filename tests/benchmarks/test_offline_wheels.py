"""The wheels for a GPU machine without network: the project's own pins, and nothing the job cannot run without."""

import tomllib
from pathlib import Path

from benchmarks.offline_wheels import KFORGE_WHEELS, KINETIX_WHEELS

REPO_ROOT = Path(__file__).resolve().parents[2]


def _pins(requirements) -> dict[str, str]:
    """name -> version of each `name==version` requirement (extras and markers dropped)."""
    pins = {}
    for requirement in requirements:
        name, _, version = requirement.partition("==")
        if version:
            pins[name.split("[")[0].strip().lower()] = version.split(";")[0].split("#")[0].strip()
    return pins


def test_the_project_wheels_carry_the_versions_pyproject_pins():
    project = tomllib.loads((REPO_ROOT / "pyproject.toml").read_text())["project"]
    pinned = _pins(project["dependencies"]) | _pins(project["optional-dependencies"]["bench"])
    carried = _pins(KFORGE_WHEELS)
    assert carried and all(pinned[name] == version for name, version in carried.items()), (carried, pinned)
    assert "ray" not in carried  # larger than a transfer allows; jobs run without it


def test_kinetix_gets_its_own_zarr_2_and_the_numcodecs_that_zarr_2_needs():
    kinetix = _pins(KINETIX_WHEELS)
    numcodecs = tuple(int(part) for part in kinetix["numcodecs"].split("."))
    assert kinetix["zarr"].startswith("2.") and numcodecs < (0, 16)  # 0.16 dropped blosc functions zarr 2 imports
    assert kinetix["kinetix-env"] == "3.0.2"
