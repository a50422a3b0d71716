"""The zarr v3 store of a dataset: one array per stored field, one shard file per level batch, written with tensorstore.

A dataset lives at a local path or an object-store URL (`pipeline.storage.store`); its keys:

    <root>/data/                      zarr v3 group; its attributes hold the `DatasetSpec` (layout, geometry, split)
    <root>/data/<field>/zarr.json     one array per field, shape (num_slots, [num_steps,] *field shape)
    <root>/data/<field>/c/<g>/0/...   the shard file of global level batch g (absent when the batch kept nothing)
    <root>/manifest/                  commit records (`pipeline.storage.manifest`)

Slot s of every array holds one level's trajectory; level batch g owns slots [g L, (g + 1) L) and is exactly one
shard file per array, so every file has one writer, is written once per attempt, and a retry overwrites it.

Per-step state fields are stored as uint32 prediction residuals (`pipeline.storage.state_codec`); `Dataset.write_batch`
and `Dataset.read` encode and decode them, so callers see the state's own dtypes and values.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from collections.abc import Iterable, Mapping, Sequence

import numpy as np
import tensorstore as ts
import zarr
from zarr.codecs import BloscCodec, Crc32cCodec, TransposeCodec

from kforge.pipeline.storage.layout import DONE, VALID, DatasetError, FieldSpec, Layout, check_layout
from kforge.pipeline.storage.state_codec import decode_arrays, encode_arrays, is_coded, stored_dtype
from kforge.pipeline.storage.store import Store, StoreError, open_store

FORMAT_VERSION = 3
"""Version of the on-disk format written by this code; a dataset of another version is refused.

2: per-step state fields stored as prediction residuals (`pipeline.storage.state_codec`).
3: the data definition's physics entry names its scheme and holds every physics parameter and solver setting."""

DATA_DIR = "data"
GROUP_METADATA = f"{DATA_DIR}/zarr.json"
"""Key of the zarr group's metadata; written last when a dataset is created, so its presence means a dataset."""
MANIFEST_DIR = "manifest"
CONFIG_FILE = "config.yaml"
"""The resolved config of the latest run, saved in the dataset directory."""
SPEC_ATTRIBUTE = "kforge_dataset"
"""Key of the `DatasetSpec` in the zarr group's attributes."""

BLOSC_LEVEL = 5
"""zstd level inside Blosc. On coded state, level 5 stores 5 % fewer bytes than level 1 (s expert windows: 34.7 vs
36.6 B per transition) at about 100 MB/s per core, thousands of times a worker's rate of kept data."""

IO_CONCURRENCY = 4
"""Parallel chunk encodes/decodes and file operations of one process's tensorstore context."""


@dataclasses.dataclass(frozen=True)
class Geometry:
    """How slots are grouped: `num_shards` work units of `batches_per_shard` level batches of `levels_per_batch`."""

    num_shards: int
    batches_per_shard: int
    levels_per_batch: int

    def __post_init__(self):
        for name in ("num_shards", "batches_per_shard", "levels_per_batch"):
            if getattr(self, name) < 1:
                raise ValueError(f"Geometry.{name} must be >= 1, got {getattr(self, name)}")

    @property
    def num_batches(self) -> int:
        return self.num_shards * self.batches_per_shard

    @property
    def num_slots(self) -> int:
        return self.num_batches * self.levels_per_batch

    def global_batch(self, shard: int, batch: int) -> int:
        """Index of level batch `batch` of `shard` among all level batches (= its shard file index)."""
        if not 0 <= shard < self.num_shards:
            raise ValueError(f"shard {shard} out of range [0, {self.num_shards})")
        if not 0 <= batch < self.batches_per_shard:
            raise ValueError(f"batch {batch} out of range [0, {self.batches_per_shard})")
        return shard * self.batches_per_shard + batch

    def slots(self, shard: int, batch: int) -> range:
        """Global slots of a level batch; level i of the batch goes to slot start + i."""
        start = self.global_batch(shard, batch) * self.levels_per_batch
        return range(start, start + self.levels_per_batch)


@dataclasses.dataclass(frozen=True)
class DatasetSpec:
    """Everything fixed when a dataset is created; stored in the group attributes and checked on open."""

    layout: Layout
    geometry: Geometry
    split: str
    attributes: Mapping = dataclasses.field(default_factory=dict)  # caller's JSON metadata (config, its hash, versions)

    def to_json(self) -> dict:
        return {
            "format_version": FORMAT_VERSION,
            "layout": self.layout.to_json(),
            "geometry": dataclasses.asdict(self.geometry),
            "split": self.split,
            "attributes": json.loads(json.dumps(dict(self.attributes))),
        }

    @classmethod
    def from_json(cls, data: Mapping, where: str) -> DatasetSpec:
        version = data.get("format_version")
        if version != FORMAT_VERSION:
            raise DatasetError(f"{where}: dataset format version {version}; this code reads version {FORMAT_VERSION}")
        try:
            return cls(
                layout=Layout.from_json(data["layout"]),
                geometry=Geometry(**data["geometry"]),
                split=str(data["split"]),
                attributes=data["attributes"],
            )
        except (KeyError, TypeError, ValueError) as error:
            raise DatasetError(f"{where}: malformed dataset spec ({error!r})") from error


def _array_shape(spec: FieldSpec, layout: Layout, num_slots: int) -> tuple[int, ...]:
    return (num_slots,) + spec.full_shape(layout.num_steps)


def _create_array(group: zarr.Group, spec: FieldSpec, layout: Layout, geometry: Geometry) -> None:
    shape = _array_shape(spec, layout, geometry.num_slots)
    shard = (geometry.levels_per_batch,) + shape[1:]
    if spec.per_step:
        chunk = (1,) + shape[1:]  # one trajectory per chunk: empty slots cost nothing, a read decodes one trajectory
        time_last = (0,) + tuple(range(2, len(shape))) + (1,)  # each feature's time series contiguous
        filters = [TransposeCodec(order=time_last)] if len(shape) > 2 else []
    else:
        chunk, filters = shard, []
    group.create_array(
        spec.name,
        shape=shape,
        chunks=chunk,
        shards=shard,
        dtype=stored_dtype(spec),
        fill_value=0 if is_coded(spec) else spec.fill_value,  # a coded empty slot is all zeros
        filters=filters,
        compressors=[BloscCodec(cname="zstd", clevel=BLOSC_LEVEL, shuffle="shuffle"), Crc32cCodec()],
        dimension_names=("traj",) + (("t",) if spec.per_step else ()) + tuple(f"d{i}" for i in range(len(spec.shape))),
    )


def create_dataset(root: str | os.PathLike | Store, spec: DatasetSpec) -> Dataset:
    """Create the dataset's group and arrays (all slots empty), or open it if it exists with the same spec.

    The zarr metadata is built in memory and written object by object, the group's metadata last: until then
    `open_dataset` sees no dataset, so a crash never leaves a half-created one (a rerun writes the same objects).
    Call it once (e.g. under the job's lease) before workers write.
    """
    store = open_store(root)
    if store.exists(GROUP_METADATA):
        return _open_matching(store, spec)
    buffers = {}
    group = zarr.create_group(
        zarr.storage.MemoryStore(buffers), zarr_format=3, attributes={SPEC_ATTRIBUTE: spec.to_json()}
    )
    for field in spec.layout.fields:
        _create_array(group, field, spec.layout, spec.geometry)
    objects = {key: buffer.to_bytes() for key, buffer in buffers.items()}
    group_metadata = objects.pop("zarr.json")
    for key, value in sorted(objects.items()):
        store.write(f"{DATA_DIR}/{key}", value)
    if store.create_exclusive(GROUP_METADATA, group_metadata) is None:
        return _open_matching(store, spec)  # another process created it first
    return Dataset(store, spec)


def _open_matching(store: Store, spec: DatasetSpec) -> Dataset:
    dataset = open_dataset(store)
    if dataset.spec.to_json() != spec.to_json():
        raise DatasetError(f"{store.location}: a dataset with a different spec already exists there")
    return dataset


def open_dataset(root: str | os.PathLike | Store) -> Dataset:
    """Open an existing dataset (a local path or an `s3://`, `gs://` URL); raise `DatasetError` if it is missing,
    of another format, or its layout differs from the one this code derives for its sizes."""
    try:
        store = open_store(root)
        meta = store.read_json(GROUP_METADATA)
    except StoreError as error:
        raise DatasetError(f"{root}: unreadable dataset metadata ({error})") from error
    if meta is None:
        raise DatasetError(f"{store.location}: not a dataset (no {GROUP_METADATA})")
    try:
        spec_json = meta["attributes"][SPEC_ATTRIBUTE]
    except (KeyError, TypeError) as error:
        raise DatasetError(f"{store.url(GROUP_METADATA)}: unreadable dataset metadata ({error!r})") from error
    spec = DatasetSpec.from_json(spec_json, store.location)
    check_layout(spec.layout, store.location)
    return Dataset(store, spec)


class _Picked:
    """The rows `offsets` of a pending read of a whole shard object, as a future."""

    def __init__(self, future, offsets: np.ndarray):
        self._future, self._offsets = future, offsets

    def result(self) -> np.ndarray:
        return self._future.result()[self._offsets]


def object_digest(store: Store, key: str) -> str | None:
    """sha256 hex digest of an object's bytes, or None if it does not exist."""
    data = store.read(key)
    return None if data is None else hashlib.sha256(data).hexdigest()


def array_digest(array: np.ndarray) -> str:
    """sha256 hex digest of an array's C-order bytes (its decoded content)."""
    return hashlib.sha256(np.ascontiguousarray(array).tobytes()).hexdigest()


class Dataset:
    """An open dataset: its spec and tensorstore handles of its arrays (opened on first use)."""

    def __init__(self, store: Store, spec: DatasetSpec):
        self.store = store
        self.root = store.location
        """Where the dataset lives (a local path or a URL), as given."""
        self.spec = spec
        self._context = ts.Context(
            {
                "data_copy_concurrency": {"limit": IO_CONCURRENCY},
                "file_io_concurrency": {"limit": IO_CONCURRENCY},
            }
        )
        self._arrays: dict[str, ts.TensorStore] = {}

    @property
    def layout(self) -> Layout:
        return self.spec.layout

    @property
    def geometry(self) -> Geometry:
        return self.spec.geometry

    @staticmethod
    def array_prefix(name: str) -> str:
        """Key prefix of field `name`'s array."""
        return f"{DATA_DIR}/{name}/"

    def array(self, name: str) -> ts.TensorStore:
        """The tensorstore handle of field `name` (opened once); its shape and dtype are checked against the layout."""
        if name not in self._arrays:
            self._arrays[name] = self._open_array(name)
        return self._arrays[name]

    def _open_array(self, name: str) -> ts.TensorStore:
        spec = self.layout.field(name)
        try:
            store = ts.open(
                {"driver": "zarr3", "kvstore": self.store.child_spec(self.array_prefix(name))},
                context=self._context,
                open=True,
            ).result()
        except ValueError as error:
            raise DatasetError(f"{self.root}: cannot open array {name}: {error}") from error
        expected = _array_shape(spec, self.layout, self.geometry.num_slots)
        dtype = stored_dtype(spec)
        shape = tuple(store.shape)  # longer than the spec says after an interrupted growth (`grow_dataset`)
        if shape[1:] != expected[1:] or shape[0] < expected[0] or store.dtype.numpy_dtype != np.dtype(dtype):
            raise DatasetError(
                f"{self.root}: array {name} is {store.dtype.numpy_dtype}{tuple(store.shape)}, "
                f"the spec says {dtype}{expected}"
            )
        return store

    def batch_key(self, name: str, global_batch: int) -> str:
        """The key of the shard object of `global_batch` in field `name`'s array."""
        ndim = len(_array_shape(self.layout.field(name), self.layout, 1))
        return self.array_prefix(name) + "/".join(["c", str(global_batch), *(["0"] * (ndim - 1))])

    def write_batch(self, global_batch: int, arrays: Mapping[str, np.ndarray]) -> None:
        """Write whole shard files of one level batch: `arrays[name]` has shape (levels_per_batch, ...) per field.

        Per-step state fields are stored coded (`pipeline.storage.state_codec`), which needs `done` and
        `meta/valid` among `arrays`.
        """
        start = global_batch * self.geometry.levels_per_batch
        stop = start + self.geometry.levels_per_batch
        stored = encode_arrays(self.layout, arrays)
        futures = [self.array(name)[start:stop].write(value) for name, value in stored.items()]
        for future in futures:
            future.result()

    def read(
        self, names: Iterable[str], slots: Sequence[int] | range, whole: Mapping[str, np.ndarray] | None = None
    ) -> dict[str, np.ndarray]:
        """Field name -> values of the given slots, in the given order, shape (len(slots), ...).

        `whole[name]`, a bool per level batch, marks the shard objects of field `name` to read whole (one request)
        and pick the slots from; the others are read slot by slot (one range request per trajectory and object, plus
        the object's index). Every read of the call is issued before any is waited for.
        """
        names = list(names)
        coded = any(is_coded(self.layout.field(name)) for name in names)
        fetch = names + [name for name in (DONE, VALID) if coded and name not in names]
        if isinstance(slots, range) and slots.step == 1:
            pending = {name: [(slice(None), self.array(name)[slots.start : slots.stop].read())] for name in fetch}
        else:
            index = np.asarray(slots, np.int64)
            pending = {name: self._read_parts(name, index, (whole or {}).get(name)) for name in fetch}
        arrays = {}
        for name, parts in pending.items():
            try:
                values = [(rows, future.result()) for rows, future in parts]
            except ValueError as error:  # e.g. "Stored and computed checksum do not match" (crc32c)
                raise DatasetError(f"{self.root}: cannot read {name}: {error}") from error
            if len(values) == 1 and isinstance(values[0][0], slice):
                arrays[name] = values[0][1]
                continue
            first = values[0][1]
            arrays[name] = np.empty((len(slots),) + first.shape[1:], first.dtype)
            for rows, value in values:
                arrays[name][rows] = value
        decoded = decode_arrays(self.layout, arrays, arrays[DONE], arrays[VALID]) if coded else arrays
        return {name: decoded[name] for name in names}

    def _read_parts(self, name: str, index: np.ndarray, whole: np.ndarray | None) -> list:
        """(rows of the result, future of their values) covering `index`: slot by slot, except the level batches
        marked in `whole`, whose shard objects are read whole and the rows picked."""
        array = self.array(name)
        per_batch = self.geometry.levels_per_batch
        batch_of = index // per_batch
        picked = np.zeros(len(index), bool) if whole is None else whole[batch_of]
        parts = []
        if len(index) == 0 or not picked.all():
            rows = np.flatnonzero(~picked)
            parts.append((rows if picked.any() else slice(None), array[index[rows]].read()))
        for batch in np.unique(batch_of[picked]):
            rows = np.flatnonzero(picked & (batch_of == batch))
            offsets = index[rows] - batch * per_batch
            future = array[batch * per_batch : (batch + 1) * per_batch].read()
            parts.append((rows, _Picked(future, offsets)))
        return parts
