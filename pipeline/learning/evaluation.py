"""Evaluation of a trained BC policy beside its baselines, on three sets of levels:

- train: the dataset's levels the policy was trained on (`validation`: those it held out), from each level's start
  and from stored states in the middle of the experts' trajectories, with the experts' recorded success beside;
- unseen: levels of the dataset's split that the dataset does not hold (ids from `split.num_levels` on), passed
  through the split's trivial-level filter;
- hand: Kinetix's hand-designed levels of the dataset's size.

Every set is played, on the same levels with the same episode keys, by the BC policy, the no-op policy and the
uniform random policy. An episode is a level's first episode from its start state (no reset): success if green
touched blue, failure if green touched red, timeout otherwise.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from omegaconf import OmegaConf

from kforge.agents import NetworkConfig, make_bc_network, network_actor, run_episode
from kforge.engine import PHYSICS_SCHEMES, PhysicsScheme, physics_scheme
from kforge.env import (
    ActionType,
    EnvParams,
    EnvState,
    StaticEnvParams,
    action_mask,
    filter_levels,
    list_levels,
    load_level,
    noop_action,
    random_action,
    reset,
    under_scheme,
)
from kforge.pipeline.generation import EnvSection, JobConfig, environment, merge_layers, sample_batch, to_schema_object
from kforge.pipeline.learning.checkpoints import checkpoint_steps, restore_checkpoint
from kforge.pipeline.learning.config import LEVEL_SETS, BCConfig, network_config, run_config_file
from kforge.pipeline.learning.data import kept_levels
from kforge.pipeline.learning.train import LEVELS_FILE, Learner
from kforge.pipeline.reading import TrajectoryDatasetManager
from kforge.pipeline.storage import CONFIG_FILE, DatasetError, iter_records, open_dataset

JOB_PHYSICS_SCHEME = EnvSection.physics
"""The scheme a job plays under unless its `env.physics` names another (the schema's default: kinetix)."""

ACTION_TYPE = ActionType.MULTI_DISCRETE

STORED_STARTS_PER_TRAJECTORY = 4
"""Mid-trajectory start states drawn from each stored expert trajectory (states with timestep > 0)."""

UNSEEN_SAMPLE_CHUNK = 64
"""Split levels sampled and filtered at a time while collecting unseen levels."""

EVAL_CHUNK_LEVELS = 64
"""Start states played together in one compiled program (bounds memory)."""


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


@dataclasses.dataclass
class StartSet:
    """Start states of one set of levels, with each level's action mask and env params (leading axis S)."""

    states: EnvState
    masks: jnp.ndarray  # (S, 6) bool
    params: EnvParams  # leaves (S, ...)
    level_ids: list  # (S,) the level of each start (split id, or hand-designed level name)


@functools.partial(jax.jit, static_argnames=("network", "static", "num_episodes", "greedy"))
def _play(
    params, states, masks, env_params, keys, policy_index, network: NetworkConfig | None, static, num_episodes, greedy
):
    """(success, failure) (S, K) bool of K first episodes from each start state, for the policy at `policy_index` of
    (no-op, random, the BC network): one compiled program serves all three."""

    def noop(state, mask, key):
        return noop_action(ACTION_TYPE)

    def uniform(state, mask, key):
        return jnp.where(mask, random_action(key, ACTION_TYPE), 0)

    actors = [noop, uniform]
    if network is not None:
        actors.append(
            network_actor(make_bc_network(network), params, network.architecture.observation_type, static, greedy)
        )

    def act(state, mask, key):
        return jax.lax.switch(policy_index, actors, state, mask, key)

    def level(start, mask, env_params, key):
        episodes = jax.vmap(lambda k: run_episode(act, start, mask, k, env_params, static))(
            jax.random.split(key, num_episodes)
        )
        return episodes.success, episodes.failure

    return jax.vmap(level)(states, masks, env_params, keys)


BASELINE_INDEX = {Baseline.NOOP: 0, Baseline.RANDOM: 1}
POLICY_INDEX = len(BASELINE_INDEX)


def play(
    player: Baseline | None,
    starts: StartSet,
    static: StaticEnvParams,
    num_episodes: int,
    seed: int,
    greedy: bool,
    policy: TrainedPolicy | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(success, failure) (S, K) of a baseline, or of `policy` when `player` is None, from every start; start i's
    episode keys derive from (seed, i) only, so every player plays the same keys."""
    count = len(starts.level_ids)
    keys = jax.vmap(lambda i: jax.random.fold_in(jax.random.key(seed), i))(jnp.arange(count))
    index = POLICY_INDEX if player is None else BASELINE_INDEX[player]
    width = min(EVAL_CHUNK_LEVELS, 1 << (count - 1).bit_length())  # one program shape per set (padded chunks)
    successes, failures = [], []
    for begin in range(0, count, width):
        rows = np.arange(begin, begin + width)
        chunk = np.where(rows < count, rows, begin)  # padding repeats the chunk's first start
        success, failure = _play(
            None if policy is None else policy.params,
            jax.tree.map(lambda x, rows=chunk: x[rows], starts.states),
            starts.masks[chunk],
            jax.tree.map(lambda x, rows=chunk: x[rows], starts.params),
            keys[chunk],
            jnp.int32(index),
            None if policy is None else policy.network,
            static,
            num_episodes,
            greedy,
        )
        real = rows < count
        successes.append(np.asarray(success)[real])
        failures.append(np.asarray(failure)[real])
    return np.concatenate(successes), np.concatenate(failures)


def _broadcast(params: EnvParams, count: int) -> EnvParams:
    return jax.tree.map(lambda x: jnp.broadcast_to(jnp.asarray(x), (count,) + jnp.shape(x)), params)


def dataset_job(dataset: str) -> JobConfig | None:
    """The generation config stored with the dataset (None if it has none: a dataset not made by `kforge run`)."""
    text = open_dataset(dataset).store.read(CONFIG_FILE)
    if text is None:
        return None
    return to_schema_object(
        merge_layers(JobConfig, [(f"{dataset}/{CONFIG_FILE}", OmegaConf.create(text.decode()))]), JobConfig
    )


def dataset_starts(
    dataset: str, level_ids: list[int], env_params: EnvParams, seed: int
) -> tuple[StartSet, StartSet, np.ndarray]:
    """(level starts, mid-trajectory starts, experts' recorded success rate per level) of dataset levels.

    A stored trajectory begins at its level's start (the experts' windows start with a reset); mid-trajectory
    starts are `STORED_STARTS_PER_TRAJECTORY` stored states per trajectory with timestep > 0, drawn with `seed`.
    """
    levels = kept_levels(dataset)
    slots = [levels[level][0] for level in level_ids]
    expert = {
        level.level_id: level.expert_success_rate
        for r in iter_records(open_dataset(dataset).store)
        for level in r.levels
    }
    reader = TrajectoryDatasetManager(dataset, batch_size=1)
    batch = reader.load_slots(np.asarray(slots))
    starts = StartSet(
        jax.tree.map(lambda x: x[:, 0], batch.env_state),
        batch.action_mask[:, 0],
        _broadcast(env_params, len(slots)),
        list(level_ids),
    )
    timestep = np.asarray(batch.env_state.timestep)
    rng = np.random.default_rng(seed)
    rows, columns = [], []
    for row in range(len(slots)):
        candidates = np.flatnonzero(timestep[row] > 0)
        if len(candidates):
            picked = rng.choice(candidates, size=min(STORED_STARTS_PER_TRAJECTORY, len(candidates)), replace=False)
            rows += [row] * len(picked)
            columns += sorted(picked.tolist())
    rows, columns = np.asarray(rows, np.int64), np.asarray(columns, np.int64)
    stored = StartSet(
        jax.tree.map(lambda x: x[rows, columns], batch.env_state),
        batch.action_mask[rows, columns],
        _broadcast(env_params, len(rows)),
        [level_ids[row] for row in rows],
    )
    rates = np.array([np.nan if expert[level] is None else expert[level] for level in level_ids], np.float64)
    return starts, stored, rates


def unseen_starts(job: JobConfig, count: int) -> StartSet:
    """Start states of the first `count` split levels past the dataset's (ids from `split.num_levels` on) that the
    split's filter keeps."""
    env_params, static = environment(job)
    kept_ids, kept_levels_ = [], []
    first = job.split.num_levels
    while len(kept_ids) < count:
        ids = np.arange(first, first + UNSEEN_SAMPLE_CHUNK)
        levels = sample_batch(job, ids)
        keep = np.asarray(filter_levels(levels, env_params, static, noop_steps=job.filter.noop_steps).keep)
        if not job.filter.enabled:
            keep[:] = True
        for row in np.flatnonzero(keep)[: count - len(kept_ids)]:
            kept_ids.append(int(ids[row]))
            kept_levels_.append(jax.tree.map(lambda x, r=row: x[r], levels))
        first += UNSEEN_SAMPLE_CHUNK
    stacked = jax.tree.map(lambda *xs: jnp.stack(xs), *kept_levels_)
    return StartSet(jax.vmap(reset)(stacked), jax.vmap(action_mask)(stacked), _broadcast(env_params, count), kept_ids)


def hand_starts(
    static: StaticEnvParams,
    scheme: PhysicsScheme = PHYSICS_SCHEMES[JOB_PHYSICS_SCHEME],
    max_levels: int | None = None,
) -> StartSet:
    """Start states of the bundled hand-designed Kinetix levels of the dataset's size (the first `max_levels` by
    name), each with its own params under the dataset's physics `scheme` (which `static` was made with)."""
    sizes = {name: under_scheme(scheme, EnvParams(), StaticEnvParams.for_size(name))[1] for name in ("s", "m", "l")}
    size = next((name for name, sized in sizes.items() if sized == static), None)
    if size is None:
        raise DatasetError(f"the dataset's static parameters {static} are none of Kinetix's s, m and l in its scheme")
    names = list_levels(size)[:max_levels]
    loaded = [load_level(name) for name in names]
    stacked = jax.tree.map(lambda *xs: jnp.stack(xs), *(entry.level for entry in loaded))
    own = [under_scheme(scheme, entry.params, static)[0] for entry in loaded]
    params = jax.tree.map(lambda *xs: jnp.stack([jnp.asarray(x) for x in xs]), *own)
    return StartSet(jax.vmap(reset)(stacked), jax.vmap(action_mask)(stacked), params, names)


def _rates(success: np.ndarray, failure: np.ndarray) -> dict:
    """Mean over starts of the per-start rates, with the standard error of the success rate across starts."""
    per_start = success.mean(axis=1)
    return {
        "success": float(per_start.mean()),
        "success_se": float(per_start.std(ddof=1) / np.sqrt(len(per_start))) if len(per_start) > 1 else 0.0,
        "failure": float(failure.mean()),
        "timeout": float(1.0 - success.mean() - failure.mean()),
    }


def _play_all(policy, starts, static, episodes, seed, greedy) -> tuple[dict, dict]:
    """Rates of the BC policy and the baselines on one start set, and the BC policy's per-start success rate."""
    rates, per_start = {}, {}
    for name, player in (("bc", None), ("noop", Baseline.NOOP), ("random", Baseline.RANDOM)):
        success, failure = play(player, starts, static, episodes, seed, greedy, policy)
        rates[name] = _rates(success, failure)
        per_start[name] = success.mean(axis=1)
    return rates, per_start


def play_physics(job: JobConfig | None, static: StaticEnvParams) -> tuple[str, EnvParams]:
    """(scheme name, env params) evaluation plays the dataset's levels under: its job's `env.physics` (Kinetix's play
    unless the job named another), Kinetix's play for data made without a job config."""
    if job is not None:
        return job.env.physics, environment(job)[0]
    default = JOB_PHYSICS_SCHEME
    return default, under_scheme(physics_scheme(default), EnvParams(), static)[0]


def evaluate_policy(
    policy: TrainedPolicy,
    level_sets: tuple[str, ...] = ("train", "unseen", "hand"),
    episodes: int = 16,
    unseen_levels: int = 256,
    greedy: bool = False,
    seed: int = 0,
    max_levels: int | None = None,
    report=None,
) -> dict:
    """The evaluation report (JSON-ready): per set, rates of the BC policy and the baselines from level starts (and
    for dataset levels from stored mid-trajectory states, with the experts' recorded success)."""
    unknown = [name for name in level_sets if name not in LEVEL_SETS]
    if unknown:
        raise ValueError(f"unknown level set {unknown[0]!r}; expected some of {', '.join(LEVEL_SETS)}")
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    dataset = policy.config.dataset
    job = dataset_job(dataset)
    scheme_name, env_params = play_physics(job, policy.static)
    scheme = physics_scheme(scheme_name)
    result = {
        "policy": str(policy.run_dir),
        "physics": scheme_name,
        "step": policy.step,
        "dataset": dataset,
        "episodes": episodes,
        "greedy": greedy,
        "seed": seed,
        "sets": {},
    }
    split_ids = json.loads((policy.run_dir / LEVELS_FILE).read_text())
    for name in level_sets:
        if report is not None:
            report(f"evaluating on {name} levels")
        if name in ("train", "validation"):
            ids = split_ids[name][:max_levels]
            if not ids:
                result["sets"][name] = {"levels": 0}
                continue
            starts, stored, expert = dataset_starts(dataset, ids, env_params, seed)
            from_start, per_start = _play_all(policy, starts, policy.static, episodes, seed, greedy)
            from_stored, _ = _play_all(policy, stored, policy.static, episodes, seed + 1, greedy)
            from_start["expert_recorded"] = {"success": float(np.nanmean(expert))}
            result["sets"][name] = {
                "levels": len(ids),
                "stored_starts": len(stored.level_ids),
                "from_start": from_start,
                "from_stored_states": from_stored,
                "per_level": {str(i): float(s) for i, s in zip(ids, per_start["bc"], strict=True)},
            }
        elif name == "unseen":
            if job is None:
                raise DatasetError(
                    f"{dataset}: no {CONFIG_FILE} (not made by kforge run), so its split's unseen levels are unknown"
                )
            starts = unseen_starts(job, unseen_levels if max_levels is None else min(unseen_levels, max_levels))
            from_start, per_start = _play_all(policy, starts, policy.static, episodes, seed, greedy)
            result["sets"][name] = {
                "levels": len(starts.level_ids),
                "first_level_id": job.split.num_levels,
                "from_start": from_start,
                "per_level": {str(i): float(s) for i, s in zip(starts.level_ids, per_start["bc"], strict=True)},
            }
        else:
            starts = hand_starts(policy.static, scheme, max_levels)
            from_start, per_start = _play_all(policy, starts, policy.static, episodes, seed, greedy)
            result["sets"][name] = {
                "levels": len(starts.level_ids),
                "from_start": from_start,
                "per_level": dict(zip(starts.level_ids, map(float, per_start["bc"]), strict=True)),
            }
    return result


def report_table(result: dict) -> str:
    """The report as a text table: one row per set and start kind, success rates of each policy."""
    header = f"{'levels':<12} {'starts':<18} {'n':>5} {'BC':>12} {'no-op':>7} {'random':>7} {'expert':>7}"
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
            rates = entry[kind]
            bc = f"{rates['bc']['success']:.3f}±{rates['bc']['success_se']:.3f}"
            expert = rates.get("expert_recorded", {}).get("success")
            lines.append(
                f"{name:<12} {kind.replace('_', ' '):<18} {count:>5} {bc:>12} {rates['noop']['success']:>7.3f} "
                f"{rates['random']['success']:>7.3f} {'' if expert is None else f'{expert:.3f}':>7}"
            )
    return "\n".join(lines)
