"""A description of the machine a benchmark ran on, recorded in every `--json` report.

Figures from different machines are not comparable (two 2-core CPUs used for this project's measurements differ by
2-3x in steps per second, and not by the same factor for every engine), so reports name the CPU model.
"""

from __future__ import annotations

import os
import platform
from pathlib import Path

import jax

CPUINFO = Path("/proc/cpuinfo")


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
