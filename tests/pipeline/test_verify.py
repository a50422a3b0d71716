"""`kforge verify`: a clean dataset passes; corruption, missing files and uncommitted batches name their shard;
`--repair` withdraws the commits of bad batches."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from pipeline_test_helpers import GEOMETRY, batch_file, batch_result

from kforge.pipeline.cli.verify import main
from kforge.pipeline.storage import Lease
from kforge.pipeline.storage.manifest import record_key
from kforge.pipeline.storage.repair import damaged_commits
from kforge.pipeline.storage.shard_store import open_dataset
from kforge.pipeline.storage.verify import verify_dataset
from kforge.pipeline.storage.writer import clean_uncommitted, write_level_batch


@pytest.fixture
def copy(dataset_dir, tmp_path):
    target = tmp_path / "ds"
    shutil.copytree(dataset_dir, target)
    return target


def test_a_clean_dataset_passes(dataset_dir, capsys):
    reports = verify_dataset(dataset_dir)
    assert [r.ok for r in reports] == [True, True]
    assert [r.num_kept for r in reports] == [4, 4]  # two batches of two kept trajectories per shard
    main([str(dataset_dir)], prog="kforge verify")
    out = capsys.readouterr().out
    assert "shard-000000: ok" in out and "shard-000001: ok" in out and "bad shards: none" in out


def test_a_flipped_byte_in_a_chunk_fails_its_shard(copy, capsys):
    dataset = open_dataset(copy)
    path = batch_file(dataset, "env_state/sim/bodies/position", GEOMETRY.global_batch(1, 1))
    data = bytearray(path.read_bytes())
    data[100] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(SystemExit) as exit_info:
        main([str(copy)], prog="kforge verify")
    assert exit_info.value.code == 1
    captured = capsys.readouterr()
    assert "shard-000000: ok" in captured.out
    assert "shard-000001: BAD" in captured.out
    assert (
        "batch 1: env_state/sim/bodies/position: file data/env_state/sim/bodies/position/c/3/0/0/0 sha256 mismatch"
        in (captured.out)
    )
    assert "cannot decode" in captured.out  # crc32c of the chunk
    assert "bad shards shard-000001" in captured.err


def test_a_missing_file_fails_its_shard(copy):
    dataset = open_dataset(copy)
    batch_file(dataset, "done", GEOMETRY.global_batch(0, 1)).unlink()
    reports = verify_dataset(copy)
    assert [r.ok for r in reports] == [False, True]
    assert "batch 1: done: file data/done/c/1/0 missing" in reports[0].problems
    assert "batch 1: done: decoded content differs from the record" in reports[0].problems


def test_a_missing_record_makes_the_shard_incomplete(copy):
    (copy / "manifest" / "shard-000001" / "batch-000.json").unlink()
    reports = verify_dataset(copy)
    assert reports[1].problems == ["level batches [0] not committed"]
    assert any("uncommitted data file" in note for note in reports[1].notes)
    lenient = verify_dataset(copy, allow_incomplete=True)
    assert [r.ok for r in lenient] == [True, True] and lenient[1].num_kept == 2


def test_an_unreadable_dataset_exits_with_the_reason(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main([str(tmp_path)], prog="kforge verify")
    assert exit_info.value.code == 2  # the caller's input, not damaged data
    assert "not a dataset" in capsys.readouterr().err


def test_repair_withdraws_the_bad_batch_and_rewriting_it_gives_back_the_untouched_dataset(
    dataset_dir, copy, rolled_out, capsys
):
    dataset = open_dataset(copy)
    g = GEOMETRY.global_batch(1, 1)
    path = batch_file(dataset, "env_state/sim/bodies/position", g)
    data = bytearray(path.read_bytes())
    data[100] ^= 0xFF
    path.write_bytes(bytes(data))
    main([str(copy), "--repair"], prog="kforge verify")
    out = capsys.readouterr().out
    assert (
        "withdrew the commit of shard-000001 batch 1: env_state/sim/bodies/position: file "
        "data/env_state/sim/bodies/position/c/3/0/0/0 sha256 mismatch" in out
    )
    assert "repaired: 1 level batches to regenerate" in out
    assert [r.committed for r in verify_dataset(copy, allow_incomplete=True)] == [[0, 1], [0]]
    # The next run regenerates exactly that batch (here: the same writer call that made it).
    with Lease.acquire(copy) as lease:
        clean_uncommitted(copy, 1, lease.holder.job_id)
    write_level_batch(open_dataset(copy), 1, 1, batch_result(rolled_out, (10 * g, 10 * g + 1, 10 * g + 2)))
    for name in ("env_state/sim/bodies/position", "action", "done"):
        np.testing.assert_array_equal(
            open_dataset(copy).read([name], range(GEOMETRY.num_slots))[name],
            open_dataset(dataset_dir).read([name], range(GEOMETRY.num_slots))[name],
        )
    assert all(report.ok for report in verify_dataset(copy))
    main([str(copy), "--repair"], prog="kforge verify")
    assert "nothing to repair" in capsys.readouterr().out


def test_an_unfinished_dataset_points_at_allow_incomplete_and_the_command_that_finishes_it(copy, capsys):
    (copy / "manifest" / "shard-000001" / "batch-000.json").unlink()
    with pytest.raises(SystemExit) as exit_info:
        main([str(copy)], prog="kforge verify")
    assert exit_info.value.code == 1
    err = capsys.readouterr().err
    assert f"1 level batches are not committed: finish the job with kforge run {copy / 'config.yaml'}" in err
    assert "--allow-incomplete" in err
    assert "--repair" not in err  # nothing committed is damaged


def test_the_check_a_resumed_run_makes_finds_missing_and_damaged_files(dataset_dir, copy):
    assert damaged_commits(dataset_dir) == []
    dataset = open_dataset(copy)
    batch_file(dataset, "done", GEOMETRY.global_batch(0, 1)).unlink()
    flipped = batch_file(dataset, "action", GEOMETRY.global_batch(1, 0))
    data = bytearray(flipped.read_bytes())
    data[50] ^= 0x01
    flipped.write_bytes(bytes(data))
    assert damaged_commits(copy) == [
        "shard-000000 batch 1: file data/done/c/1/0 missing",
        "shard-000001 batch 0: file data/action/c/2/0/0 sha256 mismatch",
    ]
    # A resumed run reads no data object: it finds the missing file, not the flipped byte (verify and readers do).
    assert damaged_commits(copy, read_objects=False) == ["shard-000000 batch 1: file data/done/c/1/0 missing"]


def test_repair_withdraws_a_record_past_the_dataset_s_batches_per_shard(copy, capsys):
    stray = json.loads((copy / record_key(0, 1)).read_text()) | {"batch": GEOMETRY.batches_per_shard}
    (copy / record_key(0, GEOMETRY.batches_per_shard)).write_text(json.dumps(stray))
    with pytest.raises(SystemExit):
        main([str(copy)])
    assert "batch 2: record outside the dataset's 2 level batches per shard" in capsys.readouterr().out
    main([str(copy), "--repair"])
    assert "withdrew the commit of shard-000000 batch 2: record outside" in capsys.readouterr().out
    assert not (copy / record_key(0, GEOMETRY.batches_per_shard)).exists()
    assert all(report.ok for report in verify_dataset(copy))
