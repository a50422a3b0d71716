"""Commit records: one small JSON object per committed level batch, `manifest/shard-000012/batch-003.json`.

A level batch is committed exactly when its record exists: data objects are written first, the record last, as one
object (atomic on every store). The manifest, not any scheduler, is the truth about what a dataset holds.
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterator

from kforge.pipeline.storage.layout import DatasetError
from kforge.pipeline.storage.records import BatchRecord
from kforge.pipeline.storage.shard_store import MANIFEST_DIR
from kforge.pipeline.storage.store import Location, StoreError, open_store

RECORD_VERSION = 1
"""Version of the record format written by this code."""

_RECORD_KEY = re.compile(rf"{MANIFEST_DIR}/shard-(\d{{6}})/batch-(\d{{3,}})\.json")
_SHARD_KEY = re.compile(rf"{MANIFEST_DIR}/shard-(\d{{6}})/")
TEMP_MARKER = ".tmp-"
"""Infix of a record left half-written by older versions of this code (`batch-003.json.tmp-<uuid>`); never a commit."""


def shard_prefix(shard: int) -> str:
    return f"{MANIFEST_DIR}/{shard_name(shard)}/"


def shard_name(shard: int) -> str:
    """Stable name of a shard in reports: 'shard-000012'."""
    return f"shard-{shard:06d}"


def record_key(shard: int, batch: int) -> str:
    """The key of a level batch's commit record below the dataset root."""
    return f"{shard_prefix(shard)}batch-{batch:03d}.json"


def write_record(root: Location, shard: int, batch: int, record: dict | BatchRecord) -> dict:
    """Commit a level batch: write its record (`BatchRecord` or its JSON) as one object. Returns the JSON as stored
    (with its version)."""
    if isinstance(record, BatchRecord):
        record = record.to_json()
    record = {"record_version": RECORD_VERSION, **record}
    open_store(root).write(record_key(shard, batch), json.dumps(record, indent=1, sort_keys=True).encode())
    return record


def commit_record(root: Location, shard: int, batch: int, record: dict | BatchRecord) -> dict | None:
    """Commit a level batch only if it is not committed: its record is created, never written over (a conditional
    create), so a job can never replace another job's commit. Returns the JSON as stored, or None if a record
    exists."""
    if isinstance(record, BatchRecord):
        record = record.to_json()
    record = {"record_version": RECORD_VERSION, **record}
    data = json.dumps(record, indent=1, sort_keys=True).encode()
    return record if open_store(root).create_exclusive(record_key(shard, batch), data) is not None else None


def remove_record(root: Location, shard: int, batch: int) -> bool:
    """Uncommit a level batch; True if a record existed and was removed. The removal is conditional on the record
    read just before (its generation), so a record that another writer replaced meanwhile stays."""
    store = open_store(root)
    key = record_key(shard, batch)
    data, generation = store.read_versioned(key)
    if data is None:
        return False
    return store.replace(key, None, generation) is not None


def record_exists(root: Location, shard: int, batch: int) -> bool:
    return open_store(root).exists(record_key(shard, batch))


def read_record(root: Location, shard: int, batch: int) -> BatchRecord:
    """The commit record of a level batch; `DatasetError` if it is missing or unreadable."""
    return read_record_sized(root, shard, batch)[0]


def read_record_sized(root: Location, shard: int, batch: int) -> tuple[BatchRecord, int]:
    """(the commit record of a level batch, the bytes of its object), from one read."""
    data = _record_bytes(root, shard, batch)
    where = f"{shard_name(shard)} batch {batch}: record {record_key(shard, batch)}"
    return BatchRecord.from_json(_checked_record(root, shard, batch, data), where), len(data)


def read_record_json(root: Location, shard: int, batch: int) -> dict:
    """The commit record of a level batch as stored (JSON), checked only for its version and batch."""
    return _checked_record(root, shard, batch, _record_bytes(root, shard, batch))


def _record_bytes(root: Location, shard: int, batch: int) -> bytes:
    store = open_store(root)
    key = record_key(shard, batch)
    try:
        data = store.read(key)
    except StoreError as error:
        raise DatasetError(f"{shard_name(shard)} batch {batch}: unreadable record ({error})") from error
    if data is None:
        raise DatasetError(f"{shard_name(shard)} batch {batch}: not committed (no {store.url(key)})")
    return data


def _checked_record(root: Location, shard: int, batch: int, data: bytes) -> dict:
    key = record_key(shard, batch)
    try:
        record = json.loads(data)
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        where = f"{open_store(root).url(key)}: not JSON ({error})"
        raise DatasetError(f"{shard_name(shard)} batch {batch}: unreadable record ({where})") from error
    if not isinstance(record, dict) or record.get("record_version") != RECORD_VERSION:
        raise DatasetError(f"{shard_name(shard)} batch {batch}: record {key} is not of version {RECORD_VERSION}")
    if record.get("shard") != shard or record.get("batch") != batch:
        raise DatasetError(f"{shard_name(shard)} batch {batch}: record {key} names another batch")
    return record


def committed_batches(root: Location, shard: int) -> list[int]:
    """Sorted level batches of `shard` that have a commit record (resume continues with the others)."""
    keys = open_store(root).list(shard_prefix(shard))
    return sorted(int(match[2]) for key in keys if (match := _RECORD_KEY.fullmatch(key)))


def all_committed(root: Location) -> dict[int, list[int]]:
    """Shard -> its sorted committed level batches, for every shard with one (one listing of the manifest)."""
    found: dict[int, list[int]] = {}
    for key in open_store(root).list(f"{MANIFEST_DIR}/"):
        if match := _RECORD_KEY.fullmatch(key):
            found.setdefault(int(match[1]), []).append(int(match[2]))
    return {shard: sorted(batches) for shard, batches in sorted(found.items())}


def recorded_shards(root: Location) -> list[int]:
    """Sorted shards with a manifest entry (committed or once started)."""
    keys = open_store(root).list(f"{MANIFEST_DIR}/")
    return sorted({int(match[1]) for key in keys if (match := _SHARD_KEY.match(key))})


def iter_records(root: Location) -> Iterator[BatchRecord]:
    """Every commit record of the dataset, by shard then batch."""
    store = open_store(root)
    for shard, batches in all_committed(store).items():
        for batch in batches:
            yield read_record(store, shard, batch)


def temp_records(root: Location, shard: int) -> list[str]:
    """Keys of records of `shard` left half-written by a crash (never commits)."""
    return [key for key in open_store(root).list(shard_prefix(shard)) if TEMP_MARKER in key]
