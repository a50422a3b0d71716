"""BC training throughput beside a base commit's: transitions per second of the training loop end to end (batches read
from the dataset's host cache, observations rendered, gradient and optimiser steps) with each tree's default model.

Each tree runs in its own process (its `kforge` first on the path): it opens the dataset's training levels with the
loader as `kforge bc train` does, compiles its training program, then times `--steps` gradient steps, reading each
batch as the loop does (the base tree one step per call, the measured one `steps_per_dispatch` per call). It also
times the parts of one call alone: reading a batch from the host cache onto the device, rendering a batch's
observations, and the whole training call. The trees alternate (base first in odd rounds, second in even ones); the
figures are medians over rounds, with the measured / base ratio of wall time and of CPU time (the process's, all
threads: the figure that holds when the machine is shared).

    python -m benchmarks.bc_throughput --base f9d66a2 --dataset DATASET --json benchmarks/results/bc_throughput_cpu.json

Without `--dataset`, the quickstart's tiny dataset is made first (`kforge run 1M/s --scale tiny`).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPOSITORY = Path(__file__).resolve().parent.parent
PART_REPEATS = 2
"""Timings of each part of one batch; the median is kept."""


def _median_seconds(action, repeats: int = PART_REPEATS) -> float:
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        action()
        times.append(time.perf_counter() - started)
    return statistics.median(times)


def worker(dataset: str, batch_size: int, steps: int, run_dir: str) -> dict:
    """The figures of the tree this process imports `kforge` from."""
    import jax

    from kforge.pipeline.learning import kept_levels, load_bc_config
    from kforge.pipeline.learning.data import validation_split
    from kforge.pipeline.learning.train import Learner
    from kforge.pipeline.reading import TrajectoryDatasetManager
    from kforge.pipeline.storage import open_dataset

    overrides = [f"output_dir={run_dir}", "tracking.wandb=disabled", f"train.batch_size={batch_size}"]
    config = load_bc_config(dataset, overrides)
    train_ids, _ = validation_split(sorted(kept_levels(dataset)), config.validation.fraction, config.train.seed)
    layout = open_dataset(dataset).layout
    learner = Learner(config, layout.static, layout.num_steps)
    loader = TrajectoryDatasetManager(
        dataset,
        batch_size=batch_size,
        seed=config.train.seed,
        prefetch=config.train.prefetch,
        level_ids=train_ids,
        cache_bytes=int(config.train.cache_gb * (1 << 30)),
    )
    per_call = getattr(learner, "steps_per_dispatch", 1)

    def call(state, batches):
        if hasattr(learner, "steps"):
            return learner.steps(state, batches)[0]
        return learner.step(state, batches[0])[0]

    with loader:
        state = learner.init(config.train.seed)
        started = time.perf_counter()
        state = jax.block_until_ready(call(state, [loader.load_next_batch() for _ in range(per_call)]))
        compile_s = time.perf_counter() - started
        calls = max(1, steps // per_call)
        wall, cpu = time.perf_counter(), time.process_time()
        for _ in range(calls):
            state = call(state, [loader.load_next_batch() for _ in range(per_call)])
        jax.block_until_ready(state)
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
        batch = loader.load_next_batch()
        render = jax.jit(learner.observations)
        jax.block_until_ready(render(batch.env_state))
        parts = {
            "read_batch_s": _median_seconds(lambda: jax.block_until_ready(loader.load_slots(batch.trajectory_index))),
            "render_observations_s": _median_seconds(lambda: jax.block_until_ready(render(batch.env_state))),
            "training_call_s": _median_seconds(lambda: jax.block_until_ready(call(state, [batch] * per_call))),
        }
    transitions = calls * per_call * batch_size * layout.num_steps
    return {
        "model": {key: value for key, value in vars(config.model).items()},
        "steps_per_call": per_call,
        "timed_steps": calls * per_call,
        "transitions": transitions,
        "compile_and_first_call_s": compile_s,
        "wall_s": wall,
        "cpu_s": cpu,
        "transitions_per_s": transitions / wall,
        "transitions_per_cpu_s": transitions / cpu,
        "parts_per_call": parts,
        "parts_transitions_per_call": per_call * batch_size * layout.num_steps,
        "cached": loader.cached,
    }


def run_tree(tree: Path, dataset: str, batch_size: int, steps: int, scratch: Path) -> dict:
    """`worker` in a process that imports the tree's `kforge`."""
    from benchmarks.first_run import tree_environment

    command = [sys.executable, str(Path(__file__).resolve()), "--worker", dataset, str(batch_size), str(steps)]
    command.append(str(scratch / "run"))
    done = subprocess.run(command, cwd=tree, env=tree_environment(tree), capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"{tree}: the worker exited {done.returncode}:\n{done.stderr[-2000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def make_dataset(folder: Path) -> str:
    """The quickstart's tiny dataset, made by the measured tree."""
    output = folder / "tiny"
    command = [
        sys.executable,
        "-m",
        "kforge",
        "run",
        "1M/s",
        "--scale",
        "tiny",
        f"output_dir={output}",
        "--no-progress",
    ]
    subprocess.run(command, cwd=REPOSITORY, check=True, capture_output=True)
    return str(output)


def summarise(results: list[dict]) -> dict:
    """Median figures per tree and the measured / base ratios."""
    medians = {}
    for name in ("base", "measured"):
        runs = [r["figures"] for r in results if r["tree"] == name]
        medians[name] = {
            key: statistics.median(run[key] for run in runs) for key in ("transitions_per_s", "transitions_per_cpu_s")
        } | {
            "parts_ms_per_call": {
                part: 1e3 * statistics.median(run["parts_per_call"][part] for run in runs)
                for part in runs[0]["parts_per_call"]
            },
            "parts_transitions_per_call": runs[0]["parts_transitions_per_call"],
            "model": runs[0]["model"],
            "steps_per_call": runs[0]["steps_per_call"],
        }
    ratios = {
        key: round(medians["measured"][key] / medians["base"][key], 2)
        for key in ("transitions_per_s", "transitions_per_cpu_s")
    }
    return {"medians": medians, "measured_over_base": ratios}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    bases = parser.add_mutually_exclusive_group(required=True)
    bases.add_argument("--base", help="the base commit (a git worktree of it is made in a temporary folder)")
    bases.add_argument("--base-tree", type=Path, help="a checkout of the base commit")
    parser.add_argument("--dataset", help="a dataset to train on (default: the quickstart's tiny one, made first)")
    parser.add_argument("--batch-size", type=int, default=16, help="trajectories per gradient step, both trees")
    parser.add_argument("--steps", type=int, default=8, help="gradient steps timed per tree and round")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--json", type=Path, help="write the figures here")
    args = parser.parse_args()
    from benchmarks.first_run import base_tree, check_shadowing, describe_tree

    with (
        tempfile.TemporaryDirectory(prefix="kforge-bc-throughput-") as scratch,
        base_tree(args.base, args.base_tree) as base,
    ):
        scratch = Path(scratch)
        trees = {"base": base, "measured": REPOSITORY}
        for tree in trees.values():
            check_shadowing(tree)
        dataset = args.dataset or make_dataset(scratch)
        results = []
        for round_index in range(args.rounds):
            order = ["base", "measured"] if round_index % 2 == 0 else ["measured", "base"]
            for name in order:
                figures = run_tree(trees[name], dataset, args.batch_size, args.steps, scratch / f"{name}-{round_index}")
                results.append({"round": round_index, "tree": name, "figures": figures})
                print(
                    f"round {round_index} {name:8s}: {figures['transitions_per_s']:8.0f} transitions/s, "
                    f"{figures['transitions_per_cpu_s']:8.0f} per CPU second",
                    flush=True,
                )
        described = {name: describe_tree(tree) for name, tree in trees.items()}
    summary = summarise(results)
    for name in ("base", "measured"):
        parts = ", ".join(f"{k} {v:.0f} ms" for k, v in summary["medians"][name]["parts_ms_per_call"].items())
        transitions = summary["medians"][name]["parts_transitions_per_call"]
        print(f"{name:8s} parts of one call ({transitions} transitions): {parts}")
    ratio = summary["measured_over_base"]
    print(f"measured / base: {ratio['transitions_per_s']:.2f}x wall, {ratio['transitions_per_cpu_s']:.2f}x CPU time")
    if args.json:
        from benchmarks.machine import describe_machine  # imports JAX: only once every run is done

        base_commit = described["base"]["commit"][:7]
        report = {
            "command": (
                f"python -m benchmarks.bc_throughput --base {base_commit} --dataset DATASET "
                f"--batch-size {args.batch_size} --steps {args.steps} --rounds {args.rounds}"
            ),
            "dataset": Path(dataset).name,  # the folder's name: no machine path in the report
            "trees": described,
            "machine": describe_machine() | {"load_average_1_5_15_min": list(os.getloadavg())},
            "batch_size": args.batch_size,
            "runs": results,
            **summary,
        }
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--worker":
        dataset, batch_size, steps, run_dir = sys.argv[2:6]
        print(json.dumps(worker(dataset, int(batch_size), int(steps), run_dir)))
    else:
        main()
