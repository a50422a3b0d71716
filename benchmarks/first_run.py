"""The quickstart's first run beside a base commit's: wall seconds of `kforge run 1M/s --scale tiny` with a cold and
with a warm compilation cache.

Each run is a fresh process (`python -m kforge run 1M/s --scale tiny`, the quickstart's command; `python -m pipeline`
in a tree from before the `kforge` namespace, which has no kforge/ package) writing into a fresh output folder. A
round runs, for each tree, the first run with an empty `compile_cache.dir` and then the second run on the cache the
first one filled; the base tree and the measured tree alternate (base first in odd rounds, second in even ones), so a
change in the machine's load falls on both. A tree's packages shadow the installed ones through PYTHONPATH (the
embedded Ray worker inherits it; checked before the runs: the command line's package loads from the tree).
Prints the seconds of every run with a digest of the records it committed, the median per tree and run, and the
ratios measured / base; `--json PATH` writes them with the command, both commits and the machine.

    python -m benchmarks.first_run --base 64225c5
    python -m benchmarks.first_run --base-tree ../kforge-base --rounds 2 \
        --json benchmarks/results/quickstart_first_run.json
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

REPOSITORY = Path(__file__).resolve().parent.parent
QUICKSTART = ("run", "1M/s", "--scale", "tiny")
"""The quickstart's `kforge` arguments (README)."""
RUNS = ("first", "second")
"""A tree's runs in a round: with an empty compilation cache, then with the cache the first run filled."""
NAMESPACE_PACKAGE = "kforge/__init__.py"
"""What a tree with the `kforge` namespace holds."""
TAIL_CHARS = 2000
"""Characters of a failed run's output shown in the error."""


def git(tree: Path, *args: str) -> str:
    return subprocess.run(["git", "-C", str(tree), *args], check=True, capture_output=True, text=True).stdout.strip()


def describe_tree(tree: Path) -> dict:
    """The commit a tree is at and whether its tracked files differ from it."""
    return {"commit": git(tree, "rev-parse", "HEAD"), "modified": bool(git(tree, "status", "--porcelain", "-uno"))}


@contextlib.contextmanager
def base_tree(base: str | None, given: Path | None) -> Iterator[Path]:
    """The base checkout: `given`, or a detached git worktree of `base` in a temporary folder (removed after)."""
    if given is not None:
        yield given.resolve()
        return
    with tempfile.TemporaryDirectory(prefix="kforge-base-") as folder:
        tree = Path(folder) / "tree"
        git(REPOSITORY, "worktree", "add", "--detach", str(tree), base)
        try:
            yield tree
        finally:
            git(REPOSITORY, "worktree", "remove", "--force", str(tree))


def cli_package(tree: Path) -> str:
    """The package `python -m` runs the command line of `tree` as: `kforge`, or `pipeline` before the namespace."""
    return "kforge" if (tree / NAMESPACE_PACKAGE).is_file() else "pipeline"


def tree_environment(tree: Path) -> dict[str, str]:
    """This process's environment with `tree` first on PYTHONPATH."""
    environment = dict(os.environ)
    environment["PYTHONPATH"] = os.pathsep.join(filter(None, [str(tree), environment.get("PYTHONPATH")]))
    return environment


def check_shadowing(tree: Path) -> None:
    """Fail unless the command line run as `timed_run` runs it would load its package from `tree`."""
    module = "kforge.pipeline" if cli_package(tree) == "kforge" else "pipeline"
    loaded = subprocess.run(
        [sys.executable, "-c", f"import {module} as p; print(p.__file__)"],
        cwd=tree,
        env=tree_environment(tree),
        check=True,
        capture_output=True,
        text=True,
    ).stdout.strip()
    if not Path(loaded).resolve().is_relative_to(tree):
        raise SystemExit(f"{tree}: its {module} does not shadow the installed one ({loaded} loads instead)")


def records_digest(output: Path) -> str:
    """SHA-256 (16 hex digits) of a dataset's commit records less their provenance (times, worker): which data the
    run made, so runs of one tree can be seen to agree and the two trees to differ."""
    digest = hashlib.sha256()
    for path in sorted((output / "manifest").rglob("*.json")):
        record = json.loads(path.read_text())
        record.pop("provenance", None)
        digest.update(path.relative_to(output).as_posix().encode() + json.dumps(record, sort_keys=True).encode())
    return digest.hexdigest()[:16]


def timed_run(tree: Path, cache: Path, output: Path, log: Path) -> float:
    """Wall seconds of the quickstart's run of `tree` with compilation cache `cache`, writing into `output`."""
    settings = [f"compile_cache.dir={cache}", f"output_dir={output}"]
    command = [sys.executable, "-m", cli_package(tree), *QUICKSTART, *settings]
    started = time.perf_counter()
    with log.open("w") as sink:
        done = subprocess.run(command, cwd=tree, env=tree_environment(tree), stdout=sink, stderr=subprocess.STDOUT)
    seconds = time.perf_counter() - started
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(command)} in {tree} exited {done.returncode}:\n{log.read_text()[-TAIL_CHARS:]}")
    return seconds


def measure(trees: dict[str, Path], rounds: int, scratch: Path) -> list[dict]:
    """Every run of every round: {round, tree, run, seconds}, printed as each ends."""
    results = []
    for round_index in range(rounds):
        order = list(trees) if round_index % 2 == 0 else list(reversed(trees))
        for name in order:
            cache = scratch / f"round-{round_index}-{name}-cache"
            for run in RUNS:
                output = scratch / f"round-{round_index}-{name}-{run}"
                seconds = timed_run(trees[name], cache, output, scratch / f"round-{round_index}-{name}-{run}.log")
                digest = records_digest(output)
                results.append(
                    {"round": round_index, "tree": name, "run": run, "seconds": round(seconds, 1), "records": digest}
                )
                print(f"round {round_index} {name:<8} {run:<6} run {seconds:7.1f} s  records {digest}", flush=True)
    return results


def summarise(results: list[dict]) -> dict:
    """Median seconds per tree and run, and measured / base per run."""
    medians = {
        name: {
            run: statistics.median(r["seconds"] for r in results if (r["tree"], r["run"]) == (name, run))
            for run in RUNS
        }
        for name in ("base", "measured")
    }
    ratios = {run: round(medians["measured"][run] / medians["base"][run], 3) for run in RUNS}
    return {"median_seconds": medians, "measured_over_base": ratios}


def machine() -> dict:
    from benchmarks.machine import describe_machine  # imports JAX: only once every run is done

    return describe_machine() | {"load_average_1_5_15_min": list(os.getloadavg())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    bases = parser.add_mutually_exclusive_group(required=True)
    bases.add_argument("--base", help="the base commit (a git worktree of it is made in a temporary folder)")
    bases.add_argument("--base-tree", type=Path, help="a checkout of the base commit")
    parser.add_argument("--tree", type=Path, default=REPOSITORY, help="the tree measured (default: this repository)")
    parser.add_argument("--rounds", type=int, default=1, help="rounds of both trees' two runs (default 1)")
    parser.add_argument("--json", type=Path, help="write the report to this file")
    args = parser.parse_args()
    if args.rounds < 1:
        parser.error(f"--rounds must be >= 1, got {args.rounds}")
    with (
        base_tree(args.base, args.base_tree) as base,
        tempfile.TemporaryDirectory(prefix="kforge-first-run-") as scratch,
    ):
        trees = {"base": base, "measured": args.tree.resolve()}
        for tree in trees.values():
            check_shadowing(tree)
        described = {name: describe_tree(tree) for name, tree in trees.items()}
        results = measure(trees, args.rounds, Path(scratch))
    summary = summarise(results)
    for run in RUNS:
        base_s, measured_s = (summary["median_seconds"][name][run] for name in ("base", "measured"))
        ratio = summary["measured_over_base"][run]
        print(f"{run:<6} run: base {base_s:.1f} s, measured {measured_s:.1f} s, measured / base {ratio:.2f}")
    if args.json:
        base_commit = described["base"]["commit"][:7]
        report = {
            "command": f"python -m benchmarks.first_run --base {base_commit} --rounds {args.rounds}",
            "command_runs_in": "a checkout of trees.measured.commit (the same runs as the --base-tree / --tree given)",
            "quickstart": "kforge " + " ".join(QUICKSTART),
            "trees": described,
            "rounds": args.rounds,
            "runs": results,
            **summary,
            "machine": machine(),
        }
        args.json.write_text(json.dumps(report, indent=1) + "\n")


if __name__ == "__main__":
    main()
