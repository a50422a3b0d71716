"""Every shell command the README shows, and every command a finished run suggests on its "next:" lines, runs in a
fresh folder as a new user would type it: in order, from the quickstart's tiny dataset on, each exiting 0, none
printing third-party output (wandb's or Ray's) on the terminal. Commands a test cannot run are listed with the
reason; two are shortened, also listed with the reason."""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.helpers import measured

REPO = Path(__file__).resolve().parents[2]
README = REPO / "README.md"

NOT_RUN = {
    "python3 -m venv": "the test runs inside the project's installed virtualenv",
    ". .venv/bin/activate": "the test runs inside the project's installed virtualenv",
    "pip install": "the test runs inside the project's installed virtualenv",
    "python -m pytest": "the test suite itself",
    "python -m kforge.jobs.submit": "needs a Ray cluster's job server (HEAD:8265) and storage every node reaches",
    "sbatch": "needs a SLURM cluster",
    "ray up": "needs cloud credentials: the cluster launcher starts machines",
}
"""Command prefix -> why the test does not run it."""

SHORTENED = {
    "kforge bc train": (
        ["train.num_steps=4", "validation.every_steps=2", "checkpoint.every_steps=2"],
        "2,000 gradient steps take about an hour on 2 cores",
    ),
    "kforge evaluate": (
        ["--episodes", "1", "--unseen-levels", "2", "--max-levels", "2"],
        "16 episodes on 256 unseen levels take most of an hour on 2 cores",
    ),
}
"""Command prefix -> (arguments appended, why): the command runs as written, on less work."""

THIRD_PARTY_LINE = re.compile(
    r"^(wandb:|\((\w+ )?pid=\d+|\(raylet\)|\(gcs_server\)|\(autoscaler|.*\bworker\.py:\d+ -- |"
    r"Started a local Ray instance)"
)
"""Lines of wandb's and Ray's own terminal output (their prefixes), which belong in the logs without --verbose."""

RUN_SECONDS = 1800
"""[s] Limit of one command (the quickstart's generation compiles for minutes on 2 cores)."""


def readme_commands(text: str) -> list[str]:
    """The shell commands of the README's bash blocks, in order: one per line, `&&` chains split, comments dropped."""
    commands = []
    for block in re.findall(r"```bash\n(.*?)```", text, flags=re.DOTALL):
        for line in block.splitlines():
            line = line.split("  #", 1)[0].strip()
            commands += [part.strip() for part in line.split("&&") if part.strip()]
    return commands


def next_commands(output: str) -> list[str]:
    """The commands on a run's closing "next:" lines, comments dropped."""
    lines = output.splitlines()
    start = lines.index("next:") + 1
    return [line.split("  #", 1)[0].strip() for line in lines[start:] if line.startswith("  ")]


def skipped(command: str) -> str | None:
    return next((why for prefix, why in NOT_RUN.items() if command.startswith(prefix)), None)


def as_run(command: str) -> str:
    for prefix, (extra, _) in SHORTENED.items():
        if command.startswith(prefix):
            return f"{command} {shlex.join(extra)}"
    return command


def run(command: str, cwd: Path, env: dict) -> str:
    started = time.perf_counter()
    result = subprocess.run(
        ["bash", "-c", as_run(command)], cwd=cwd, env=env, capture_output=True, text=True, timeout=RUN_SECONDS
    )
    output = result.stdout + result.stderr
    measured("README command", seconds=time.perf_counter() - started, exit=result.returncode, command=as_run(command))
    assert result.returncode == 0, f"{command!r} exited {result.returncode}:\n{output[-3000:]}"
    chatter = [line for line in output.splitlines() if THIRD_PARTY_LINE.match(line)]
    assert not chatter, f"{command!r} printed third-party output without --verbose: {chatter[:5]}"
    return result.stdout


def test_readme_parsing_finds_the_quickstart_and_the_command_line_block():
    commands = readme_commands(README.read_text())
    assert "kforge run 1M/s --scale tiny" in commands and "kforge verify outputs/1M-s-tiny" in commands
    assert "kforge bc train outputs/1M-s-tiny" in commands and "kforge demo" in commands
    assert [command for command in commands if not skipped(command) and not command.startswith("kforge")] == []
    assert next_commands("done\nnext:\n  kforge verify d\n  kforge bc train d    # then evaluate\n") == [
        "kforge verify d",
        "kforge bc train d",
    ]


@pytest.mark.slow
def test_every_readme_and_next_command_runs_on_a_fresh_tiny_dataset(tmp_path):
    env = os.environ | {
        "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}",  # kforge of this virtualenv
        "HOME": str(tmp_path),  # compiled programs, wandb and Ray files stay in the folder
    }
    env.pop("WANDB_MODE", None)  # wandb as a user gets it (offline by default)
    commands = [command for command in readme_commands(README.read_text()) if not skipped(command)]
    quickstart = commands.index("kforge verify outputs/1M-s-tiny")
    suggested = []
    for index, command in enumerate(commands):
        output = run(command, tmp_path, env)
        if index < quickstart and command.startswith("kforge run"):
            suggested = next_commands(output)
        if index == quickstart:
            assert suggested, "the quickstart's run printed no next: lines"
            for next_command in suggested:
                run(next_command, tmp_path, env)
