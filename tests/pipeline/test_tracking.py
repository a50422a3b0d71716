"""Tracking: per-batch and per-shard metrics worked out by hand from commit records; an offline wandb run holds them
(read back from its .wandb file); tracking is disabled in tests and is no part of the data."""

import json
import os
import struct
from pathlib import Path

import pytest
from pipeline_test_helpers import tiny_job

from kforge.pipeline.generation import ConfigError, resolve
from kforge.pipeline.generation.coordinator import Commit
from kforge.pipeline.generation.definition import data_fingerprint
from kforge.pipeline.generation.tracking import WANDB_MODE_ENV, batch_metrics, start_tracking, tracking_mode
from kforge.pipeline.storage import PROVENANCE
from kforge.pipeline.storage.manifest import write_record

STEPS_PER_SLOT = 24 + 256 + 24
"""Env steps per level slot of the tiny job: no-op filter 24 + PPO budget 256 + stored window 24."""
WINDOW_STEPS = 24


def record(shard, batch, outcomes, rates, seconds=None):
    """A commit record with what tracking reads: each level's outcome and expert success rate, kept count, timing."""
    levels = [{"outcome": outcome, "expert_success_rate": rate} for outcome, rate in zip(outcomes, rates, strict=True)]
    result = {"shard": shard, "batch": batch, "num_kept": outcomes.count("kept"), "levels": levels}
    if seconds is not None:
        result[PROVENANCE] = {"seconds": seconds}
    return result


# Shard 0: a kept and a filtered level (4 s, 3 of them training), then an unsolved and a kept one (2 s).
BATCH_A = record(0, 0, ["kept", "filtered:no_actuator"], [1.0, 0.5], {"train": 3.0, "collect": 0.5, "total": 4.0})
BATCH_B = record(0, 1, ["unsolved", "kept"], [0.25, 0.75], {"train": 1.5, "total": 2.0})
# Shard 1: a failed (no success rate) and a kept level without timing, then a batch of padding slots only.
BATCH_C = record(1, 0, ["failed", "kept"], [None, 1.0])
BATCH_D = record(1, 1, ["padding", "padding"], [0.0, 0.0], {"total": 1.0})


def test_batch_metrics_by_hand():
    a = batch_metrics([BATCH_A], tiny_job("unused"))
    assert a["levels"] == 2 and a["kept"] == 1 and a["filtered/no_actuator"] == 1 and a["unsolved"] == 0
    assert a["kept_rate"] == 0.5 and a["solve_rate"] == 1.0  # the filtered level was not trained
    assert a["expert_success_rate"] == 1.0  # the filtered level's rate does not count
    assert a["env_steps"] == 2 * STEPS_PER_SLOT and a["transitions"] == WINDOW_STEPS
    assert a["seconds"] == 4.0 and a["seconds/train"] == 3.0 and a["seconds/collect"] == 0.5
    assert a["env_steps_per_s"] == 2 * STEPS_PER_SLOT / 4.0 and a["transitions_per_s"] == WINDOW_STEPS / 4.0

    shard = batch_metrics([BATCH_A, BATCH_B], tiny_job("unused"))
    assert shard["levels"] == 4 and shard["kept"] == 2 and shard["unsolved"] == 1
    assert shard["solve_rate"] == pytest.approx(2 / 3) and shard["expert_success_rate"] == pytest.approx(2 / 3)
    assert shard["seconds"] == 6.0 and shard["seconds/train"] == 4.5
    assert shard["env_steps_per_s"] == 4 * STEPS_PER_SLOT / 6.0 and shard["transitions_per_s"] == 2 * WINDOW_STEPS / 6

    untimed = batch_metrics([BATCH_C], tiny_job("unused"))
    assert untimed["failed"] == 1 and untimed["solve_rate"] == 0.5 and untimed["expert_success_rate"] == 1.0
    assert not any(key.startswith(("seconds", "env_steps_per_s", "transitions_per_s")) for key in untimed)

    padding = batch_metrics([BATCH_D], tiny_job("unused"))
    assert padding["levels"] == 0 and padding["env_steps"] == 2 * STEPS_PER_SLOT  # padding slots are computed too
    assert not {"kept_rate", "solve_rate", "expert_success_rate"} & set(padding)


def test_tracking_is_disabled_in_tests_by_default(tmp_path):
    job = tiny_job(tmp_path)
    assert job.tracking.wandb == "offline"  # the config's default; the test run's WANDB_MODE overrides it
    assert os.environ[WANDB_MODE_ENV] == "disabled" and tracking_mode(job) == "disabled"
    tracker = start_tracking(resolve(job))
    tracker.log_commits([Commit(BATCH_A, shard_complete=False)])
    tracker.finish({"committed_batches": 1})
    assert list(tmp_path.iterdir()) == []  # no wandb directory


def test_tracking_settings_are_checked_and_do_not_change_the_data(tmp_path, monkeypatch):
    elsewhere = tiny_job(tmp_path, "tracking.wandb=disabled", "tracking.project=other", "tracking.dir=/elsewhere")
    assert data_fingerprint(resolve(tiny_job(tmp_path))) == data_fingerprint(resolve(elsewhere))
    with pytest.raises(ConfigError, match=r"tracking\.wandb must be one of offline, online, disabled, got 'cloud'"):
        tiny_job(tmp_path, "tracking.wandb=cloud")
    monkeypatch.setenv(WANDB_MODE_ENV, "dryrun")
    with pytest.raises(ConfigError, match=r"WANDB_MODE='dryrun' must be one of"):
        tracking_mode(tiny_job(tmp_path))


def test_an_offline_run_logs_every_batch_each_completed_shard_and_the_summary(tmp_path, monkeypatch):
    monkeypatch.delenv(WANDB_MODE_ENV)
    job = tiny_job(tmp_path, "tracking.wandb=offline")  # 2 shards of 2 level batches
    for batch in (BATCH_A, BATCH_B, BATCH_C, BATCH_D):
        write_record(tmp_path, batch["shard"], batch["batch"], batch)  # the shard metrics read the manifest
    # Shard 1's first batch was committed by an earlier run: its shard metrics still count it.
    commits = [Commit(BATCH_A, False), Commit(BATCH_B, True), Commit(BATCH_D, True)]
    tracker = start_tracking(resolve(job))
    tracker.log_commits(commits)
    tracker.finish({"committed_batches": 4, "outcomes": {"kept": 3, "filtered:no_actuator": 1}, "worker_failures": []})

    run_dir = tracker_dir(tmp_path)
    rows, summary = wandb_history(run_dir)
    batches = [row for row in rows if "batch/levels" in row]
    shards = [row for row in rows if "shard/levels" in row]
    assert [row["committed_batches"] for row in batches] == [1, 2, 3]
    assert [row["batch/kept"] for row in batches] == [1, 1, 0] and batches[0]["batch/seconds/train"] == 3.0
    assert {"progress/env_steps_per_s", "progress/transitions_per_s", "batch/transitions_per_s"} <= set(batches[0])
    assert [(row["completed_shards"], row["shard/index"]) for row in shards] == [(1, 0), (2, 1)]
    assert shards[0]["shard/kept"] == 2 and shards[0]["shard/seconds"] == 6.0
    assert shards[1]["shard/levels"] == 2 and shards[1]["shard/failed"] == 1  # BATCH_C, from the earlier run
    assert summary["run/committed_batches"] == 4 and summary["run/outcomes/filtered/no_actuator"] == 1
    assert summary["run/worker_failures"] == 0


def tracker_dir(output_dir: Path) -> Path:
    """The single offline run directory under a dataset directory (tracking.dir defaults to output_dir/logs)."""
    (run_dir,) = (output_dir / "logs" / "wandb").glob("offline-run-*")
    return run_dir


LEVELDB_BLOCK = 32768
"""A .wandb file is a LevelDB-style log: 32 KiB blocks of records with 7-byte headers (crc32c, length, type)."""
LEVELDB_HEADER = struct.Struct("<IHB")
WANDB_FILE_HEADER = 7
"""Bytes before the first record: b":W&B", a 2-byte magic and a version byte."""
FULL, LAST = 1, 4


def wandb_history(run_dir: Path) -> tuple[list[dict], dict]:
    """(history rows, final summary) of an offline run, read from its run-<id>.wandb file."""
    from wandb.proto import wandb_internal_pb2

    (path,) = run_dir.glob("run-*.wandb")
    data = path.read_bytes()
    assert data[:4] == b":W&B", f"{path} is not a wandb run file"
    rows, summary, position, pending = [], {}, WANDB_FILE_HEADER, b""
    while position + LEVELDB_HEADER.size <= len(data):
        left_in_block = LEVELDB_BLOCK - position % LEVELDB_BLOCK
        if left_in_block < LEVELDB_HEADER.size:  # block trailer padding
            position += left_in_block
            continue
        _, length, kind = LEVELDB_HEADER.unpack_from(data, position)
        start = position + LEVELDB_HEADER.size
        pending += data[start : start + length]
        position = start + length
        if kind not in (FULL, LAST):
            continue
        entry = wandb_internal_pb2.Record()
        entry.ParseFromString(pending)
        pending = b""
        if entry.WhichOneof("record_type") == "history":
            rows.append(_values(entry.history.item))
        elif entry.WhichOneof("record_type") == "summary":
            summary |= _values(entry.summary.update)
    return rows, summary


def _values(items) -> dict:
    return {item.key or "/".join(item.nested_key): json.loads(item.value_json) for item in items}
