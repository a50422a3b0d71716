"""Where a dataset lives: a local folder, `s3://bucket/prefix` or `gs://bucket/prefix`, as one small key-value layer.

Every read and write of a dataset goes through a `Store` (a tensorstore kvstore rooted at the dataset): whole-object
reads and writes, deletes, listings by prefix and a conditional create. Nothing relies on rename, fsync or directory
listings: a write replaces one object atomically (tensorstore's `file` driver writes a lock file and renames it over
the key; S3 and GCS replace objects atomically), so a commit is one object written after the data it names.

Credentials and endpoints come from the environment only (`AWS_ACCESS_KEY_ID`, `AWS_SECRET_ACCESS_KEY`,
`AWS_SESSION_TOKEN`, `AWS_REGION`, `AWS_ENDPOINT_URL` for an S3-compatible server; Google's application default
credentials for GCS). They are read when a store is opened and never written anywhere.
"""

from __future__ import annotations

import functools
import json
import os
from pathlib import Path

import tensorstore as ts

S3_SCHEME = "s3://"
GCS_SCHEME = "gs://"
ENDPOINT_ENV = "AWS_ENDPOINT_URL"
"""An S3-compatible server's URL (e.g. a MinIO or moto server); unset: AWS itself."""
REGION_ENVS = ("AWS_REGION", "AWS_DEFAULT_REGION")
DEFAULT_REGION = "us-east-1"
"""Region signed into requests to an `AWS_ENDPOINT_URL` server when no region is set (such servers ignore it)."""
LOCAL_PARTIAL_SUFFIX = ".__lock"
"""Suffix of the file tensorstore's `file` driver writes before renaming it over the key; left only by a crash."""

_NO_VALUE = b"\x02"
"""tensorstore's storage generation of a missing key: a write conditioned on it creates the key only if absent."""


class StoreError(ValueError):
    """A location that is not a dataset store (bad URL), or an I/O failure, named with the location."""


def is_remote(location: str | os.PathLike) -> bool:
    """True for an object-store URL (`s3://`, `gs://`)."""
    return str(location).startswith((S3_SCHEME, GCS_SCHEME))


def join(location: str | os.PathLike, *parts: str) -> str:
    """A location below `location` (a URL or a local path), as a string."""
    if is_remote(location):
        return "/".join([str(location).rstrip("/"), *(part.strip("/") for part in parts)])
    return str(Path(location).joinpath(*parts))


def kvstore_spec(location: str | os.PathLike) -> dict:
    """The tensorstore kvstore spec of a location (ends in "/": keys are appended to it); credentials stay out."""
    text = str(location)
    for scheme, driver in ((S3_SCHEME, "s3"), (GCS_SCHEME, "gcs")):
        if text.startswith(scheme):
            bucket, _, prefix = text.removeprefix(scheme).partition("/")
            if not bucket:
                raise StoreError(f"{text}: no bucket in the URL (expected {scheme}bucket/prefix)")
            prefix = prefix.strip("/")
            spec = {"driver": driver, "bucket": bucket, "path": f"{prefix}/" if prefix else ""}
            if driver == "s3":
                endpoint = os.environ.get(ENDPOINT_ENV)
                region = next((os.environ[name] for name in REGION_ENVS if os.environ.get(name)), None)
                if endpoint:
                    spec["endpoint"] = endpoint
                    spec["aws_region"] = region or DEFAULT_REGION
                elif region:
                    spec["aws_region"] = region
            return spec
    if "://" in text:
        raise StoreError(
            f"{text}: unsupported URL scheme (use a local path, {S3_SCHEME}bucket/prefix or {GCS_SCHEME}...)"
        )
    return {"driver": "file", "path": os.path.abspath(text) + "/"}


class Store:
    """Objects below one location, by key ("manifest/shard-000000/batch-000.json"): read, write, delete, list, and
    `create_exclusive` (atomic on a local filesystem, S3 and GCS: see `create_exclusive`)."""

    def __init__(self, location: str | os.PathLike):
        self.location = str(location)
        self.spec = kvstore_spec(location)
        try:
            self._kv = ts.KvStore.open(self.spec).result()
        except ValueError as error:
            raise StoreError(f"{self.location}: cannot open ({error})") from error

    def __repr__(self) -> str:
        return f"Store({self.location!r})"

    @property
    def is_local(self) -> bool:
        return self.spec["driver"] == "file"

    def url(self, key: str = "") -> str:
        """Where `key` lives, for messages."""
        return join(self.location, key) if key else self.location

    def child_spec(self, prefix: str) -> dict:
        """The kvstore spec of the keys below `prefix` (for a zarr array opened by tensorstore)."""
        return {**self.spec, "path": self.spec["path"] + prefix.strip("/") + "/"}

    def _call(self, what: str, key: str, future):
        try:
            return future.result()
        except ValueError as error:
            raise StoreError(f"{self.url(key)}: {what} failed ({error})") from error

    def read(self, key: str) -> bytes | None:
        """The object's bytes, or None if there is none."""
        result = self._call("read", key, self._kv.read(key))
        return result.value if result.state == "value" else None

    def read_versioned(self, key: str) -> tuple[bytes | None, bytes]:
        """(bytes or None, generation): the generation conditions a later `replace`."""
        result = self._call("read", key, self._kv.read(key))
        return (result.value if result.state == "value" else None), result.stamp.generation

    def exists(self, key: str) -> bool:
        return self.read(key) is not None

    def write(self, key: str, value: bytes) -> None:
        """Create or replace an object (atomically: a reader sees the old or the new bytes)."""
        self._call("write", key, self._kv.write(key, value))

    def create_exclusive(self, key: str, value: bytes) -> bytes | None:
        """Create an object only if none exists; its generation, or None if one exists.

        Atomic where the store checks the condition itself: a local filesystem (tensorstore's lock file), S3 and
        S3-compatible servers that honour `If-None-Match: *` (AWS since 2024, moto, MinIO), GCS (generation
        match 0). A server that ignores the header lets two racing creators both succeed; `owns` then tells the
        loser once the winner's write is visible (a read-back after the create).
        """
        generation = self._call("create", key, self._kv.write(key, value, if_equal=_NO_VALUE)).generation
        return generation or None

    def replace(self, key: str, value: bytes | None, generation: bytes) -> bytes | None:
        """Write (or delete, with None) an object only if it is still at `generation`; the new generation, or None
        if it changed meanwhile (someone else wrote it)."""
        stamp = self._call("write", key, self._kv.write(key, value, if_equal=generation))
        return stamp.generation or None

    def delete(self, key: str) -> None:
        """Remove an object (nothing happens if there is none)."""
        self._call("delete", key, self._kv.write(key, None))

    def list(self, prefix: str = "") -> list[str]:
        """Sorted keys that start with `prefix` (all of them below it, at any depth)."""
        key_range = ts.KvStore.KeyRange(inclusive_min=prefix, exclusive_max=_successor(prefix)) if prefix else None
        keys = self._call("list", prefix, self._kv.list(key_range))
        return sorted(key.decode() for key in keys)

    def size(self, key: str) -> int:
        """Bytes of an object (0 if there is none)."""
        if self.is_local:
            try:
                return os.stat(self.spec["path"] + key).st_size
            except FileNotFoundError:
                return 0
        return len(self.read(key) or b"")

    def partial_writes(self, key: str) -> list[str]:
        """Keys of half-done writes of `key` that a crash left behind (local lock files; an object store has none:
        its writes are all or nothing)."""
        if not self.is_local:
            return []
        folder, _, name = key.rpartition("/")
        try:
            names = os.listdir(self.spec["path"] + folder)
        except (FileNotFoundError, NotADirectoryError):
            return []
        return sorted(f"{folder}/{found}" for found in names if found.startswith(name + LOCAL_PARTIAL_SUFFIX))

    def delete_partial(self, key: str) -> None:
        """Remove a key named by `partial_writes`."""
        if self.is_local:
            try:
                os.remove(self.spec["path"] + key)
            except FileNotFoundError:
                pass

    def read_json(self, key: str):
        """The JSON value of an object, or None if there is none; `StoreError` naming it if it is not JSON."""
        data = self.read(key)
        if data is None:
            return None
        try:
            return json.loads(data)
        except (json.JSONDecodeError, UnicodeDecodeError) as error:
            raise StoreError(f"{self.url(key)}: not JSON ({error})") from error


def _successor(prefix: str) -> str:
    """The smallest string after every string that starts with `prefix`."""
    return prefix[:-1] + chr(ord(prefix[-1]) + 1)


@functools.lru_cache(maxsize=64)
def _cached_store(location: str, spec_json: str) -> Store:
    return Store(location)


Location = str | os.PathLike | Store
"""Where a dataset is: a local path, an s3:// or gs:// URL, or an open `Store`."""


def open_store(location: str | os.PathLike | Store) -> Store:
    """The store of a location (a local path or an `s3://`, `gs://` URL); stores are reused per location and
    environment."""
    if isinstance(location, Store):
        return location
    return _cached_store(str(location), json.dumps(kvstore_spec(location), sort_keys=True))
