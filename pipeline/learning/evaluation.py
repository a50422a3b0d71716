"""Evaluation of a trained BC policy beside its baselines, on the sets of `evaluation_sets`:

- train: the dataset's levels the policy was trained on (`validation`: those it held out), from each level's start
  and from stored states in the middle of the experts' trajectories, with the experts' recorded success beside;
- unseen: levels of the dataset's split from the fixed range `UNSEEN_FIRST_LEVEL` on that pass the split's
  trivial-level filter, checked disjoint from every level of the dataset;
- hand: Kinetix's hand-designed levels: all 74 (s, m and l) for the entity transformer, which reads any number of
  entities; those of the dataset's size for the MLP, whose input has the size's width.

Every set is played, on the same levels with the same episode keys, by the BC policy, the no-op policy and the
uniform random policy, under the dataset's physics scheme (Kinetix's unless its job named another). An episode is a
level's first episode from its start state (no reset): success if green touched blue, failure if green touched red,
timeout otherwise. Success is the mean over starts of each start's success rate, with its standard error across
starts; the BC policy's difference to random is paired by start (same start, same keys), with the standard error of
the per-start differences.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import json
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from omegaconf import OmegaConf

from kforge.agents import Architecture, NetworkConfig, make_bc_network, network_actor, run_episode
from kforge.engine import PhysicsScheme, physics_scheme
from kforge.env import (
    ActionType,
    EnvParams,
    EnvState,
    StaticEnvParams,
    list_levels,
    noop_action,
    random_action,
    under_scheme,
)
from kforge.pipeline.generation import JobConfig, ResolvedJob, merge_layers, resolve, to_schema_object
from kforge.pipeline.learning.checkpoints import checkpoint_steps, restore_checkpoint
from kforge.pipeline.learning.config import LEVEL_SETS, BCConfig, network_config, run_config_file
from kforge.pipeline.learning.evaluation_sets import (
    JOB_PHYSICS_SCHEME,
    KINETIX_SIZES,
    UNSEEN_FIRST_LEVEL,
    UNSEEN_LEVELS,
    StartSet,
    check_unseen_disjoint,
    dataset_level_ids,
    dataset_starts,
    level_file_starts,
    scheme_static,
    size_of,
    unseen_starts,
)
from kforge.pipeline.learning.train import LEVELS_FILE, Learner
from kforge.pipeline.storage import CONFIG_FILE, DatasetError, open_dataset

ACTION_TYPE = ActionType.MULTI_DISCRETE

EVAL_CHUNK_LEVELS = 64
"""Start states played together in one compiled program (bounds memory)."""

PLAYERS = ("bc", "noop", "random")
"""Every set's players: the BC policy, then the baselines."""


class Baseline(enum.Enum):
    """Policies every set is also played with."""

    NOOP = "noop"
    RANDOM = "random"


@dataclasses.dataclass(frozen=True)
class TrainedPolicy:
    """A BC run's policy at a checkpoint."""

    run_dir: Path
    config: BCConfig
    network: NetworkConfig
    params: object
    step: int
    static: StaticEnvParams


def load_policy(run_dir: str | Path, step: int | None = None) -> TrainedPolicy:
    """The policy of a BC run directory at its latest checkpoint (or at `step`)."""
    config_file = run_config_file(run_dir)
    run_dir = config_file.parent
    config = to_schema_object(merge_layers(BCConfig, [(str(config_file), OmegaConf.load(config_file))]), BCConfig)
    steps = checkpoint_steps(run_dir)
    if not steps:
        raise FileNotFoundError(f"{run_dir}: no checkpoint yet")
    if step is None:
        step = steps[-1]
    elif step not in steps:
        raise FileNotFoundError(f"{run_dir}: no checkpoint at step {step} (checkpoints: {steps})")
    layout = open_dataset(config.dataset).layout
    static = layout.static
    learner = Learner(config, static, layout.num_steps, devices=jax.local_devices()[:1])
    state = restore_checkpoint(run_dir, step, jax.device_get(learner.init(config.train.seed)))
    return TrainedPolicy(run_dir, config, network_config(config), state.params, step, static)


@dataclasses.dataclass(frozen=True)
class Episodes:
    """How each start of a set is played: `count` first episodes, with keys from `seed`, greedy or sampled actions."""

    count: int
    seed: int
    greedy: bool = False


DEFAULT_EPISODES = Episodes(count=16, seed=0)
"""How `evaluate_policy` plays each start unless told: 16 first episodes [episodes per start], keys from seed 0,
sampled actions."""


class _Chunk(NamedTuple):
    """Start states played together in one compiled program (leading axis S)."""

    states: EnvState
    masks: jnp.ndarray  # (S, 6) bool
    env_params: EnvParams  # leaves (S, ...)
    keys: jnp.ndarray  # (S,) each start's episode key


@dataclasses.dataclass(frozen=True)
class _Program:
    """What a compiled evaluation program is specialised on: the BC network (None for the baselines only), the
    static env params, the episodes per start and greedy or sampled actions."""

    network: NetworkConfig | None
    static: StaticEnvParams
    num_episodes: int
    greedy: bool


def _noop_actor(state, mask, key):
    return noop_action(ACTION_TYPE)


def _uniform_actor(state, mask, key):
    return jnp.where(mask, random_action(key, ACTION_TYPE), 0)


@functools.partial(jax.jit, static_argnames=("program",))
def _play(params, chunk: _Chunk, policy_index, program: _Program):
    """(success, failure) (S, K) bool of K first episodes from each start state, for the policy at `policy_index` of
    (no-op, random, the BC network): one compiled program serves all three."""
    network, static = program.network, program.static
    actors = [_noop_actor, _uniform_actor]
    if network is not None:
        actors.append(
            network_actor(
                make_bc_network(network), params, network.architecture.observation_type, static, program.greedy
            )
        )

    def act(state, mask, key):
        return jax.lax.switch(policy_index, actors, state, mask, key)

    def level(start, mask, env_params, key):
        episodes = jax.vmap(lambda k: run_episode(act, start, mask, k, env_params, static))(
            jax.random.split(key, program.num_episodes)
        )
        return episodes.success, episodes.failure

    return jax.vmap(level)(chunk.states, chunk.masks, chunk.env_params, chunk.keys)


BASELINE_INDEX = {Baseline.NOOP: 0, Baseline.RANDOM: 1}
POLICY_INDEX = len(BASELINE_INDEX)


def play(
    player: Baseline | None,
    starts: StartSet,
    static: StaticEnvParams,
    episodes: Episodes,
    policy: TrainedPolicy | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(success, failure) (S, K) of a baseline, or of `policy` when `player` is None, from every start; start i's
    episode keys derive from (seed, i) only, so every player plays the same keys."""
    count = len(starts.level_ids)
    keys = jax.vmap(lambda i: jax.random.fold_in(jax.random.key(episodes.seed), i))(jnp.arange(count))
    index = POLICY_INDEX if player is None else BASELINE_INDEX[player]
    program = _Program(None if policy is None else policy.network, static, episodes.count, episodes.greedy)
    width = min(EVAL_CHUNK_LEVELS, 1 << (count - 1).bit_length())  # one program shape per set (padded chunks)
    successes, failures = [], []
    for begin in range(0, count, width):
        rows = np.arange(begin, begin + width)
        chunk = np.where(rows < count, rows, begin)  # padding repeats the chunk's first start
        played = _Chunk(
            jax.tree.map(lambda x, rows=chunk: x[rows], starts.states),
            starts.masks[chunk],
            jax.tree.map(lambda x, rows=chunk: x[rows], starts.params),
            keys[chunk],
        )
        success, failure = _play(None if policy is None else policy.params, played, jnp.int32(index), program)
        real = rows < count
        successes.append(np.asarray(success)[real])
        failures.append(np.asarray(failure)[real])
    return np.concatenate(successes), np.concatenate(failures)


def dataset_job(dataset: str) -> ResolvedJob | None:
    """The generation config stored with the dataset, resolved once for every set evaluation plays (None if it has
    none: a dataset not made by `kforge run`)."""
    text = open_dataset(dataset).store.read(CONFIG_FILE)
    if text is None:
        return None
    return resolve(
        to_schema_object(
            merge_layers(JobConfig, [(f"{dataset}/{CONFIG_FILE}", OmegaConf.create(text.decode()))]), JobConfig
        )
    )


Outcomes = dict[str, tuple[np.ndarray, np.ndarray]]
"""Player name -> (success, failure) (S, K) bool of K first episodes from each of S starts."""


def _standard_error(values: np.ndarray) -> float:
    return float(values.std(ddof=1) / np.sqrt(len(values))) if len(values) > 1 else 0.0


def rates(outcomes: Outcomes) -> dict:
    """Per player: success (mean over starts of each start's success rate) with its standard error across starts,
    failure and timeout rates; and `bc_minus_random`, the BC policy's success minus random's paired by start, with
    the standard error of the per-start differences (when the BC policy played)."""
    summary = {}
    for name, (success, failure) in outcomes.items():
        per_start = success.mean(axis=1)
        summary[name] = {
            "success": float(per_start.mean()),
            "success_se": _standard_error(per_start),
            "failure": float(failure.mean()),
            "timeout": float(1.0 - success.mean() - failure.mean()),
        }
    if "bc" in outcomes:
        difference = outcomes["bc"][0].mean(axis=1) - outcomes["random"][0].mean(axis=1)
        summary["bc_minus_random"] = {"difference": float(difference.mean()), "se": _standard_error(difference)}
    return summary


def play_set(
    policy: TrainedPolicy | None, starts: StartSet, static: StaticEnvParams, episodes: int, seed: int, greedy: bool
) -> Outcomes:
    """Outcomes of the BC policy (unless `policy` is None) and both baselines on the same starts with the same keys."""
    players = (("bc", None),) if policy is not None else ()
    players += (("noop", Baseline.NOOP), ("random", Baseline.RANDOM))
    plan = Episodes(episodes, seed, greedy)
    return {name: play(player, starts, static, plan, policy) for name, player in players}


def _concatenate(parts: list[Outcomes]) -> Outcomes:
    return {name: tuple(np.concatenate([part[name][i] for part in parts]) for i in range(2)) for name in parts[0]}


def readable_sizes(policy: TrainedPolicy, scheme: PhysicsScheme) -> tuple[str, ...]:
    """Kinetix sizes the policy's network can read: all of them for the entity transformer, the dataset's own for
    the MLP (its input width is the size's)."""
    if policy.network.architecture is Architecture.TRANSFORMER:
        return KINETIX_SIZES
    return (size_of(policy.static, scheme),)


def level_set_entry(played: dict[str, tuple[list[str], Outcomes]]) -> dict:
    """The set entry of levels played by size (size -> (level names, outcomes)): rates over all levels and per size,
    and each level's success rate of the BC policy (of random when the BC policy did not play)."""
    parts, per_size, per_level = [], {}, {}
    for size, (names, outcomes) in played.items():
        parts.append(outcomes)
        per_size[size] = {"levels": len(names), "from_start": rates(outcomes)}
        first = "bc" if "bc" in outcomes else "random"
        per_level.update(zip(names, map(float, outcomes[first][0].mean(axis=1)), strict=True))
    overall = rates(_concatenate(parts))
    return {"levels": len(per_level), "from_start": overall, "sizes": per_size, "per_level": per_level}


def play_level_files(
    policy: TrainedPolicy | None,
    files: dict[str, list[str]],
    scheme: PhysicsScheme,
    episodes: int,
    seed: int,
    greedy: bool = False,
) -> dict:
    """The set entry (`level_set_entry`) of Kinetix level files (paths or bundled names) by size, each played under
    `scheme` with its own params (the baselines only when `policy` is None)."""
    played = {}
    for size, sources in files.items():
        if sources:
            static = scheme_static(scheme, size)
            starts = level_file_starts(sources, static, scheme)
            played[size] = (list(sources), play_set(policy, starts, static, episodes, seed, greedy))
    return level_set_entry(played)


def play_physics(job: ResolvedJob | None, static: StaticEnvParams) -> tuple[str, EnvParams]:
    """(scheme name, env params) evaluation plays the dataset's levels under: its job's `env.physics` (Kinetix's play
    unless the job named another), Kinetix's play for data made without a job config."""
    if job is not None:
        return job.config.env.physics, job.env_params
    default = JOB_PHYSICS_SCHEME
    return default, under_scheme(physics_scheme(default), EnvParams(), static)[0]


def evaluate_policy(
    policy: TrainedPolicy,
    level_sets: tuple[str, ...] = ("train", "unseen", "hand"),
    episodes: Episodes = DEFAULT_EPISODES,
    unseen_levels: int = UNSEEN_LEVELS,
    max_levels: int | None = None,
    report=None,
) -> dict:
    """The evaluation report (JSON-ready): per set, rates of the BC policy and the baselines from level starts (and
    for dataset levels from stored mid-trajectory states, with the experts' recorded success)."""
    unknown = [name for name in level_sets if name not in LEVEL_SETS]
    if unknown:
        raise ValueError(f"unknown level set {unknown[0]!r}; expected some of {', '.join(LEVEL_SETS)}")
    if episodes.count < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes.count}")
    dataset = policy.config.dataset
    job = dataset_job(dataset)
    scheme_name, env_params = play_physics(job, policy.static)
    scheme = physics_scheme(scheme_name)
    result = {
        "policy": str(policy.run_dir),
        "physics": scheme_name,
        "step": policy.step,
        "dataset": dataset,
        "episodes": episodes.count,
        "greedy": episodes.greedy,
        "seed": episodes.seed,
        "sets": {},
    }
    split_ids = json.loads((policy.run_dir / LEVELS_FILE).read_text())
    for name in level_sets:
        if report is not None:
            report(f"evaluating on {name} levels")
        if name in ("train", "validation"):
            result["sets"][name] = _dataset_set_entry(policy, split_ids[name][:max_levels], env_params, episodes)
        elif name == "unseen":
            count = unseen_levels if max_levels is None else min(unseen_levels, max_levels)
            result["sets"][name] = _unseen_set_entry(policy, job, count, episodes)
        else:
            files = {size: list_levels(size)[:max_levels] for size in readable_sizes(policy, scheme)}
            result["sets"][name] = play_level_files(
                policy, files, scheme, episodes.count, episodes.seed, episodes.greedy
            )
    return result


def _dataset_set_entry(policy: TrainedPolicy, ids: list, env_params: EnvParams, plan: Episodes) -> dict:
    """The set entry of dataset levels `ids`: rates from their starts (beside the experts' recorded success) and
    from stored mid-trajectory states, and each level's success rate of the BC policy."""
    if not ids:
        return {"levels": 0}
    dataset = policy.config.dataset
    starts, stored, expert = dataset_starts(dataset, ids, env_params, plan.seed)
    from_start = play_set(policy, starts, policy.static, plan.count, plan.seed, plan.greedy)
    from_stored = play_set(policy, stored, policy.static, plan.count, plan.seed + 1, plan.greedy)
    return {
        "levels": len(ids),
        "stored_starts": len(stored.level_ids),
        "from_start": rates(from_start) | {"expert_recorded": {"success": float(np.nanmean(expert))}},
        "from_stored_states": rates(from_stored),
        "per_level": {str(i): float(s) for i, s in zip(ids, from_start["bc"][0].mean(axis=1), strict=True)},
    }


def _unseen_set_entry(policy: TrainedPolicy, job: ResolvedJob | None, count: int, plan: Episodes) -> dict:
    """The set entry of `count` unseen levels of the dataset's split, checked disjoint from the dataset's levels."""
    dataset = policy.config.dataset
    if job is None:
        raise DatasetError(
            f"{dataset}: no {CONFIG_FILE} (not made by kforge run), so its split's unseen levels are unknown"
        )
    starts = unseen_starts(job, count)
    check_unseen_disjoint(starts, dataset, dataset_level_ids(dataset))
    outcomes = play_set(policy, starts, policy.static, plan.count, plan.seed, plan.greedy)
    return {
        "levels": len(starts.level_ids),
        "first_level_id": UNSEEN_FIRST_LEVEL,
        "from_start": rates(outcomes),
        "per_level": {str(i): float(s) for i, s in zip(starts.level_ids, outcomes["bc"][0].mean(axis=1), strict=True)},
    }


def report_table(result: dict) -> str:
    """The report as a text table: one row per set and start kind, success rates of each policy."""
    header = (
        f"{'levels':<12} {'starts':<18} {'n':>5} {'BC':>12} {'no-op':>7} {'random':>7} {'BC-random':>14} {'expert':>7}"
    )
    lines = [
        f"policy {result['policy']} at step {result['step']}, {result['episodes']} episodes per start"
        + (", greedy" if result["greedy"] else ""),
        header,
    ]
    for name, entry in result["sets"].items():
        if not entry.get("levels"):
            lines.append(f"{name:<12} {'-':<18} {0:>5}")
            continue
        for kind, count in (("from_start", entry["levels"]), ("from_stored_states", entry.get("stored_starts"))):
            if kind not in entry:
                continue
            played = entry[kind]
            bc = f"{played['bc']['success']:.3f}±{played['bc']['success_se']:.3f}"
            gain = f"{played['bc_minus_random']['difference']:+.3f}±{played['bc_minus_random']['se']:.3f}"
            expert = played.get("expert_recorded", {}).get("success")
            lines.append(
                f"{name:<12} {kind.replace('_', ' '):<18} {count:>5} {bc:>12} {played['noop']['success']:>7.3f} "
                f"{played['random']['success']:>7.3f} {gain:>14} {'' if expert is None else f'{expert:.3f}':>7}"
            )
    return "\n".join(lines)
