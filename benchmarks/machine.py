"""What every `--json` report records of its run: the command, the commit of the checkout, and the machine.

Figures from different machines are not comparable (two 2-core CPUs used for this project's measurements differ by
2-3x in steps per second, and not by the same factor for every engine), so reports name the CPU model.
"""

from __future__ import annotations

import os
import platform
import shlex
import subprocess
import sys
from pathlib import Path

import jax

CPUINFO = Path("/proc/cpuinfo")
CHECKOUT = Path(__file__).resolve().parents[1]


def cpu_model() -> str:
    """The CPU's model name (Linux: from /proc/cpuinfo), or what `platform` knows elsewhere."""
    if CPUINFO.exists():
        for line in CPUINFO.read_text().splitlines():
            key, _, value = line.partition(":")
            if key.strip() == "model name":
                return value.strip()
    return platform.processor() or platform.machine()


def describe_machine() -> dict:
    """Backend, devices, CPU model and count, and OS platform."""
    return {
        "backend": jax.default_backend(),
        "devices": [str(device) for device in jax.devices()],
        "cpu_model": cpu_model(),
        "cpu_count": os.cpu_count(),
        "platform": platform.platform(),
    }


def provenance(argv: list[str] | None = None) -> dict:
    """The command that runs this benchmark with `argv` (default: this process's arguments), the commit its checkout
    is at (None outside a git checkout) and whether tracked files differ from that commit."""
    argv = sys.argv if argv is None else argv
    command = shlex.join(["python", "-m", f"benchmarks.{Path(argv[0]).stem}", *argv[1:]])
    git = ["git", "-C", str(CHECKOUT)]
    head = subprocess.run([*git, "rev-parse", "HEAD"], capture_output=True, text=True)
    if head.returncode != 0:
        return {"command": command, "commit": None, "modified": None}
    status = subprocess.run([*git, "status", "--porcelain", "--untracked-files=no"], capture_output=True, text=True)
    return {"command": command, "commit": head.stdout.strip(), "modified": bool(status.stdout.strip())}
