"""Typed commit records: every filter reason has an outcome, records round-trip through JSON unchanged, object sizes
are optional, a malformed record is named."""

from __future__ import annotations

import json

import pytest

from kforge.env import FilterReason
from kforge.pipeline.storage import DatasetError, Outcome
from kforge.pipeline.storage.manifest import read_record, write_record
from kforge.pipeline.storage.records import BatchRecord

pytestmark = pytest.mark.smoke

RECORD = {
    "shard": 0,
    "batch": 1,
    "global_batch": 1,
    "slots": [2, 4],
    "num_kept": 1,
    "levels": [
        {
            "slot": 2,
            "kept": True,
            "outcome": "kept",
            "level_id": 2,
            "level_seed": 77,
            "expert_success_rate": 1.0,
            "episode_lengths": [5, 7],
            "expert_env_steps": 256,
            "learning_curve": {"success_rate": [None, 0.5], "mean_return": [0.1, 0.9]},
        },
        {
            "slot": 3,
            "kept": False,
            "outcome": "filtered:no_actuator",
            "level_id": 3,
            "level_seed": 78,
            "expert_success_rate": None,
            "episode_lengths": [],
        },
    ],
    "arrays": {
        "done": {"file": "data/done/c/1/0", "sha256": "ab", "data_sha256": "cd", "size": 321},
        "action": {"file": None, "sha256": None, "data_sha256": "ef"},
    },
    "curve_env_steps": [128, 256],
    "provenance": {"seconds": {"total": 1.5}, "worker": "w"},
}


def test_every_filter_reason_has_an_outcome():
    reasons = [reason for reason in FilterReason if reason != FilterReason.KEPT]
    outcomes = [Outcome.filtered(reason.name.lower()) for reason in reasons]
    assert [outcome.value for outcome in outcomes] == [f"filtered:{reason.name.lower()}" for reason in reasons]
    assert all(outcome.is_filtered and not outcome.is_trained for outcome in outcomes)
    assert [o for o in Outcome if o.is_trained] == [Outcome.KEPT, Outcome.UNSOLVED, Outcome.FAILED]


def test_a_record_round_trips_through_the_manifest_unchanged(tmp_path):
    stored = write_record(tmp_path, 0, 1, RECORD)
    record = read_record(tmp_path, 0, 1)
    assert isinstance(record, BatchRecord)
    assert record.levels[1].outcome is Outcome.FILTERED_NO_ACTUATOR and record.kept_slots == [2]
    assert (
        record.to_json() | {"record_version": 1}
        == stored
        == json.loads((tmp_path / "manifest/shard-000000/batch-001.json").read_text())
    )


def test_object_sizes_are_read_and_a_record_without_them_reads_as_before(tmp_path):
    """`arrays.*.size` is an optional key of record version 1: records written before it read with sizes unknown."""
    write_record(tmp_path, 0, 1, RECORD)
    assert read_record(tmp_path, 0, 1).object_sizes == {"data/done/c/1/0": 321}
    older = json.loads(json.dumps(RECORD))
    del older["arrays"]["done"]["size"]
    write_record(tmp_path, 0, 1, older)
    record = read_record(tmp_path, 0, 1)
    assert record.object_sizes == {"data/done/c/1/0": None} and record.arrays["done"].sha256 == "ab"
    assert "size" not in record.to_json()["arrays"]["done"]


def test_a_malformed_record_is_named(tmp_path):
    broken = json.loads(json.dumps(RECORD))
    broken["levels"][1]["outcome"] = "vanished"
    write_record(tmp_path, 0, 1, broken)
    with pytest.raises(DatasetError, match="batch 1: record .* level 1: malformed level record .*vanished"):
        read_record(tmp_path, 0, 1)
    del broken["num_kept"]
    write_record(tmp_path, 0, 1, broken)
    with pytest.raises(DatasetError, match="shard-000000 batch 1: record .*: record without 'num_kept'"):
        read_record(tmp_path, 0, 1)
