"""The start states a policy is evaluated from, one `StartSet` per set of levels:

- a dataset's levels (`dataset_starts`): each level's start and stored states inside the experts' trajectories, with
  the experts' recorded success from the commit records;
- unseen levels (`unseen_starts`): levels of the dataset's split drawn from a fixed index range far past any
  dataset (`UNSEEN_FIRST_LEVEL` on) that pass the split's trivial-level filter: the same levels every time, and
  checked disjoint from the dataset's levels when evaluated (`check_unseen_disjoint`);
- Kinetix level files (`level_file_starts`): the bundled hand-designed levels (`hand_starts`, all of one size), or
  level files written by Kinetix's own sampler, each with its own parameters under the dataset's physics scheme.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from kforge.engine import PHYSICS_SCHEMES, PhysicsScheme
from kforge.env import (
    EnvParams,
    EnvState,
    StaticEnvParams,
    action_mask,
    filter_levels,
    list_levels,
    load_level,
    reset,
    under_scheme,
)
from kforge.pipeline.generation import EnvSection, ResolvedJob, sample_batch
from kforge.pipeline.learning.data import kept_levels
from kforge.pipeline.reading import TrajectoryDatasetManager
from kforge.pipeline.storage import DatasetError, iter_records, open_dataset

JOB_PHYSICS_SCHEME = EnvSection.physics
"""The scheme a job plays under unless its `env.physics` names another (the schema's default: kinetix)."""

KINETIX_SIZES = ("s", "m", "l")
"""Kinetix's env sizes; the hand-designed levels are 10 s, 24 m and 40 l levels."""

UNSEEN_FIRST_LEVEL = 1 << 31
"""[split level index] The first candidate of the unseen set: level 2^31 of the split, then 2^31 + 1, ... A level's
key folds its index in as a uint32, so these are ordinary levels of the split, and no dataset reaches them (it would
need `split.num_levels` > 2^31). Fixed, so the unseen set is the same levels for every dataset of a split whatever
its size."""

UNSEEN_LEVELS = 512
"""Unseen levels evaluated by default."""

UNSEEN_SAMPLE_CHUNK = 64
"""Split levels sampled and filtered at a time while collecting unseen levels."""

STORED_STARTS_PER_TRAJECTORY = 4
"""Mid-trajectory start states drawn from each stored expert trajectory (states with timestep > 0)."""


@dataclasses.dataclass
class StartSet:
    """Start states of one set of levels, with each level's action mask and env params (leading axis S)."""

    states: EnvState
    masks: jnp.ndarray  # (S, 6) bool
    params: EnvParams  # leaves (S, ...)
    level_ids: list  # (S,) the level of each start (split id, or level name / file)


def _broadcast(params: EnvParams, count: int) -> EnvParams:
    return jax.tree.map(lambda x: jnp.broadcast_to(jnp.asarray(x), (count,) + jnp.shape(x)), params)


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


def unseen_starts(resolved: ResolvedJob, count: int = UNSEEN_LEVELS) -> StartSet:
    """Start states of the first `count` split levels from `UNSEEN_FIRST_LEVEL` on that the split's filter keeps."""
    job = resolved.config
    if job.split.num_levels > UNSEEN_FIRST_LEVEL:
        raise DatasetError(
            f"split.num_levels={job.split.num_levels} reaches the unseen levels (ids from {UNSEEN_FIRST_LEVEL} on)"
        )
    env_params, static = resolved.env_params, resolved.static
    kept_ids, kept_levels_ = [], []
    first = UNSEEN_FIRST_LEVEL
    while len(kept_ids) < count:
        ids = np.arange(first, first + UNSEEN_SAMPLE_CHUNK, dtype=np.int64)
        levels = sample_batch(resolved, ids)
        keep = np.asarray(filter_levels(levels, env_params, static, noop_steps=job.filter.noop_steps).keep)
        if not job.filter.enabled:
            keep[:] = True
        for row in np.flatnonzero(keep)[: count - len(kept_ids)]:
            kept_ids.append(int(ids[row]))
            kept_levels_.append(jax.tree.map(lambda x, r=row: x[r], levels))
        first += UNSEEN_SAMPLE_CHUNK
    stacked = jax.tree.map(lambda *xs: jnp.stack(xs), *kept_levels_)
    return StartSet(jax.vmap(reset)(stacked), jax.vmap(action_mask)(stacked), _broadcast(env_params, count), kept_ids)


def dataset_level_ids(dataset: str) -> set[int]:
    """Every split level id the dataset's commit records name, kept or not."""
    return {level.level_id for record in iter_records(open_dataset(dataset).store) for level in record.levels}


def check_unseen_disjoint(unseen: StartSet, dataset: str, dataset_ids: set[int]) -> None:
    """`DatasetError` in one line if any unseen level is one of the dataset's levels."""
    shared = sorted(set(unseen.level_ids) & dataset_ids)
    if shared:
        raise DatasetError(
            f"{dataset}: {len(shared)} unseen levels are dataset levels (first: {shared[0]}); "
            f"the unseen set must be disjoint from every training level"
        )


def scheme_static(scheme: PhysicsScheme, size: str) -> StaticEnvParams:
    """The static parameters of Kinetix size `size` under `scheme`."""
    return under_scheme(scheme, EnvParams(), StaticEnvParams.for_size(size))[1]


def size_of(static: StaticEnvParams, scheme: PhysicsScheme) -> str:
    """Which of Kinetix's sizes `static` is under `scheme`; `DatasetError` if none."""
    size = next((name for name in KINETIX_SIZES if scheme_static(scheme, name) == static), None)
    if size is None:
        raise DatasetError(f"the dataset's static parameters {static} are none of Kinetix's s, m and l in its scheme")
    return size


def level_file_starts(sources: list[str], static: StaticEnvParams, scheme: PhysicsScheme) -> StartSet:
    """Start states of Kinetix level files (paths or bundled names) of the size `static` has under `scheme`, each
    with its own params under `scheme`."""
    loaded = [load_level(source) for source in sources]
    stacked = jax.tree.map(lambda *xs: jnp.stack(xs), *(entry.level for entry in loaded))
    own = [under_scheme(scheme, entry.params, static)[0] for entry in loaded]
    params = jax.tree.map(lambda *xs: jnp.stack([jnp.asarray(x) for x in xs]), *own)
    return StartSet(jax.vmap(reset)(stacked), jax.vmap(action_mask)(stacked), params, list(sources))


def hand_starts(
    static: StaticEnvParams,
    scheme: PhysicsScheme = PHYSICS_SCHEMES[JOB_PHYSICS_SCHEME],
    max_levels: int | None = None,
) -> StartSet:
    """Start states of the bundled hand-designed Kinetix levels of the size `static` has under `scheme` (the first
    `max_levels` by name), each with its own params under `scheme`."""
    return level_file_starts(list_levels(size_of(static, scheme))[:max_levels], static, scheme)
