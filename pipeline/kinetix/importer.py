"""Levels and initial states from Kinetix-Offline shards: written by `kforge export` or by Kinetix's own code.

`path` is a split's zarr v2 group (every non-empty shard, in name order, as Kinetix's loader lists them) or one shard
array, at a local path or an `s3://`, `gs://` URL (read through the dataset store layer). The first record of each
trajectory is its initial state (Kinetix-Offline windows start at a reset); it is mapped to our `EnvState` by
`env.kinetix_state`, and its simulator state and task form the trajectory's `Level`.
The size is read from the field shapes (any Kinetix size); frame skip and episode length are Kinetix's. Record fields
other than `env_state/*` are not needed here and extra fields are ignored, as Kinetix's loader ignores them.
"""

from __future__ import annotations

import os
from typing import NamedTuple

import numpy as np

from kforge.env import EnvState, KinetixStateError, Level, StaticEnvParams, state_from_kinetix
from kforge.pipeline.kinetix.zarr_v2 import ARRAY_FILE, GROUP_FILE, RecordArray, array_names
from kforge.pipeline.storage import STATE_PREFIX, DatasetError, StoreError, join, open_store

RECORD_NDIM = 3
"""Kinetix-Offline trajectory shards hold records of shape (trajectories, steps, 1)."""


class KinetixLevels(NamedTuple):
    """The trajectories' start levels and initial states, in shard then row order."""

    levels: Level  # leaves (B, ...): simulator state (empty contact cache) and task of each initial state
    initial_states: EnvState  # leaves (B, ...): the first state of each trajectory
    static: StaticEnvParams  # the size read from the records


def kinetix_shard_paths(path: str | os.PathLike) -> list[str]:
    """The shard arrays at `path`: the path itself if it is one, else the arrays of the group, sorted by name."""
    path = str(path)
    try:
        store = open_store(path)
        is_array, is_group = store.exists(ARRAY_FILE), store.exists(GROUP_FILE)
    except StoreError as error:
        raise DatasetError(str(error)) from error
    if is_array:
        return [path]
    if not is_group:
        raise DatasetError(f"{path}: neither a Kinetix-Offline split (zarr v2 group) nor a shard (zarr v2 array)")
    names = array_names(path)
    if not names:
        raise DatasetError(f"{path}: the group holds no shard arrays")
    return [join(path, name) for name in names]


def _first_step_leaves(shard: str) -> dict[str, np.ndarray] | None:
    """Kinetix state leaf name -> (N, ...) values at the first step of each trajectory; None for an empty shard."""
    array = RecordArray.open(shard)
    if len(array.shape) != RECORD_NDIM or array.shape[2] != 1:
        raise DatasetError(f"{shard}: records of shape {array.shape}, expected (trajectories, steps, 1)")
    if array.shape[0] == 0 or array.shape[1] == 0:
        return None
    prefix = f"{STATE_PREFIX}/"
    names = [name for name in array.dtype.names if name.startswith(prefix)]
    if not names:
        raise DatasetError(f"{shard}: no {prefix}* fields in the records")
    rows = array.chunks[0]
    parts = [array.read(start, start + rows)[:, 0, 0] for start in range(0, array.shape[0], rows)]
    first = np.concatenate(parts)
    return {name.removeprefix(prefix): first[name] for name in names}


def _name(shard: str) -> str:
    """The array name of a shard (the last part of its path or URL)."""
    return os.path.basename(shard.rstrip("/"))


def load_kinetix_levels(path: str | os.PathLike) -> KinetixLevels:
    """Levels and initial states of every trajectory at `path` (module doc); `DatasetError` naming the shard and
    field if a shard is unreadable, lacks a state leaf or does not fit the size of the others."""
    shards = kinetix_shard_paths(path)
    per_shard = {shard: leaves for shard in shards if (leaves := _first_step_leaves(shard)) is not None}
    if not per_shard:
        raise DatasetError(f"{path}: every shard is empty")
    reference, reference_leaves = next(iter(per_shard.items()))
    for shard, leaves in per_shard.items():
        if leaves.keys() != reference_leaves.keys():
            differing = sorted(leaves.keys() ^ reference_leaves.keys())
            raise DatasetError(f"{shard}: state fields {differing} differ from those of {_name(reference)}")
        for name, value in leaves.items():
            if value.shape[1:] != reference_leaves[name].shape[1:]:
                raise DatasetError(
                    f"{shard}: field {STATE_PREFIX}/{name} has shape {value.shape[1:]}, "
                    f"{_name(reference)} has {reference_leaves[name].shape[1:]}"
                )
    leaves = {
        name: np.concatenate([shard_leaves[name] for shard_leaves in per_shard.values()]) for name in reference_leaves
    }
    try:
        states, static = state_from_kinetix(leaves)
    except KinetixStateError as error:
        raise DatasetError(f"{path}: the {STATE_PREFIX}/* fields are not a Kinetix state: {error}") from error
    return KinetixLevels(levels=Level(sim=states.sim, task=states.task), initial_states=states, static=static)
