"""Export a dataset in the Kinetix-Offline layout, readable by kinetix-env 3.0.2's `TrajectoryDatasetManager`.

    <out>/<split>/.zgroup, .zattrs    zarr v2 group of the split; attributes["kforge_export"] describe the export
    <out>/<split>/shard-000000/       one array per shard: structured records of shape (N, T, 1) with the fields
                                      `action`, `action_mask`, `done` and `env_state/<Kinetix leaf>` (82 leaves);
                                      attributes["kforge_export"] hold each row's level_id and level_seed

T is the dataset's window (256 steps in release-style datasets). Every committed, kept trajectory is exported once.
Kinetix's loader shuffles batches of consecutive records, not records, so trajectories are permuted across and within
shards by a permutation drawn from the seed; shards are filled evenly (sizes differ by at most one). The state
fields hold Kinetix's full `EnvState` (`env.kinetix_state`: unkept leaves such as contact manifolds are filled as
Kinetix fills them when it expands a state); per-level fields of our store and the action mask are repeated over
time, as Kinetix stores them. The split's folder is built under a hidden staging name and renamed when complete.
"""

from __future__ import annotations

import dataclasses
import math
import os
import shutil
import uuid
from pathlib import Path, PurePosixPath

import numcodecs
import numpy as np
from tqdm import tqdm

from kforge.env import EnvState, StaticEnvParams, kinetix_leaf_specs, state_to_kinetix
from kforge.pipeline.kinetix.zarr_v2 import RecordArray, create_group
from kforge.pipeline.reading import TrajectoryDatasetManager
from kforge.pipeline.storage import (
    ACTION,
    ACTION_MASK,
    DONE,
    STATE_PREFIX,
    DatasetError,
    Layout,
    is_remote,
    iter_records,
    open_dataset,
    require_intact,
    static_to_json,
)

EXPORT_ATTRIBUTE = "kforge_export"
"""Key of this exporter's metadata in the group's and each shard's zarr attributes (Kinetix ignores attributes)."""

SHARD_NAME = "shard-{:06d}"
"""Array name of shard i: sortable, as Kinetix's loader orders shards by name before its seeded shuffle."""

DEFAULT_TRAJECTORIES_PER_SHARD = 1024
"""About 390 MB raw and 20-30 MB on disk per size-s shard of 256-step trajectories."""

TRAJECTORIES_PER_CHUNK = 16
"""Rows per zarr chunk, (16, T, 1): 6 MB raw at size s and T = 256; Kinetix's loader decodes whole chunks."""

ZSTD_LEVEL = 9
"""Zstd level of every chunk: Kinetix-style records of size-s episodes take about 93 B per transition on disk."""


@dataclasses.dataclass(frozen=True)
class KeptTrajectory:
    """One committed, kept trajectory of the source dataset."""

    slot: int
    level_id: int
    level_seed: int


@dataclasses.dataclass(frozen=True)
class ExportSummary:
    """What an export wrote."""

    group: Path  # the split's zarr v2 group: pass it to Kinetix's TrajectoryDatasetManager
    num_trajectories: int
    shard_sizes: dict[str, int]  # shard (array) name -> trajectories in it
    record_bytes: int  # bytes of one (trajectory, step) record


def record_dtype(layout: Layout) -> np.dtype:
    """Structured dtype of one Kinetix-Offline record of a dataset with this layout.

    Our stored names `action`, `action_mask`, `done` and the `env_state/` prefix are Kinetix's record names.
    """
    action, mask = layout.field(ACTION), layout.field(ACTION_MASK)
    state = [
        (f"{STATE_PREFIX}/{name}", spec.dtype, spec.shape) for name, spec in kinetix_leaf_specs(layout.static).items()
    ]
    return np.dtype([(ACTION, action.dtype, action.shape), (ACTION_MASK, mask.dtype, mask.shape), (DONE, bool), *state])


def kinetix_records(
    dtype: np.dtype,
    action: np.ndarray,
    action_mask: np.ndarray,
    done: np.ndarray,
    states: EnvState,
    static: StaticEnvParams,
) -> np.ndarray:
    """(B, T, 1) records of `dtype` (`record_dtype`) of B trajectories: actions (B, T, ...), action masks (B, T, 6),
    done (B, T) and states with leaves (B, T, ...)."""
    leaves = {f"{STATE_PREFIX}/{name}": value for name, value in state_to_kinetix(states, static).items()}
    columns = {ACTION: action, ACTION_MASK: action_mask, DONE: done, **leaves}
    if set(columns) != set(dtype.names):
        raise ValueError(f"record fields {sorted(set(dtype.names) ^ set(columns))} are not filled or not in the dtype")
    records = np.empty(np.shape(done) + (1,), dtype)
    for name, value in columns.items():
        records[name] = np.asarray(value)[:, :, None]
    return records


def kept_trajectories(root: str | os.PathLike) -> list[KeptTrajectory]:
    """The committed, kept trajectories of a dataset, by slot (from its commit records)."""
    kept = [
        KeptTrajectory(level.slot, level.level_id, level.level_seed)
        for record in iter_records(root)
        for level in record.levels
        if level.kept
    ]
    return sorted(kept, key=lambda trajectory: trajectory.slot)


def shard_plan(num_trajectories: int, trajectories_per_shard: int, seed: int) -> list[np.ndarray]:
    """Indices (into the kept trajectories) of each shard: a seeded permutation cut into even consecutive parts."""
    if trajectories_per_shard < 1:
        raise ValueError(f"trajectories_per_shard must be >= 1, got {trajectories_per_shard}")
    order = np.random.default_rng(seed).permutation(num_trajectories)
    return np.array_split(order, math.ceil(num_trajectories / trajectories_per_shard))


def split_group(out_dir: str | os.PathLike, split: str) -> Path:
    """The split's group folder under `out_dir`; refuses split names that would leave it."""
    parts = PurePosixPath(split).parts
    if not parts or PurePosixPath(split).is_absolute() or any(part in ("..", ".") for part in parts):
        raise DatasetError(f"split name {split!r} is not a relative folder name")
    return Path(out_dir).joinpath(*parts)


class ExportTargetExists(DatasetError):
    """The export's output folder already holds something (nothing is overwritten)."""


def export_kinetix(
    dataset_dir: str | os.PathLike,
    out_dir: str | os.PathLike,
    seed: int = 0,
    trajectories_per_shard: int = DEFAULT_TRAJECTORIES_PER_SHARD,
    show_progress: bool = True,
) -> ExportSummary:
    """Write the dataset's kept trajectories to `<out_dir>/<split>` in the Kinetix-Offline layout (module doc).

    Raises `DatasetError` naming the problem if the dataset is missing or corrupt (`DatasetDamaged` if a committed
    level batch's data files are missing or differ from their recorded sha256: checked before anything is read),
    holds no committed trajectory, or the split's folder already exists and is not empty.
    """
    dataset = open_dataset(dataset_dir)
    require_intact(dataset_dir)
    split = dataset.spec.split
    kept = kept_trajectories(dataset_dir)
    if not kept:
        raise DatasetError(f"{dataset_dir}: no committed trajectories to export")
    group = split_group(out_dir, split)
    if group.exists() and (not group.is_dir() or any(group.iterdir())):
        raise ExportTargetExists(f"{group}: output already exists and is not empty; remove it or choose another output")
    plan = shard_plan(len(kept), trajectories_per_shard, seed)
    source = _ShardSource(
        TrajectoryDatasetManager(dataset_dir, batch_size=1),
        dataset.layout,
        record_dtype(dataset.layout),
        numcodecs.Zstd(level=ZSTD_LEVEL),
    )
    group.parent.mkdir(parents=True, exist_ok=True)
    staging = group.parent / f".{group.name}.partial-{uuid.uuid4().hex}"
    shard_sizes = {}
    try:
        create_group(staging, {EXPORT_ATTRIBUTE: _export_attributes(dataset, dataset_dir, seed, len(kept))})
        with tqdm(total=len(kept), unit="traj", desc=f"export {split}", disable=not show_progress) as bar:
            for index, rows in enumerate(plan):
                name = SHARD_NAME.format(index)
                chosen = [kept[row] for row in rows]
                _write_shard(staging / name, chosen, source, bar)
                shard_sizes[name] = len(chosen)
        os.rename(staging, group)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return ExportSummary(group, len(kept), shard_sizes, source.dtype.itemsize)


def _export_attributes(dataset, dataset_dir: str | os.PathLike, seed: int, num_trajectories: int) -> dict:
    """What the split's group attributes say of the export: its format, source dataset, seed and layout."""
    layout = dataset.layout
    return {
        "format": "Kinetix-Offline trajectories (kinetix-env 3.0.2 TrajectoryDatasetManager)",
        "source": str(dataset_dir) if is_remote(dataset_dir) else str(Path(dataset_dir).resolve()),
        "split": dataset.spec.split,
        "data_fingerprint": dataset.spec.attributes.get("data_fingerprint"),
        "seed": seed,
        "num_trajectories": num_trajectories,
        "num_steps": layout.num_steps,
        "action_type": layout.action_type.value,
        "static_env_params": static_to_json(layout.static),
    }


@dataclasses.dataclass(frozen=True)
class _ShardSource:
    """Where an export's shards read their trajectories, and how they encode them."""

    reader: TrajectoryDatasetManager  # the source dataset's loader
    layout: Layout
    dtype: np.dtype  # the Kinetix record (`record_dtype`)
    compressor: numcodecs.abc.Codec


def _write_shard(path: Path, chosen: list[KeptTrajectory], source: _ShardSource, bar: tqdm) -> None:
    """Write the `chosen` trajectories, in order, as the shard array at `path`, chunk by chunk."""
    layout, dtype = source.layout, source.dtype
    ids = {"level_id": [t.level_id for t in chosen], "level_seed": [t.level_seed for t in chosen]}
    array = RecordArray.create(
        path,
        (len(chosen), layout.num_steps, 1),
        TRAJECTORIES_PER_CHUNK,
        dtype,
        source.compressor,
        {EXPORT_ATTRIBUTE: ids},
    )
    for chunk, start in enumerate(range(0, len(chosen), TRAJECTORIES_PER_CHUNK)):
        part = chosen[start : start + TRAJECTORIES_PER_CHUNK]
        batch = source.reader.load_slots(np.array([t.slot for t in part], np.int64))
        records = kinetix_records(dtype, batch.action, batch.action_mask, batch.done, batch.env_state, layout.static)
        array.write_chunk(chunk, records)
        bar.update(len(part))
