"""How fast the command line answers: wall time of `kforge <subcommand> --help` and of an argument or config error,
per subcommand, each in a fresh process (`python -m kforge`, as the installed `kforge` runs it).

    python -m benchmarks.cli_latency [--repeats 3]

Prints one line per command: the median wall time of `--help` and of the error, and the error's exit code (2 for
every input error). Imports nothing heavy itself; run it from the repository root.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ERRORS = {
    "run": ["run", "1M/s", "split.num_levelz=3"],
    "run (PPO sizes)": ["run", "1M/s", "--scale", "tiny", "ppo.num_minibatches=3"],
    "verify": ["verify", "{missing}"],
    "stats": ["stats", "{missing}"],
    "export": ["export", "--format", "kinetix", "{missing}", "{missing}-out"],
    "levels sample": ["levels", "sample", "--size", "x", "--seed", "0", "--num", "1"],
    "levels preview": ["levels", "preview", "s/h0_weak_thrust", "--out", "start.bmp"],
    "levels import": ["levels", "import", "{missing}.json"],
    "levels export": ["levels", "export", "1M/s", "0", "split.num_levelz=3"],
    "levels list": ["levels", "list", "--size", "xl"],
    "bc train": ["bc", "train", "{missing}"],
    "evaluate": ["evaluate", "{missing}"],
    "render": ["render", "{missing}.json", "--steps", "0"],
    "demo": ["demo", "--steps", "x"],
}
"""Subcommand (with what is wrong, in brackets, where it has several cases) -> arguments that are wrong ({missing}: a
path that does not exist)."""


def wall_seconds(arguments: list[str]) -> tuple[float, int]:
    """(seconds, exit code) of one `python -m kforge ARGUMENTS` in a fresh process."""
    started = time.perf_counter()
    result = subprocess.run([sys.executable, "-m", "kforge", *arguments], capture_output=True, text=True)
    return time.perf_counter() - started, result.returncode


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3, help="runs per command; the median is printed (default 3)")
    args = parser.parse_args()
    if args.repeats < 1:
        parser.error(f"--repeats must be >= 1, got {args.repeats}")
    missing = str(Path(tempfile.gettempdir()) / "kforge-cli-latency-missing")
    print(f"{'subcommand':<20} {'--help [s]':>10} {'error [s]':>10} {'exit':>5}")
    for name, template in ERRORS.items():
        arguments = [part.format(missing=missing) for part in template]
        subcommand = name.partition(" (")[0].split()  # "run (PPO sizes)": a second error of `kforge run`
        helps = [wall_seconds([*subcommand, "--help"])[0] for _ in range(args.repeats)]
        errors = [wall_seconds(arguments) for _ in range(args.repeats)]
        code = errors[-1][1]
        error_median = statistics.median(seconds for seconds, _ in errors)
        print(f"{name:<20} {statistics.median(helps):>10.2f} {error_median:>10.2f} {code:>5}")


if __name__ == "__main__":
    main()
