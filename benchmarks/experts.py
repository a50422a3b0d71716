"""Expert quality: how often a PPO specialist solves its level at a given budget, on random and hand-designed s levels.

Two level sets: the first `--levels` levels of split 1M/s (the pipeline's level keys, so level i here is level i of
that split) and Kinetix's 10 hand-designed s levels (bundled with `env`, `kforge levels list --size s`). Each level
gets one expert per budget in `--budgets`, trained and rolled out exactly as pipeline/generation/level_batch.py does
(its env, PPO and collection settings and per-level keys). Per set and budget it prints:

- window success: the share of levels whose expert window is successful (the pipeline's definition: a 256-step
  window from the level's start with auto-reset in which at least one episode ends and every ending is a success,
  `agents.collect_windows`), over all levels and over those the trivial-level filter keeps
  (`env.level_filter.filter_levels` with the pipeline's no-op steps). Kinetix-Offline's card: about 50 % of generated
  levels were solvable at its budgets;
- evaluation success: `agents.evaluate` over `--episodes` episodes per level, averaged over levels;
- wall time per level (training, window and evaluation of a vmapped batch divided by its levels; compiling excluded
  and printed apart);
- with several budgets, whether each larger budget solves strictly more levels than the one before, and which levels
  only the smaller one solved.

Budgets must be multiples of the PPO update (num_envs x num_steps; 2,000 env steps by default); `--scale tiny` or
`--set ppo.num_envs=8 ppo.num_steps=32` allows powers of two. `--json` prints one JSON document with per-level
results instead. The default run (64 random levels at 1M) trains 64M env steps plus the hand-designed set, about
half an hour on a 2-core CPU; 10M as well is about 8 x 10^8 env steps, about five hours. `--first-level K` measures
levels K, K + 1, ... with their own keys, so a long measurement can be cut into parts (same results as one run
with the same `--batch`), and `--merge` prints the summaries and budget comparisons of the parts' `--json` reports
taken together (the levels every budget covers); `--hand-first K --hand-count N` cuts the hand-designed set the
same way (levels in name order, each with the keys of its position in the whole set). benchmarks/results/ holds
the reports the README quotes (per-level results included), so a new part can be merged with them. A quick check,
and a measurement in parts:

    python -m benchmarks.experts --levels 8 --budgets 65536 131072 --scale tiny
    python -m benchmarks.experts --budgets 1000000 10000000 --json
    python -m benchmarks.experts --levels 32 --first-level 32 --batch 32 --budgets 10000000 \\
        --sets random --json > b.json
    python -m benchmarks.experts --merge a.json b.json 1m.json
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks.machine import describe_machine, provenance
from kforge.agents import EpisodePlan, WindowPlan, collect_windows, evaluate, train_levels
from kforge.configs import split_path
from kforge.engine import physics_scheme
from kforge.env import FilterReason, Level, bundled_level_path, filter_levels, load_level, under_scheme
from kforge.pipeline.generation import (
    KeyPurpose,
    ResolvedJob,
    level_keys,
    load_config,
    resolve,
    sample_batch,
)

SPLIT = "1M/s"
SPLIT_CONFIG = split_path(SPLIT)
"""The split whose levels, env, filter, PPO and collection settings are used (its budget is replaced)."""

HAND_LEVELS_DIR = bundled_level_path("s/h0_weak_thrust").parent
"""The hand-designed s levels bundled with `env`."""
HAND_LEVELS_SEED = 1_000_003
"""Split seed of the hand-designed levels' training keys: a stream no release split uses."""

EVALUATE_PURPOSE = max(KeyPurpose) + 1
"""Key purpose of evaluation episodes, after the pipeline's own purposes (sample, train, collect)."""

DEFAULT_BUDGETS = (1_000_000,)
DEFAULT_RANDOM_LEVELS = 64
DEFAULT_EPISODES = 16
KINETIX_OFFLINE_SOLVED_SHARE = 0.5
"""Share of generated levels Kinetix-Offline's card calls solvable (its experts' rollouts succeeded)."""


def load_hand_levels(directory: Path, job: ResolvedJob) -> tuple[list[str], Level]:
    """The level files of `directory` (sorted by name) as one batched Level, played under the job's physics; they
    must have the split's size."""
    paths = sorted(directory.glob("*.json"))
    if not paths:
        raise SystemExit(f"no level files in {directory}")
    loaded = [load_level(path) for path in paths]
    scheme = physics_scheme(job.config.env.physics)
    for path, level in zip(paths, loaded, strict=True):
        static = under_scheme(scheme, level.params, level.static)[1]
        if static != job.static:
            raise SystemExit(f"{path}: static parameters {static} differ from the split's {job.static}")
    return [path.stem for path in paths], jax.tree.map(lambda *x: jnp.stack(x), *(level.level for level in loaded))


def hand_range(first: int, count: int | None, available: int, error) -> tuple[int, int]:
    """(first, count) of the hand-designed levels to measure; `error(message)` reports a range outside the set."""
    count = available - first if count is None else count
    if first < 0 or count < 1 or first + count > available:
        error(f"--hand-first {first} --hand-count {count}: the set has hand-designed levels 0..{available - 1}")
    return first, count


def sample_split_levels(job: ResolvedJob, first: int, count: int) -> Level:
    """The split's levels first, ..., first + count - 1, sampled in the pipeline's batches (`work.levels_per_batch`
    levels per call, aligned as in pipeline/generation/level_batch.py, since XLA may round differently for another
    shape)."""
    batch = job.work.levels_per_batch
    aligned = first - first % batch
    chunks = [sample_batch(job, np.arange(start, start + batch)) for start in range(aligned, first + count, batch)]
    return jax.tree.map(lambda *x: jnp.concatenate(x)[first - aligned : first - aligned + count], *chunks)


class _BatchExperts:
    """One vmapped batch's experts: rolls out their windows and evaluates them with per-level keys (`job`: the
    resolved job whose settings they were trained with)."""

    def __init__(self, job: ResolvedJob, params, levels: Level, seed: int, indices: np.ndarray):
        self.job, self.params, self.levels, self.seed, self.indices = job, params, levels, seed, indices

    def window(self):
        job = self.job
        return collect_windows(
            self.params,
            self.levels,
            level_keys(self.seed, self.indices, KeyPurpose.COLLECT),
            WindowPlan(job.ppo, job.static, num_steps=job.collect.window_steps, greedy=job.collect.greedy),
            job.env_params,
        )

    def evaluate(self, episodes: int):
        job = self.job
        return evaluate(
            self.params,
            self.levels,
            level_keys(self.seed, self.indices, EVALUATE_PURPOSE),
            EpisodePlan(job.ppo, job.static, num_episodes=episodes, greedy=job.collect.greedy),
            job.env_params,
        )


def _timed(function, warm_up: bool) -> tuple[object, float]:
    """(host copy of function(), seconds of that call); `warm_up` first makes one untimed call (compiling)."""
    if warm_up:
        jax.block_until_ready(function())
    clock = time.perf_counter()
    output = jax.device_get(function())
    return output, time.perf_counter() - clock


def run_experts(
    job: ResolvedJob, levels: Level, seed: int, first: int, batch: int, episodes: int, programs: dict, log
) -> dict:
    """Train, roll out and evaluate one expert per level in vmapped batches of `batch` levels (the last padded).

    The experts use the env, PPO and collection settings of `job`. Level j of `levels` gets the keys of level
    `first + j` of its set, so a range measured in parts gets the same results as in one run with the same `batch`.

    `programs` holds compiled training programs by (PPO config, static params, batch size), shared between calls.
    Returns per-level arrays (window success, episodes ended in the window, evaluation success rate, last update's
    training success rate, env steps of the selected expert) and seconds: compiling the training (0 when reused),
    and training / window / evaluation summed over batches.
    """
    env_params, static, config = job.env_params, job.static, job.ppo
    count = len(jax.tree.leaves(levels)[0])
    padded = -(-count // batch) * batch
    names = ("successful", "episodes_ended", "eval_success_rate", "train_success_rate", "selected_env_steps")
    results = {name: [] for name in names}
    seconds = {"compile": 0.0, "train": 0.0, "window": 0.0, "evaluate": 0.0}
    for start in range(0, padded, batch):
        indices = np.minimum(np.arange(start, start + batch), count - 1)
        batch_levels = jax.tree.map(lambda x, indices=indices: x[indices], levels)
        train_keys = level_keys(seed, first + indices, KeyPurpose.TRAIN)
        if (config, static, batch) not in programs:
            clock = time.perf_counter()
            programs[config, static, batch] = train_levels.lower(
                batch_levels, train_keys, config, env_params, static
            ).compile()
            seconds["compile"] = time.perf_counter() - clock
        compiled = programs[config, static, batch]
        last = min(start + batch, count) - 1
        trained, elapsed = _timed(functools.partial(compiled, batch_levels, train_keys, env_params), warm_up=False)
        seconds["train"] += elapsed
        expert = _BatchExperts(job, trained.params, batch_levels, seed, first + indices)
        window, elapsed = _timed(expert.window, warm_up=start == 0)
        seconds["window"] += elapsed
        evaluation, elapsed = _timed(functools.partial(expert.evaluate, episodes), warm_up=start == 0)
        seconds["evaluate"] += elapsed
        results["successful"].append(window.successful)
        results["episodes_ended"].append(window.episodes_ended)
        results["eval_success_rate"].append(evaluation.success_rate)
        results["train_success_rate"].append(trained.metrics.success_rate[:, -1])
        results["selected_env_steps"].append(trained.selection.at_best(trained.selection.env_steps))
        log(f"  levels {first + start}-{first + last} done, {last + 1} of {count} ({seconds['train']:.0f} s training)")
    per_level = {name: np.concatenate(values)[:count] for name, values in results.items()}
    return {"per_level": per_level, "seconds": seconds, "padded_levels": padded}


def _share(part: np.ndarray) -> float | None:
    """Mean of a boolean or rate array; None when it is empty."""
    return float(np.mean(part)) if part.size else None


def _percent(share: float | None) -> str:
    return "n/a" if share is None else f"{share:.0%}"


def summarise(per_level: dict, keep: np.ndarray, seconds: dict, count: int, padded: int) -> dict:
    """Shares of solved levels (all / kept by the filter), evaluation success and wall time per level."""
    successful = per_level["successful"].astype(bool)
    kept = int(keep.sum())
    work_seconds = seconds["train"] + seconds["window"] + seconds["evaluate"]
    return {
        "levels": count,
        "kept_by_filter": kept,
        "solved": int(successful.sum()),
        "solved_share": _share(successful),
        "solved_kept": int(successful[keep].sum()),
        "solved_share_kept": _share(successful[keep]),
        "eval_success_rate": _share(per_level["eval_success_rate"]),
        "eval_success_rate_kept": _share(per_level["eval_success_rate"][keep]),
        "seconds_per_level": work_seconds / padded,
        "train_seconds_per_level": seconds["train"] / padded,
        "compile_seconds": seconds["compile"],
    }


class Measurement(NamedTuple):
    """What every level set of one run shares: the command's arguments, the split's job at their settings (resolved
    once), the compiled training programs and where lines go."""

    args: argparse.Namespace
    base: ResolvedJob
    programs: dict  # compiled training programs by (PPO config, static params, batch size)
    log: Callable[[str], None]


def measure_set(name: str, ids: list, levels: Level, seed: int, first: int, measurement: Measurement, random: bool):
    """Every budget on one level set: the filter's verdicts, then per budget the experts' results and summary.

    Level j of `levels` is level `first + j` of its set (its keys). `random`: the set is sampled from the level
    distribution, so Kinetix-Offline's solved share is its reference.
    """
    args, base, log = measurement.args, measurement.base, measurement.log
    verdicts = jax.device_get(filter_levels(levels, base.env_params, base.static, noop_steps=base.filter.noop_steps))
    keep = np.asarray(verdicts.keep)
    count = len(ids)
    log(f"{name}: {count} levels, {int(keep.sum())} kept by the trivial-level filter")
    report = {
        "levels": ids,
        "filter_reason": [FilterReason(int(reason)).name.lower() for reason in verdicts.reason],
        "budgets": {},
    }
    reference = f" (Kinetix-Offline ~{KINETIX_OFFLINE_SOLVED_SHARE:.0%})" if random else ""
    for budget in args.budgets:
        job = resolve(load_config(SPLIT_CONFIG, [*args.set, f"split.expert_budget={budget}"], args.scale))
        config = job.ppo
        log(f"{name} budget {budget:,}: {config.num_updates} updates of {config.num_envs} x {config.num_steps} steps")
        batch = args.batch or job.work.levels_per_batch
        run = run_experts(job, levels, seed, first, batch, args.episodes, measurement.programs, log)
        summary = summarise(run["per_level"], keep, run["seconds"], count, run["padded_levels"])
        log(_summary_line(name, budget, summary, reference))
        report["budgets"][str(budget)] = {
            "summary": summary,
            "per_level": {key: value.tolist() for key, value in run["per_level"].items()},
        }
    report["budget_comparisons"] = compare_budgets(name, ids, report["budgets"], log)
    return report


def _summary_line(name: str, budget: int, summary: dict, reference: str) -> str:
    return (
        f"{name} budget {int(budget):,}: window success {summary['solved']}/{summary['levels']} = "
        f"{_percent(summary['solved_share'])}{reference}; among the {summary['kept_by_filter']} kept "
        f"{summary['solved_kept']} = {_percent(summary['solved_share_kept'])}; evaluation success "
        f"{_percent(summary['eval_success_rate'])} (kept {_percent(summary['eval_success_rate_kept'])}); "
        f"{summary['seconds_per_level']:.1f} s per level, compile {summary['compile_seconds']:.0f} s"
    )


def compare_budgets(name: str, ids: list, budgets: dict, log) -> list:
    """For each budget after the first: does it solve strictly more levels, and which levels lost their solve."""
    comparisons = []
    ordered = sorted(budgets, key=int)
    for smaller, larger in zip(ordered, ordered[1:], strict=False):
        before = np.asarray(budgets[smaller]["per_level"]["successful"], bool)
        after = np.asarray(budgets[larger]["per_level"]["successful"], bool)
        lost = [ids[i] for i in np.flatnonzero(before & ~after)]
        comparison = {
            "smaller": int(smaller),
            "larger": int(larger),
            "solved": [int(before.sum()), int(after.sum())],
            "strictly_more": bool(after.sum() > before.sum()),
            "solved_only_by_smaller": lost,
        }
        comparisons.append(comparison)
        log(
            f"{name}: {int(larger):,} solves {after.sum()} vs {before.sum()} at {int(smaller):,} "
            f"(strictly more: {'yes' if comparison['strictly_more'] else 'no'}); solved only at the smaller budget: "
            f"{lost or 'none'}"
        )
    return comparisons


MERGE_SETTINGS = ("split_config", "scale", "overrides", "batch")
"""Report keys that parts of one measurement must share (null, the default, is a value like any other; a part that
does not record a key is not checked on it)."""

SELECTION_SETTINGS = ("select_every_updates", "select_episodes", "select_greedy")
"""PPO keys of expert selection; a report records them, and reports from before selection (none recorded) do not
merge with reports that use it."""


def merge_reports(reports: list[dict], log) -> dict:
    """One report from the reports of a measurement's parts (level ranges, or budgets run apart): per level set, the
    levels that every budget covers, their summaries and the budget comparisons. A level measured twice must have
    the same results in both reports."""
    for key in MERGE_SETTINGS:
        values = {json.dumps(report[key]) for report in reports if key in report}
        if len(values) > 1:
            raise SystemExit(f"--merge: the reports were measured with different {key}: {', '.join(sorted(values))}")
    selections = {json.dumps(report.get("expert_selection")) for report in reports}
    if len(selections) > 1:
        raise SystemExit(f"--merge: the reports select experts differently (null: before selection): {selections}")
    machines = [machine for report in reports for machine in report.get("machines", [report.get("machine")])]
    machines = list({json.dumps(machine, sort_keys=True): machine for machine in machines}.values())
    merged = {"machines": machines} | {key: reports[0].get(key) for key in (*MERGE_SETTINGS, "expert_selection")}
    merged |= {"merged_reports": len(reports), "sets": {}}
    for name in sorted({name for report in reports for name in report["sets"]}):
        reasons, results, parts = {}, {}, {}
        for report in reports:
            part = report["sets"].get(name)
            if part is None:
                continue
            for i, level in enumerate(part["levels"]):
                if reasons.setdefault(level, part["filter_reason"][i]) != part["filter_reason"][i]:
                    raise SystemExit(f"--merge: set {name} level {level}: the filter differs between reports")
            for budget, entry in part["budgets"].items():
                parts.setdefault(budget, []).append(entry["summary"])
                for i, level in enumerate(part["levels"]):
                    values = {key: column[i] for key, column in entry["per_level"].items()}
                    if results.setdefault(budget, {}).setdefault(level, values) != values:
                        raise SystemExit(f"--merge: set {name} level {level} budget {budget}: results differ")
        ids = sorted(set.intersection(*(set(by_level) for by_level in results.values())))
        missing = sorted(set(reasons) - set(ids))
        if missing:
            log(f"{name}: {len(missing)} levels lack a budget and are left out: {missing}")
        keep = np.array([reasons[level] == "kept" for level in ids], bool)
        log(f"{name}: {len(ids)} levels, {int(keep.sum())} kept by the trivial-level filter")
        reference = f" (Kinetix-Offline ~{KINETIX_OFFLINE_SOLVED_SHARE:.0%})" if name == "random" else ""
        budgets = {}
        for budget in sorted(results, key=int):
            per_level = {
                key: np.array([results[budget][level][key] for level in ids]) for key in results[budget][ids[0]]
            }
            counted = sum(summary["levels"] for summary in parts[budget])
            work = sum(summary["seconds_per_level"] * summary["levels"] for summary in parts[budget])
            train = sum(summary["train_seconds_per_level"] * summary["levels"] for summary in parts[budget])
            compile_seconds = max(summary["compile_seconds"] for summary in parts[budget])
            seconds = {"train": train, "window": work - train, "evaluate": 0.0, "compile": compile_seconds}
            summary = summarise(per_level, keep, seconds, len(ids), counted)
            log(_summary_line(f"{name} (merged)", int(budget), summary, reference))
            budgets[budget] = {
                "summary": summary,
                "per_level": {key: value.tolist() for key, value in per_level.items()},
            }
        merged["sets"][name] = {
            "levels": ids,
            "filter_reason": [reasons[level] for level in ids],
            "budgets": budgets,
            "budget_comparisons": compare_budgets(name, ids, budgets, log),
        }
    return merged


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--levels", type=int, default=DEFAULT_RANDOM_LEVELS, help="random levels of split 1M/s")
    parser.add_argument(
        "--first-level",
        type=int,
        default=0,
        help="first random level (measure a range in parts: the same results as one run with the same --batch)",
    )
    parser.add_argument("--budgets", nargs="+", type=int, default=list(DEFAULT_BUDGETS), help="env steps per expert")
    parser.add_argument(
        "--batch", type=int, help="levels per vmapped program (default: the job's work.levels_per_batch)"
    )
    parser.add_argument("--episodes", type=int, default=DEFAULT_EPISODES, help="evaluation episodes per level")
    parser.add_argument("--scale", help="pipeline scale preset applied to the split (e.g. tiny: 8 x 32 PPO updates)")
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="pipeline config overrides")
    parser.add_argument("--sets", nargs="+", default=["random", "hand"], choices=["random", "hand"])
    parser.add_argument("--hand-levels", type=Path, default=HAND_LEVELS_DIR, help="directory of hand-designed levels")
    parser.add_argument(
        "--hand-first",
        type=int,
        default=0,
        help="first hand-designed level in name order (measure the set in parts, like --first-level)",
    )
    parser.add_argument("--hand-count", type=int, help="hand-designed levels from --hand-first (default: the rest)")
    parser.add_argument(
        "--merge",
        nargs="+",
        type=Path,
        metavar="REPORT",
        help="measure nothing: merge --json reports of parts of one measurement and print their summaries",
    )
    parser.add_argument("--json", action="store_true", help="print one JSON document with per-level results")
    args = parser.parse_args(argv)

    def log(line: str) -> None:
        print(line, file=sys.stderr if args.json else sys.stdout, flush=True)

    if args.merge:
        merged = merge_reports([json.loads(path.read_text()) for path in args.merge], log)
        if args.json:
            print(json.dumps(merged, indent=2))
        return

    report = {
        **provenance(),
        "machine": describe_machine(),
        "split_config": f"configs/splits/{SPLIT}.yaml",
        "scale": args.scale,
        "overrides": args.set,
        "batch": args.batch,
        "sets": {},
    }
    job = resolve(load_config(SPLIT_CONFIG, args.set, args.scale))
    report["expert_selection"] = {key: getattr(job.ppo, key) for key in SELECTION_SETTINGS}
    measurement = Measurement(args, job, {}, log)
    if "random" in args.sets:
        ids = list(range(args.first_level, args.first_level + args.levels))
        levels = sample_split_levels(job, args.first_level, args.levels)
        report["sets"]["random"] = measure_set(
            "random s", ids, levels, job.split.seed, args.first_level, measurement, random=True
        )
    if "hand" in args.sets:
        names, levels = load_hand_levels(args.hand_levels, job)
        first, count = hand_range(args.hand_first, args.hand_count, len(names), parser.error)
        names, levels = names[first : first + count], jax.tree.map(lambda x: x[first : first + count], levels)
        report["sets"]["hand"] = measure_set(
            "hand-designed s", names, levels, HAND_LEVELS_SEED, first, measurement, random=False
        )
    if args.json:
        print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
