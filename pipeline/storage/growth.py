"""Growing a dataset: more level batches appended to its arrays, every existing commit kept.

A dataset's arrays hold `Geometry.num_slots` slots; growing gives them the slots of a larger geometry (more shards,
the same batches per shard and levels per batch), so slot s still holds the same level. The metadata objects are
rewritten one at a time, each as one write (atomic), arrays first and the group's spec last: an interruption leaves
arrays longer than the spec says, which opens (`Dataset` reads only the spec's slots) and is finished by growing again.
"""

from __future__ import annotations

import json

from kforge.pipeline.storage.layout import DatasetError
from kforge.pipeline.storage.manifest import committed_batches
from kforge.pipeline.storage.repair import withdraw_commit
from kforge.pipeline.storage.shard_store import DATA_DIR, SPEC_ATTRIBUTE, DatasetSpec, open_dataset
from kforge.pipeline.storage.store import Location, Store, open_store


def grow_dataset(root: Location, spec: DatasetSpec, levels: tuple[int, int]) -> list[tuple[int, int]]:
    """Give the dataset at `root` the larger `spec` (same layout, batches per shard and levels per batch; at least as
    many shards; new attributes), its level count growing from `levels[0]` to `levels[1]` (slot s holds level s):
    first the commits of the stored level batches whose padding slots become levels are withdrawn, so that a run
    regenerates them. Returns the (shard, batch) commits withdrawn. Idempotent. `DatasetError` if the spec differs
    in anything else or is smaller."""
    withdrawn = _withdraw_padding_batches(root, open_dataset(root).spec, *levels)
    _grow_arrays(root, spec)
    return withdrawn


def _withdraw_padding_batches(root: Location, stored: DatasetSpec, old_levels: int, new_levels: int):
    """Withdraw the commits of the stored level batches whose padding slots (level ids >= old_levels) become levels."""
    geometry = stored.geometry
    withdrawn = []
    first = old_levels // geometry.levels_per_batch  # the global batch holding level old_levels
    last = min(-(-new_levels // geometry.levels_per_batch), geometry.num_batches)
    for global_batch in range(first, last):
        shard, batch = divmod(global_batch, geometry.batches_per_shard)
        if batch in committed_batches(root, shard) and withdraw_commit(root, shard, batch):
            withdrawn.append((shard, batch))
    return withdrawn


def _grow_arrays(root: Location, spec: DatasetSpec) -> None:
    """Give the dataset's arrays and its group's spec the larger `spec`, arrays first (`grow_dataset`)."""
    store = open_store(root)
    root = store.location
    current = open_dataset(store).spec
    old, new = current.geometry, spec.geometry
    if (old.batches_per_shard, old.levels_per_batch) != (new.batches_per_shard, new.levels_per_batch):
        raise DatasetError(f"{root}: a dataset grows by whole shards only ({old} -> {new})")
    if new.num_shards < old.num_shards:
        raise DatasetError(f"{root}: a dataset cannot shrink ({old.num_shards} -> {new.num_shards} shards)")
    if current.layout.to_json() != spec.layout.to_json() or current.split != spec.split:
        raise DatasetError(f"{root}: growing cannot change the layout or the split")
    for field in spec.layout.fields:
        meta_key = f"{DATA_DIR}/{field.name}/zarr.json"
        meta = _read_json(store, meta_key)
        if meta["shape"][0] < new.num_slots:
            meta["shape"][0] = new.num_slots
            store.write(meta_key, json.dumps(meta, indent=2).encode())
    group_key = f"{DATA_DIR}/zarr.json"
    group = _read_json(store, group_key)
    group["attributes"][SPEC_ATTRIBUTE] = spec.to_json()
    store.write(group_key, json.dumps(group, indent=2).encode())


def _read_json(store: Store, key: str) -> dict:
    try:
        return json.loads(store.read(key))
    except (TypeError, json.JSONDecodeError) as error:
        raise DatasetError(f"{store.url(key)}: unreadable metadata ({error})") from error
