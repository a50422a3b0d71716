"""One rule for exit codes in every subcommand: Ctrl-C (a real SIGINT) ends each with 130 and one line; argument and
input errors exit 2 (tests/pipeline/test_cli_fast.py), damaged data 1 (tests/pipeline/test_verify.py)."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from pipeline_test_helpers import as_a_terminal_job

from kforge.pipeline.cli import EXIT_INTERRUPTED

REPO = Path(__file__).resolve().parents[2]
SIGINT_AFTER_SECONDS = 1.5
"""[s] Every command below is still importing JAX or compiling by then on any machine."""


def interruptible(dataset: Path, tmp: Path) -> dict[str, list[str]]:
    return {
        "verify": ["verify", str(dataset)],
        "stats": ["stats", str(dataset), "--out", str(tmp / "card")],
        "export": ["export", "--format", "kinetix", str(dataset), str(tmp / "export")],
        "levels sample": ["levels", "sample", "--size", "s", "--seed", "0", "--num", "64", "--out", str(tmp / "lv")],
        "levels preview": ["levels", "preview", "s/h0_weak_thrust", "--out", str(tmp / "h0.gif")],
        "render": ["render", "s/h0_weak_thrust", "--out", str(tmp / "render.gif")],
        "demo": ["demo", "--out", str(tmp / "demo.gif")],
        "bc train": ["bc", "train", str(dataset), f"output_dir={tmp / 'bc'}", "tracking.wandb=disabled"],
    }


@pytest.mark.parametrize(
    "name",
    [
        "verify",
        "stats",
        "export",
        "levels sample",
        "levels preview",
        "render",
        "demo",
        "bc train",
    ],
)
def test_sigint_exits_130_with_one_line(name, dataset_dir, tmp_path):
    argv = interruptible(dataset_dir, tmp_path)[name]
    process = subprocess.Popen(
        [sys.executable, "-m", "kforge", *argv],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=as_a_terminal_job,
    )
    time.sleep(SIGINT_AFTER_SECONDS)
    assert process.poll() is None, f"kforge {name} ended before it could be interrupted"
    process.send_signal(signal.SIGINT)
    _, err = process.communicate(timeout=120)
    assert process.returncode == EXIT_INTERRUPTED, err
    lines = err.strip().splitlines()
    assert "Traceback" not in err and len(lines) >= 1 and "interrupted" in lines[-1], err
