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

Reading accepts any chunk grid, order, separator and numcodecs codec; writing chunks the first axis only.
"""

from __future__ import annotations

import base64
import dataclasses
import itertools
import json
import math
import os
from collections.abc import Mapping
from pathlib import Path

import numcodecs
import numpy as np

from pipeline.storage import DatasetError

ZARR_FORMAT = 2
GROUP_FILE = ".zgroup"
ARRAY_FILE = ".zarray"
ATTRIBUTES_FILE = ".zattrs"
DEFAULT_SEPARATOR = "."
"""Chunk key separator when `.zarray` has no `dimension_separator` (zarr 2 before 2.8)."""


def _write_json(path: Path, value: Mapping) -> None:
    path.write_text(json.dumps(value, indent=1))


def _read_json(path: Path) -> dict:
    try:
        value = json.loads(path.read_text())
    except FileNotFoundError as error:
        raise DatasetError(f"{path.parent}: not a zarr v2 node (no {path.name})") from error
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise DatasetError(f"{path}: unreadable JSON ({error})") from error
    if not isinstance(value, dict):
        raise DatasetError(f"{path}: expected a JSON object, got {type(value).__name__}")
    return value


def create_group(path: str | os.PathLike, attributes: Mapping | None = None) -> None:
    """Make `path` (created if needed) a zarr v2 group with the given attributes."""
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    _write_json(path / GROUP_FILE, {"zarr_format": ZARR_FORMAT})
    if attributes is not None:
        _write_json(path / ATTRIBUTES_FILE, attributes)


def read_attributes(path: str | os.PathLike) -> dict:
    """The attributes of a group or array ({} if it has none)."""
    path = Path(path) / ATTRIBUTES_FILE
    return _read_json(path) if path.exists() else {}


def array_names(group: str | os.PathLike) -> list[str]:
    """Sorted names of the arrays directly in a zarr v2 group (zarr's `array_keys()`)."""
    group = Path(group)
    meta = _read_json(group / GROUP_FILE)
    if meta.get("zarr_format") != ZARR_FORMAT:
        raise DatasetError(f"{group}: zarr_format {meta.get('zarr_format')!r}, expected {ZARR_FORMAT}")
    return sorted(child.name for child in group.iterdir() if (child / ARRAY_FILE).is_file())


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
    """A zarr v2 array of structured records on disk (metadata only; chunks are read and written on demand)."""

    path: Path
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
        path = Path(path)
        path.mkdir(parents=True)
        chunks = (rows_per_chunk, *shape[1:])
        zero = np.zeros((), dtype)
        _write_json(
            path / ARRAY_FILE,
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
        if attributes is not None:
            _write_json(path / ATTRIBUTES_FILE, attributes)
        return cls(path, tuple(shape), chunks, dtype, compressor, (), zero, "C", DEFAULT_SEPARATOR)

    @classmethod
    def open(cls, path: str | os.PathLike) -> RecordArray:
        """An existing array; `DatasetError` naming the problem if its metadata is missing or not supported."""
        path = Path(path)
        meta = _read_json(path / ARRAY_FILE)
        where = str(path / ARRAY_FILE)
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
        return cls(path, shape, chunks, dtype, compressor, filters, fill, order, separator)

    @property
    def attributes(self) -> dict:
        return read_attributes(self.path)

    def _chunk_file(self, index: tuple[int, ...]) -> Path:
        return self.path / self.separator.join(str(i) for i in index)

    def write_chunk(self, chunk: int, records: np.ndarray) -> None:
        """Write rows [chunk * rows_per_chunk, ...) from `records` (shape (rows, *shape[1:]), the array's dtype)."""
        rows = self.chunks[0]
        expected = (min(rows, self.shape[0] - chunk * rows), *self.shape[1:])
        if records.dtype != self.dtype or records.shape != expected:
            raise ValueError(f"{self.path} chunk {chunk}: got {records.dtype}{records.shape}, expected {expected}")
        full = np.zeros(self.chunks, self.dtype)
        full[: len(records)] = records
        self._chunk_file((chunk,) + (0,) * (len(self.shape) - 1)).write_bytes(self.compressor.encode(full.tobytes()))

    def _read_chunk(self, index: tuple[int, ...]) -> np.ndarray:
        path = self._chunk_file(index)
        if not path.exists():
            return np.full(self.chunks, self.fill, self.dtype)
        data = path.read_bytes()
        try:
            if self.compressor is not None:
                data = self.compressor.decode(data)
            for codec in reversed(self.filters):
                data = codec.decode(data)
            data = memoryview(data).cast("B")
        except (RuntimeError, ValueError, TypeError) as error:
            raise DatasetError(f"{path}: cannot decode chunk ({error})") from error
        expected = math.prod(self.chunks) * self.dtype.itemsize
        if data.nbytes != expected:
            raise DatasetError(f"{path}: chunk decodes to {data.nbytes} bytes, expected {expected}")
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
