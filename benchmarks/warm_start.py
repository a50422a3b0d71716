"""Warm start: PPO fine-tuned from a behaviour-cloning policy against PPO from fresh parameters of the same network,
on unseen levels that pass the split's filter, paired by level (the same levels, the same training randomness).

The BC policy is an MLP over flat observations trained on the dataset (the PPO actor reads flat observations; the
critic is the experts' tanh MLP). Both arms train `--steps` env steps per level with the split's PPO settings and
are evaluated from each level's start before training and at every expert-selection point. The report gives the
success curves (mean and standard error across levels), the from-scratch run's final success, and the env steps
each arm needs to reach it (on the mean curve, and level by level).

Run it alone or as a stage of benchmarks/bc.py (`--warm-start-levels`):

    python -m benchmarks.warm_start --dataset DATASET --bc-run BC_RUN_DIR --levels 32 --steps 1000000 \\
        --json benchmarks/results/warm_start.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks.machine import describe_machine, provenance
from benchmarks.stages import stage
from kforge.agents import EpisodePlan, evaluate, initial_params, train_levels, with_bc_actor
from kforge.pipeline.generation import sample_batch
from kforge.pipeline.learning import load_policy
from kforge.pipeline.learning.evaluation import dataset_job
from kforge.pipeline.learning.evaluation_sets import check_unseen_disjoint, dataset_level_ids, unseen_starts

WARM_START_SEED = 0x3A53
"""Seed of the per-level training keys (folded with the level's split id): both arms of a level use the same key."""

LEVELS_PER_PROGRAM = 8
"""Levels trained together in one vmapped program."""


def _standard_error(values: np.ndarray) -> float:
    return float(np.std(values, ddof=1) / math.sqrt(len(values))) if len(values) > 1 else 0.0


def first_reaching(env_steps: np.ndarray, success: np.ndarray, target: float) -> int | None:
    """The env steps of the first point of a curve at or above `target` (None if it never gets there)."""
    reached = np.flatnonzero(success >= target)
    return int(env_steps[reached[0]]) if reached.size else None


def steps_to_reach(env_steps: np.ndarray, warm: np.ndarray, scratch: np.ndarray) -> dict:
    """From two success curves (levels x points, same points): the scratch run's final mean success, and the steps
    each arm's mean curve needs to reach it; level by level, the steps each arm needs to reach that level's own
    scratch-final success (levels whose scratch run ends at success 0 are left out; levels it solves from the start
    count as informative only if the scratch run needed steps to get there)."""
    target = float(np.mean(scratch[:, -1]))
    per_level = []
    for level_warm, level_scratch in zip(warm, scratch, strict=True):
        if level_scratch[-1] > 0:
            per_level.append(
                {
                    "target": float(level_scratch[-1]),
                    "warm": first_reaching(env_steps, level_warm, level_scratch[-1]),
                    "scratch": first_reaching(env_steps, level_scratch, level_scratch[-1]),
                }
            )
    informative = [row for row in per_level if row["scratch"] > 0]
    halved = [row for row in informative if row["warm"] is not None and row["warm"] * 2 <= row["scratch"]]
    return {
        "scratch_final_success": target,
        "warm_steps_to_scratch_final": first_reaching(env_steps, warm.mean(axis=0), target),
        "scratch_steps_to_own_final": first_reaching(env_steps, scratch.mean(axis=0), target),
        "levels_with_scratch_success": len(per_level),
        "levels_scratch_needed_steps": len(informative),
        "levels_warm_within_half_the_steps": len(halved),
        "per_level": per_level,
    }


def _curve(env_steps: np.ndarray, success: np.ndarray) -> list[dict]:
    return [
        {"env_steps": int(steps), "success": float(np.mean(column)), "standard_error": _standard_error(column)}
        for steps, column in zip(env_steps, success.T, strict=True)
    ]


def _train_arm(levels, level_keys, config, job, start_params) -> tuple[np.ndarray, np.ndarray]:
    """(env steps of each evaluation point with 0 first, success (L, points)) of PPO from `start_params`."""
    plan = EpisodePlan(config, job.static, num_episodes=config.select_episodes, greedy=config.select_greedy)
    start = evaluate(start_params, levels, level_keys, plan, job.env_params)
    trained = train_levels(levels, level_keys, config, job.env_params, job.static, start_params)
    env_steps = np.concatenate([[0], np.asarray(trained.selection.env_steps)[0]])
    success = np.concatenate(
        [np.asarray(start.success_rate)[:, None], np.asarray(trained.selection.success_rate)], axis=1
    )
    return env_steps, success


def _train_pair(job, config, bc_params, level_ids: np.ndarray, log) -> dict:
    """Both arms on the levels `level_ids` of the split, trained together: env steps of the points and success per
    arm (levels x points)."""
    levels = sample_batch(job, level_ids)
    level_keys = jnp.stack([jax.random.fold_in(jax.random.PRNGKey(WARM_START_SEED), int(i)) for i in level_ids])
    init_keys = jax.vmap(jax.random.split)(level_keys)[:, 0]  # the keys train_levels draws fresh parameters from
    fresh = jax.lax.map(lambda key: initial_params(key, config, job.static), init_keys)
    warm = jax.vmap(lambda params: with_bc_actor(params, bc_params))(fresh)
    result = {}
    for arm, start_params in (("warm", warm), ("scratch", fresh)):
        points, success = _train_arm(levels, level_keys, config, job, start_params)
        result |= {"env_steps": points.tolist(), arm: success.tolist()}
        log(f"warm start: levels {level_ids.tolist()} {arm}: mean success by point {np.round(success.mean(0), 3)}")
    return result


def warm_start(
    dataset: str,
    bc_run: str | Path,
    num_levels: int,
    env_steps: int,
    work_dir: Path,
    log,
    part: tuple[int, int] = (0, 1),
) -> dict | None:
    """Both arms on the first `num_levels` unseen filter-kept levels of the dataset's split, from the BC policy of
    `bc_run` (an MLP over flat observations); returns the settings, curves and steps-to-reach figures. Each program
    of levels keeps its curves in `work_dir` once done, so an interrupted run resumes at the program it stopped in.
    `part` (k, n) trains only every n-th program from the k-th (processes that share `work_dir` split the work) and
    then returns None: a run without `part` reads every program's results and reports them."""
    policy = load_policy(bc_run)
    job = dataset_job(dataset)
    if job is None:
        raise ValueError(f"{dataset}: no generation config stored; warm start needs the split's levels and PPO")
    config = dataclasses.replace(job.ppo, env_steps_per_level=env_steps, actor=policy.network)
    unseen = unseen_starts(job, num_levels)
    check_unseen_disjoint(unseen, dataset, dataset_level_ids(dataset))
    ids = np.asarray(unseen.level_ids, np.int64)
    settings = {"bc_run": Path(bc_run).name, "bc_step": policy.step, "env_steps": env_steps, "seed": WARM_START_SEED}
    rows = {"warm": [], "scratch": []}
    for index, first in enumerate(range(0, len(ids), LEVELS_PER_PROGRAM)):
        batch_ids = ids[first : first + LEVELS_PER_PROGRAM]
        name = f"warm-start-{first}-{first + len(batch_ids) - 1}"
        if index % part[1] != part[0]:
            continue
        done = stage(
            work_dir,
            name,
            settings | {"levels": batch_ids.tolist()},
            lambda batch_ids=batch_ids: _train_pair(job, config, policy.params, batch_ids, log),
            log,
        )
        points = np.asarray(done["env_steps"])
        for arm in rows:
            rows[arm].append(np.asarray(done[arm]))
    if part != (0, 1):  # a later run without --part reads every program's stage and reports
        return None
    warm_success, scratch_success = np.concatenate(rows["warm"]), np.concatenate(rows["scratch"])
    return {
        "bc_run": Path(bc_run).name,
        "bc_network": {k: getattr(v, "value", v) for k, v in dataclasses.asdict(policy.network).items()},
        "bc_step": policy.step,
        "levels": ids.tolist(),
        "env_steps_per_level": env_steps,
        "episodes_per_point": config.select_episodes,
        "seed": WARM_START_SEED,
        "curves": {"warm": _curve(points, warm_success), "scratch": _curve(points, scratch_success)},
        "paired_difference": _curve(points, warm_success - scratch_success),
        "reach": steps_to_reach(points, warm_success, scratch_success),
    }


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", required=True, help="a dataset made by kforge run (its split and PPO settings)")
    parser.add_argument("--bc-run", required=True, help="a BC run directory whose network is an MLP")
    parser.add_argument("--levels", type=int, default=32, help="unseen filter-kept levels, paired")
    parser.add_argument("--steps", type=int, default=1_000_000, help="env steps per level and arm")
    parser.add_argument("--work-dir", type=Path, default=Path("outputs/benchmarks/warm-start"), help="stage results")
    parser.add_argument("--json", type=Path, help="write the report here")
    parser.add_argument("--part", default="0/1", help="k/n: train every n-th program of levels from the k-th")
    args = parser.parse_args(argv)
    part = tuple(int(x) for x in args.part.split("/"))

    def log(line: str) -> None:
        print(line, file=sys.stderr, flush=True)

    result = warm_start(args.dataset, args.bc_run, args.levels, args.steps, args.work_dir, log, part)
    if result is None:
        log(f"part {args.part} done; run without --part to report")
        return
    names = {str(args.dataset): "DATASET", str(args.bc_run): "BC_RUN_DIR", str(args.work_dir): "WORK_DIR"}
    command = [names.get(a, a) for a in sys.argv]
    report = provenance(command) | {"machine": describe_machine(), "warm_start": result}
    print(json.dumps(result["reach"] | {"per_level": len(result["reach"]["per_level"])}, indent=1))
    if args.json:
        args.json.write_text(json.dumps(report, indent=1) + "\n")


if __name__ == "__main__":
    main()
