"""Slow: a non-editable install from the built wheel, run from outside the checkout, finds its configs and runs the
quickstart's job by split name."""

from __future__ import annotations

import os
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("wheel")
    command = [sys.executable, "-m", "pip", "wheel", "--no-deps", "-w", str(out), str(REPO)]
    subprocess.run(command, check=True, capture_output=True)
    (path,) = out.glob("kforge-*.whl")
    return path


def test_the_wheel_holds_one_top_level_package_with_every_subpackage_the_configs_and_the_bundled_levels(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    top_level = {name.split("/")[0] for name in names if not name.split("/")[0].endswith(".dist-info")}
    assert top_level == {"kforge"}
    for package in ("engine", "env", "agents", "configs", "pipeline", "pipeline/cli", "pipeline/storage"):
        assert f"kforge/{package}/__init__.py" in names
    for config in ("splits/1M/s.yaml", "splits/10M/m.yaml", "scales/tiny.yaml"):
        assert f"kforge/configs/{config}" in names
    levels = [name for name in names if name.startswith("kforge/env/levels/") and name.endswith(".json")]
    assert len(levels) == 74 and "kforge/env/levels/l/h4_cartpole.json" in levels
    assert {"kforge/env/levels/LICENSE", "kforge/env/levels/README.md"} <= names


def test_an_installed_wheel_runs_the_tiny_split_from_outside_the_checkout(wheel, tmp_path):
    """A fresh virtualenv gets kforge from the wheel alone; its dependencies come from this environment's
    site-packages (a path entry, so this checkout's editable install is not seen), which saves downloading them."""
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    python = venv / "bin" / "python"
    site = subprocess.run(
        [python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
        check=True,
        capture_output=True,
        text=True,
    ).stdout.strip()
    (Path(site) / "dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    subprocess.run([python, "-m", "pip", "install", "--no-deps", "--no-index", str(wheel)], check=True)

    work = tmp_path / "elsewhere"
    work.mkdir()
    env = {**os.environ, "WANDB_MODE": "disabled", "PYTHONPATH": ""}
    where = subprocess.run(
        [python, "-c", "from kforge import configs, pipeline; print(configs.CONFIGS_DIR); print(pipeline.__file__)"],
        cwd=work,
        env=env,
        check=True,
        capture_output=True,
        text=True,
    ).stdout.split()
    assert all(Path(path).is_relative_to(venv) for path in where), where

    kforge = str(venv / "bin" / "kforge")
    run = subprocess.run(
        [kforge, "run", "1M/s", "--scale", "tiny", "--no-progress"],
        cwd=work,
        env=env,
        capture_output=True,
        text=True,
    )
    assert run.returncode == 0, run.stderr[-2000:]
    dataset = work / "outputs" / "1M-s-tiny"
    verify = subprocess.run([kforge, "verify", str(dataset)], cwd=work, env=env, capture_output=True, text=True)
    assert verify.returncode == 0, verify.stdout[-2000:] + verify.stderr[-2000:]
    assert "bad shards: none" in verify.stdout
