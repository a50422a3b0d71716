"""Kinetix's side of a comparison: kinetix-env pins older jax and zarr, so it runs in a virtualenv of its own
(`.venv-kinetix` at the top of the checkout, built on first use), as `python -m benchmarks.<baseline>` from there.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

REPOSITORY = Path(__file__).resolve().parents[1]
"""The top of the checkout: where a baseline runs (`-m benchmarks.<baseline>` finds the package there)."""
KINETIX_REQUIREMENT = "kinetix-env==3.0.2"
DEFAULT_KINETIX_VENV = REPOSITORY / ".venv-kinetix"


def kinetix_python(venv: Path, log) -> Path:
    """The virtualenv's python, as an absolute path (Kinetix's side runs in another folder), creating the virtualenv
    with kinetix-env first if needed."""
    venv = venv.absolute()
    python = venv / "bin" / "python"
    check = [str(python), "-c", "import kinetix.environment"]
    if python.exists() and subprocess.run(check, capture_output=True).returncode == 0:
        return python
    log(f"building {venv} with {KINETIX_REQUIREMENT} (once; a few minutes)")
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    subprocess.run([str(python), "-m", "pip", "install", "--quiet", KINETIX_REQUIREMENT], check=True)
    return python


def baseline_command(python: Path, baseline: str, *arguments: str) -> list[str]:
    """The command that runs `benchmarks/<baseline>.py` under `python`; run it with `cwd=REPOSITORY`."""
    return [str(python), "-m", f"benchmarks.{baseline}", *arguments]
