"""Growing a dataset: more level batches appended to its arrays, every existing commit kept.

A dataset's arrays hold `Geometry.num_slots` slots; growing gives them the slots of a larger geometry (more shards,
the same batches per shard and levels per batch), so slot s still holds the same level. The metadata files are
rewritten one at a time, each atomically, arrays first and the group's spec last: an interruption leaves arrays
longer than the spec says, which opens (`Dataset` reads only the spec's slots) and is finished by growing again.
"""

from __future__ import annotations

import json
import os
import uuid
from pathlib import Path

from pipeline.storage.layout import DatasetError
from pipeline.storage.shard_store import DATA_DIR, SPEC_ATTRIBUTE, DatasetSpec, open_dataset


def grow_dataset(root: str | os.PathLike, spec: DatasetSpec) -> None:
    """Give the dataset at `root` the larger `spec` (same layout, batches per shard and levels per batch; at least as
    many shards; new attributes). Idempotent. `DatasetError` if the spec differs in anything else or is smaller."""
    root = Path(root)
    current = open_dataset(root).spec
    old, new = current.geometry, spec.geometry
    if (old.batches_per_shard, old.levels_per_batch) != (new.batches_per_shard, new.levels_per_batch):
        raise DatasetError(f"{root}: a dataset grows by whole shards only ({old} -> {new})")
    if new.num_shards < old.num_shards:
        raise DatasetError(f"{root}: a dataset cannot shrink ({old.num_shards} -> {new.num_shards} shards)")
    if current.layout.to_json() != spec.layout.to_json() or current.split != spec.split:
        raise DatasetError(f"{root}: growing cannot change the layout or the split")
    for field in spec.layout.fields:
        meta_path = root / DATA_DIR / field.name / "zarr.json"
        meta = _read_json(meta_path)
        if meta["shape"][0] < new.num_slots:
            meta["shape"][0] = new.num_slots
            _replace_json(meta_path, meta)
    group_path = root / DATA_DIR / "zarr.json"
    group = _read_json(group_path)
    group["attributes"][SPEC_ATTRIBUTE] = spec.to_json()
    _replace_json(group_path, group)


def _read_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as error:
        raise DatasetError(f"{path}: unreadable metadata ({error})") from error


def _replace_json(path: Path, value: dict) -> None:
    """Write `value` to a temporary file beside `path`, fsync it and rename it over `path` (atomic)."""
    temp = path.with_name(f"{path.name}.tmp-{uuid.uuid4().hex}")
    with open(temp, "w") as file:
        json.dump(value, file, indent=2)
        file.flush()
        os.fsync(file.fileno())
    os.replace(temp, path)
