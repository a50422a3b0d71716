"""Zarr v2 record arrays: the metadata zarr 2.18 writes, reading any chunk grid / order / codec, corrupt chunks."""

from __future__ import annotations

import base64
import json

import numcodecs
import numpy as np
import pytest

from kforge.pipeline.kinetix.zarr_v2 import RecordArray, array_names, create_group
from kforge.pipeline.storage.layout import DatasetError

pytestmark = pytest.mark.smoke

DTYPE = np.dtype([("a", "<i4", (6,)), ("b", "?"), ("c", "<f4", (2, 2))])
ITEMSIZE = 6 * 4 + 1 + 4 * 4  # 41 bytes, packed


def records(shape) -> np.ndarray:
    out = np.zeros(shape, DTYPE)
    count = int(np.prod(shape))
    out["a"] = np.arange(count * 6).reshape(shape + (6,))
    out["b"] = (np.arange(count) % 3 == 0).reshape(shape)
    out["c"] = np.linspace(-1.0, 1.0, count * 4).reshape(shape + (2, 2))
    return out


def test_written_metadata_is_what_zarr_2_writes(tmp_path):
    create_group(tmp_path / "g", {"note": "hi"})
    array = RecordArray.create(tmp_path / "g" / "s0", (5, 3, 1), 2, DTYPE, numcodecs.Zstd(level=9), {"ids": [1, 2]})
    for chunk, start in enumerate(range(0, 5, 2)):
        array.write_chunk(chunk, records((5, 3, 1))[start : start + 2])
    # zarr 2.18.3 writes exactly these members for such an array (plus dimension_separator, which it reads)
    assert json.loads((tmp_path / "g" / "s0" / ".zarray").read_text()) == {
        "zarr_format": 2,
        "shape": [5, 3, 1],
        "chunks": [2, 3, 1],
        "dtype": [["a", "<i4", [6]], ["b", "|b1"], ["c", "<f4", [2, 2]]],
        "compressor": {"id": "zstd", "level": 9, "checksum": False},
        "filters": None,
        "fill_value": base64.standard_b64encode(bytes(ITEMSIZE)).decode(),
        "order": "C",
        "dimension_separator": ".",
    }
    assert json.loads((tmp_path / "g" / ".zgroup").read_text()) == {"zarr_format": 2}
    assert sorted(p.name for p in (tmp_path / "g" / "s0").iterdir()) == [
        ".zarray",
        ".zattrs",
        "0.0.0",
        "1.0.0",
        "2.0.0",
    ]
    last = np.frombuffer(numcodecs.Zstd().decode((tmp_path / "g" / "s0" / "2.0.0").read_bytes()), DTYPE)
    assert len(last) == 2 * 3 and not last[3:].tobytes().strip(b"\0")  # edge chunk stored whole, zero-padded
    assert array_names(tmp_path / "g") == ["s0"]
    assert RecordArray.open(tmp_path / "g" / "s0").attributes == {"ids": [1, 2]}
    np.testing.assert_array_equal(RecordArray.open(tmp_path / "g" / "s0").read(), records((5, 3, 1)))


def test_reads_any_chunk_grid_order_codec_and_fill(tmp_path):
    """An array laid out the way zarr 2 may write one: 2-D chunk grid, Fortran order, blosc, '/' keys, a missing
    chunk (reads as the fill record)."""
    shape, chunks = (5, 7, 1), (2, 3, 1)
    expected = records(shape)
    fill = records(())
    path = tmp_path / "s"
    path.mkdir()
    compressor = numcodecs.Blosc(cname="lz4")
    meta = {
        "zarr_format": 2,
        "shape": list(shape),
        "chunks": list(chunks),
        "dtype": [["a", "<i4", [6]], ["b", "|b1"], ["c", "<f4", [2, 2]]],
        "compressor": compressor.get_config(),
        "filters": None,
        "fill_value": base64.standard_b64encode(fill.tobytes()).decode(),
        "order": "F",
        "dimension_separator": "/",
    }
    (path / ".zarray").write_text(json.dumps(meta))
    missing = (1, 2)
    for i in range(3):
        for j in range(3):
            if (i, j) == missing:
                expected[2:4, 6:7] = fill
                continue
            block = np.zeros(chunks, DTYPE)
            part = expected[i * 2 : i * 2 + 2, j * 3 : j * 3 + 3]
            block[: part.shape[0], : part.shape[1]] = part
            (path / str(i) / str(j)).mkdir(parents=True, exist_ok=True)
            (path / str(i) / str(j) / "0").write_bytes(compressor.encode(block.tobytes(order="F")))
    array = RecordArray.open(path)
    np.testing.assert_array_equal(array.read(), expected)
    np.testing.assert_array_equal(array.read(1, 4), expected[1:4])
    np.testing.assert_array_equal(array.read(4, 9), expected[4:])


def test_corrupt_or_missing_parts_are_named(tmp_path):
    array = RecordArray.create(tmp_path / "s", (2, 3, 1), 2, DTYPE, numcodecs.Zstd())
    array.write_chunk(0, records((2, 3, 1)))
    chunk = tmp_path / "s" / "0.0.0"
    chunk.write_bytes(b"not zstd at all")
    with pytest.raises(DatasetError, match="0.0.0: cannot decode chunk"):
        array.read()
    chunk.write_bytes(numcodecs.Zstd().encode(bytes(10)))
    with pytest.raises(DatasetError, match="0.0.0: chunk decodes to 10 bytes, expected 246"):
        array.read()
    with pytest.raises(DatasetError, match="not a zarr v2 node"):
        RecordArray.open(tmp_path)
    with pytest.raises(DatasetError, match="not a zarr v2 node"):
        array_names(tmp_path)
    (tmp_path / "s" / ".zarray").write_text(json.dumps({"zarr_format": 2, "shape": [1], "chunks": [1], "dtype": "<f4"}))
    with pytest.raises(DatasetError, match="is not a structured record type"):
        RecordArray.open(tmp_path / "s")
