"""Commit records: one small JSON file per committed level batch, `manifest/shard-000012/batch-003.json`.

A level batch is committed exactly when its record exists: data files are written first, the record last, by an
atomic rename. The manifest, not any scheduler, is the truth about what a dataset holds.
"""

from __future__ import annotations

import json
import os
import re
import uuid
from collections.abc import Iterator
from pathlib import Path

from pipeline.storage.layout import DatasetError
from pipeline.storage.shard_store import MANIFEST_DIR

RECORD_VERSION = 1
"""Version of the record format written by this code."""

_SHARD_DIR = re.compile(r"shard-(\d{6})")
_RECORD_FILE = re.compile(r"batch-(\d{3,})\.json")
TEMP_MARKER = ".tmp-"
"""Infix of a record being written (`batch-003.json.tmp-<uuid>`); such a file is never a commit."""


def shard_dir(root: str | os.PathLike, shard: int) -> Path:
    return Path(root) / MANIFEST_DIR / f"shard-{shard:06d}"


def shard_name(shard: int) -> str:
    """Stable name of a shard in reports: 'shard-000012'."""
    return f"shard-{shard:06d}"


def record_path(root: str | os.PathLike, shard: int, batch: int) -> Path:
    return shard_dir(root, shard) / f"batch-{batch:03d}.json"


def write_record(root: str | os.PathLike, shard: int, batch: int, record: dict) -> dict:
    """Commit a level batch: write its record to a temporary name, fsync, rename into place (atomic).

    Returns the record as stored (with its version)."""
    path = record_path(root, shard, batch)
    path.parent.mkdir(parents=True, exist_ok=True)
    temp = path.with_name(f"{path.name}{TEMP_MARKER}{uuid.uuid4().hex}")
    record = {"record_version": RECORD_VERSION, **record}
    payload = json.dumps(record, indent=1, sort_keys=True)
    with open(temp, "w") as file:
        file.write(payload)
        file.flush()
        os.fsync(file.fileno())
    os.replace(temp, path)
    directory = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(directory)
    finally:
        os.close(directory)
    return record


def remove_record(root: str | os.PathLike, shard: int, batch: int) -> bool:
    """Uncommit a level batch (before it is rewritten); True if a record existed."""
    try:
        record_path(root, shard, batch).unlink()
    except FileNotFoundError:
        return False
    return True


def read_record(root: str | os.PathLike, shard: int, batch: int) -> dict:
    """The commit record of a level batch; `DatasetError` if it is missing or unreadable."""
    path = record_path(root, shard, batch)
    try:
        record = json.loads(path.read_text())
    except FileNotFoundError as error:
        raise DatasetError(f"{shard_name(shard)} batch {batch}: not committed (no {path.name})") from error
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise DatasetError(f"{shard_name(shard)} batch {batch}: unreadable record {path} ({error})") from error
    if not isinstance(record, dict) or record.get("record_version") != RECORD_VERSION:
        raise DatasetError(f"{shard_name(shard)} batch {batch}: record {path} is not of version {RECORD_VERSION}")
    if record.get("shard") != shard or record.get("batch") != batch:
        raise DatasetError(f"{shard_name(shard)} batch {batch}: record {path} names another batch")
    return record


def committed_batches(root: str | os.PathLike, shard: int) -> list[int]:
    """Sorted level batches of `shard` that have a commit record (resume continues with the others)."""
    directory = shard_dir(root, shard)
    if not directory.is_dir():
        return []
    return sorted(int(match[1]) for path in directory.iterdir() if (match := _RECORD_FILE.fullmatch(path.name)))


def recorded_shards(root: str | os.PathLike) -> list[int]:
    """Sorted shards with a manifest folder (committed or once started)."""
    directory = Path(root) / MANIFEST_DIR
    if not directory.is_dir():
        return []
    return sorted(int(match[1]) for path in directory.iterdir() if (match := _SHARD_DIR.fullmatch(path.name)))


def iter_records(root: str | os.PathLike) -> Iterator[dict]:
    """Every commit record of the dataset, by shard then batch."""
    for shard in recorded_shards(root):
        for batch in committed_batches(root, shard):
            yield read_record(root, shard, batch)


def temp_records(root: str | os.PathLike, shard: int) -> list[Path]:
    """Records of `shard` left half-written by a crash (never commits)."""
    directory = shard_dir(root, shard)
    if not directory.is_dir():
        return []
    return sorted(path for path in directory.iterdir() if TEMP_MARKER in path.name)
