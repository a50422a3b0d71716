"""Zarr v2 groups of structured-record arrays (the Kinetix-Offline on-disk format), read and written with numcodecs.

zarr 3.1.6 cannot hold structured dtypes with sub-array fields in zarr v2 metadata: it writes a (6,) int32 field as
`|V24` and refuses to open such arrays written by zarr 2.18; tensorstore's zarr driver rejects the zstd metadata
zarr 2.18 writes (its `checksum` member). This module implements the part of the zarr v2 spec such arrays need
(https://zarr-specs.readthedocs.io/en/latest/v2/v2.0.html):

    <group>/.zgroup             {"zarr_format": 2}
    <group>/.zattrs             JSON attributes (optional)
    <group>/<name>/.zarray      shape, chunks, dtype (numpy `descr`), compressor, filters, fill_value, order, separator
    <group>/<name>/.zattrs      JSON attributes (optional)
    <group>/<name>/<i>.<j>...   one file per chunk: the whole chunk (edge chunks padded), filters then compressor

Reading accepts any chunk grid, order, separator and numcodecs codec; writing chunks the first axis only. A group
or array is named by a local path or an `s3://`, `gs://` URL; every file is read and written through the dataset
store layer (`pipeline.storage.open_store`).
"""

from __future__ import annotations

import base64
import dataclasses
import itertools
import json
import math
import os
from collections.abc import Mapping

import numcodecs
import numpy as np

from kforge.pipeline.storage import DatasetError, StoreError, join, open_store

ZARR_FORMAT = 2
GROUP_FILE = ".zgroup"
ARRAY_FILE = ".zarray"
ATTRIBUTES_FILE = ".zattrs"
DEFAULT_SEPARATOR = "."
"""Chunk key separator when `.zarray` has no `dimension_separator` (zarr 2 before 2.8)."""


def _write_json(location: str, key: str, value: Mapping) -> None:
    open_store(location).write(key, json.dumps(value, indent=1).encode())


def _read_bytes(location: str, key: str) -> bytes | None:
    try:
        return open_store(location).read(key)
    except StoreError as error:
        raise DatasetError(str(error)) from error


def _read_json(location: str, key: str) -> dict:
    data = _read_bytes(location, key)
    if data is None:
        raise DatasetError(f"{location}: not a zarr v2 node (no {key})")
    try:
        value = json.loads(data)
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise DatasetError(f"{join(location, key)}: unreadable JSON ({error})") from error
    if not isinstance(value, dict):
        raise DatasetError(f"{join(location, key)}: expected a JSON object, got {type(value).__name__}")
    return value


def create_group(location: str | os.PathLike, attributes: Mapping | None = None) -> None:
    """Make `location` (a folder is created if needed) a zarr v2 group with the given attributes."""
    location = str(location)
    if attributes is not None:
        _write_json(location, ATTRIBUTES_FILE, attributes)
    _write_json(location, GROUP_FILE, {"zarr_format": ZARR_FORMAT})


def read_attributes(location: str | os.PathLike) -> dict:
    """The attributes of a group or array ({} if it has none)."""
    location = str(location)
    return _read_json(location, ATTRIBUTES_FILE) if _read_bytes(location, ATTRIBUTES_FILE) is not None else {}


def array_names(group: str | os.PathLike) -> list[str]:
    """Sorted names of the arrays directly in a zarr v2 group (zarr's `array_keys()`)."""
    group = str(group)
    meta = _read_json(group, GROUP_FILE)
    if meta.get("zarr_format") != ZARR_FORMAT:
        raise DatasetError(f"{group}: zarr_format {meta.get('zarr_format')!r}, expected {ZARR_FORMAT}")
    try:
        keys = open_store(group).list()
    except StoreError as error:
        raise DatasetError(str(error)) from error
    return sorted(key.split("/")[0] for key in keys if key.count("/") == 1 and key.endswith(f"/{ARRAY_FILE}"))


def dtype_to_json(dtype: np.dtype) -> list:
    """Zarr v2 form of a structured dtype: [name, type] per field, [name, type, shape] for sub-array fields."""
    if dtype.names is None:
        raise ValueError(f"{dtype} is not a structured dtype")
    return [[entry[0], entry[1], list(entry[2])] if len(entry) > 2 else list(entry) for entry in dtype.descr]


def dtype_from_json(value, where: str) -> np.dtype:
    """The numpy dtype of a zarr v2 structured `dtype` entry."""
    if not isinstance(value, list):
        raise DatasetError(f"{where}: dtype {value!r} is not a structured record type")
    try:
        return np.dtype([(entry[0], entry[1], tuple(entry[2])) if len(entry) > 2 else tuple(entry) for entry in value])
    except (TypeError, ValueError, IndexError) as error:
        raise DatasetError(f"{where}: malformed structured dtype ({error})") from error


@dataclasses.dataclass(frozen=True)
class RecordArray:
    """A zarr v2 array of structured records in a folder or under a URL (metadata only; chunks are read and written
    on demand)."""

    location: str  # local path or s3:// or gs:// URL of the array
    shape: tuple[int, ...]
    chunks: tuple[int, ...]
    dtype: np.dtype
    compressor: numcodecs.abc.Codec | None
    filters: tuple[numcodecs.abc.Codec, ...]
    fill: np.ndarray  # () record that unwritten chunks read as
    order: str  # "C" or "F": memory order of a decoded chunk
    separator: str  # between chunk indices in chunk file names

    @classmethod
    def create(
        cls,
        path: str | os.PathLike,
        shape: tuple[int, ...],
        rows_per_chunk: int,
        dtype: np.dtype,
        compressor: numcodecs.abc.Codec,
        attributes: Mapping | None = None,
    ) -> RecordArray:
        """A new array of zero records, chunked `rows_per_chunk` along the first axis only."""
        location = str(path)
        chunks = (rows_per_chunk, *shape[1:])
        zero = np.zeros((), dtype)
        if attributes is not None:
            _write_json(location, ATTRIBUTES_FILE, attributes)
        _write_json(
            location,
            ARRAY_FILE,
            {
                "zarr_format": ZARR_FORMAT,
                "shape": list(shape),
                "chunks": list(chunks),
                "dtype": dtype_to_json(dtype),
                "compressor": compressor.get_config(),
                "filters": None,
                "fill_value": base64.standard_b64encode(zero.tobytes()).decode("ascii"),
                "order": "C",
                "dimension_separator": DEFAULT_SEPARATOR,
            },
        )
        return cls(location, tuple(shape), chunks, dtype, compressor, (), zero, "C", DEFAULT_SEPARATOR)

    @classmethod
    def open(cls, path: str | os.PathLike) -> RecordArray:
        """An existing array; `DatasetError` naming the problem if its metadata is missing or not supported."""
        location = str(path)
        meta = _read_json(location, ARRAY_FILE)
        where = join(location, ARRAY_FILE)
        if meta.get("zarr_format") != ZARR_FORMAT:
            raise DatasetError(f"{where}: zarr_format {meta.get('zarr_format')!r}, expected {ZARR_FORMAT}")
        try:
            shape, chunks = tuple(int(n) for n in meta["shape"]), tuple(int(n) for n in meta["chunks"])
            dtype = dtype_from_json(meta["dtype"], where)
            compressor = None if meta.get("compressor") is None else numcodecs.get_codec(meta["compressor"])
            filters = tuple(numcodecs.get_codec(config) for config in meta.get("filters") or ())
            fill_value, order = meta.get("fill_value"), meta.get("order", "C")
            separator = meta.get("dimension_separator", DEFAULT_SEPARATOR)
        except (KeyError, TypeError, ValueError) as error:
            raise DatasetError(f"{where}: malformed or unsupported metadata ({error!r})") from error
        if len(chunks) != len(shape) or any(n < 1 for n in chunks) or order not in ("C", "F"):
            raise DatasetError(f"{where}: inconsistent shape {shape}, chunks {chunks} or order {order!r}")
        fill = np.zeros((), dtype)
        if fill_value is not None:
            try:
                fill = np.frombuffer(base64.standard_b64decode(fill_value), dtype)[0]
            except (TypeError, ValueError, IndexError) as error:
                raise DatasetError(f"{where}: fill_value is not a base64 record of {dtype.itemsize} bytes") from error
        return cls(location, shape, chunks, dtype, compressor, filters, fill, order, separator)

    @property
    def attributes(self) -> dict:
        return read_attributes(self.location)

    def _chunk_key(self, index: tuple[int, ...]) -> str:
        return self.separator.join(str(i) for i in index)

    def write_chunk(self, chunk: int, records: np.ndarray) -> None:
        """Write rows [chunk * rows_per_chunk, ...) from `records` (shape (rows, *shape[1:]), the array's dtype)."""
        rows = self.chunks[0]
        expected = (min(rows, self.shape[0] - chunk * rows), *self.shape[1:])
        if records.dtype != self.dtype or records.shape != expected:
            raise ValueError(f"{self.location} chunk {chunk}: got {records.dtype}{records.shape}, expected {expected}")
        full = np.zeros(self.chunks, self.dtype)
        full[: len(records)] = records
        key = self._chunk_key((chunk,) + (0,) * (len(self.shape) - 1))
        open_store(self.location).write(key, self.compressor.encode(full.tobytes()))

    def _read_chunk(self, index: tuple[int, ...]) -> np.ndarray:
        key = self._chunk_key(index)
        data = _read_bytes(self.location, key)
        if data is None:
            return np.full(self.chunks, self.fill, self.dtype)
        try:
            if self.compressor is not None:
                data = self.compressor.decode(data)
            for codec in reversed(self.filters):
                data = codec.decode(data)
            data = memoryview(data).cast("B")
        except (RuntimeError, ValueError, TypeError) as error:
            raise DatasetError(f"{join(self.location, key)}: cannot decode chunk ({error})") from error
        expected = math.prod(self.chunks) * self.dtype.itemsize
        if data.nbytes != expected:
            raise DatasetError(f"{join(self.location, key)}: chunk decodes to {data.nbytes} bytes, expected {expected}")
        return np.frombuffer(data, self.dtype).reshape(self.chunks, order=self.order)

    def read(self, start: int = 0, stop: int | None = None) -> np.ndarray:
        """Records of rows [start, stop) along the first axis, shape (stop - start, *shape[1:])."""
        stop = self.shape[0] if stop is None else min(stop, self.shape[0])
        out = np.empty((max(stop - start, 0), *self.shape[1:]), self.dtype)
        if len(out) == 0:
            return out
        rows = self.chunks[0]
        grid = [range(math.ceil(n / c)) for n, c in zip(self.shape[1:], self.chunks[1:], strict=True)]
        for first in range(start // rows, math.ceil(stop / rows)):
            base = first * rows
            lo, hi = max(start, base), min(stop, base + rows)
            for rest in itertools.product(*grid):
                where, take = [slice(lo - start, hi - start)], [slice(lo - base, hi - base)]
                for i, size, length in zip(rest, self.chunks[1:], self.shape[1:], strict=True):
                    end = min((i + 1) * size, length)
                    where.append(slice(i * size, end))
                    take.append(slice(0, end - i * size))
                out[tuple(where)] = self._read_chunk((first, *rest))[tuple(take)]
        return out
