"""Readers verify: `kforge export` and `kforge bc train` check the recorded checksums of a dataset's committed objects
before they read it, and refuse a flipped byte or a removed object with the same one-line error."""

from __future__ import annotations

import shutil

import pytest
from pipeline_test_helpers import batch_file

from kforge.pipeline.kinetix.export import export_kinetix
from kforge.pipeline.learning import load_bc_config, train_bc
from kforge.pipeline.storage.repair import DatasetDamaged
from kforge.pipeline.storage.shard_store import open_dataset

DAMAGED = "1 committed level batches have missing, unreadable or damaged files"


def _flip_byte(path) -> None:
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x01
    path.write_bytes(bytes(data))


@pytest.fixture(params=["flipped byte", "removed object"])
def damaged(request, dataset_dir, tmp_path):
    """A copy of the dataset whose `done` object of global batch 1 (shard 0, batch 1) has a flipped byte or is gone,
    and the problem the refusal must name."""
    root = tmp_path / "ds"
    shutil.copytree(dataset_dir, root)
    path = batch_file(open_dataset(root), "done", 1)
    if request.param == "flipped byte":
        _flip_byte(path)
        problem = "sha256 mismatch"
    else:
        path.unlink()
        problem = "missing"
    return root, rf"shard-000000 batch 1: file data/done/c/1/0 {problem}\); run `kforge verify --repair {root}`"


def test_export_refuses_a_damaged_batch_before_writing(damaged, tmp_path):
    root, problem = damaged
    with pytest.raises(
        DatasetDamaged, match=rf"^{root}: {DAMAGED} \({problem}, then `kforge run .*config.yaml`"
    ) as error:
        export_kinetix(root, tmp_path / "out", show_progress=False)
    assert "\n" not in str(error.value)
    assert not (tmp_path / "out").exists()


def test_bc_train_refuses_a_damaged_batch_before_training(damaged, tmp_path):
    root, problem = damaged
    config = load_bc_config(str(root), [f"output_dir={tmp_path / 'bc'}", "train.num_steps=1", "train.batch_size=2"])
    with pytest.raises(
        DatasetDamaged, match=rf"^{root}: {DAMAGED} \({problem}, then `kforge run .*config.yaml`"
    ) as error:
        train_bc(config, show_progress=False)
    assert "\n" not in str(error.value)
