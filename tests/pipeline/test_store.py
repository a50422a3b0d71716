"""Writing and committing level batches: bit-exact round trip of real env states, replay from a stored state,
empty slots, crash before the commit, retries, and clear errors on bad input or a mismatching dataset."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import jax
import numpy as np
import pytest
from pipeline_test_helpers import ACTION_TYPE, GEOMETRY, PARAMS, STATIC, batch_file, batch_result, dataset_spec

from kforge.env import step
from kforge.pipeline.storage.layout import DatasetError, flatten_state, unflatten_state
from kforge.pipeline.storage.lease import Lease, LeaseLost
from kforge.pipeline.storage.manifest import committed_batches, read_record, record_key
from kforge.pipeline.storage.records import Outcome
from kforge.pipeline.storage.shard_store import create_dataset, open_dataset
from kforge.pipeline.storage.store import LOCAL_PARTIAL_SUFFIX
from kforge.pipeline.storage.writer import clean_uncommitted, stored_arrays, write_level_batch

SHARD, BATCH = 1, 0
SLOTS = GEOMETRY.slots(SHARD, BATCH)  # slots 6, 7, 8: levels 0 and 1 kept, level 2 empty


@pytest.fixture
def written(tmp_path, rolled_out):
    dataset = create_dataset(tmp_path / "ds", dataset_spec())
    record = write_level_batch(dataset, SHARD, BATCH, batch_result(rolled_out))
    return dataset, record


def bits(x):
    x = np.asarray(x)
    return x.view(f"u{x.dtype.itemsize}") if x.dtype.kind == "f" else x


def test_round_trip_is_bit_exact(written, rolled_out):
    dataset, _ = written
    states, action, done, success = rolled_out
    names = [spec.name for spec in dataset.layout.fields]
    stored = dataset.read(names, [SLOTS[0], SLOTS[1]])
    expected = flatten_state(jax.tree.map(lambda x: x[:2], states))
    for spec in dataset.layout.state_fields:
        want = expected[spec.name] if spec.per_step else expected[spec.name][:, 0]
        np.testing.assert_array_equal(bits(stored[spec.name]), bits(want), err_msg=spec.name)
    np.testing.assert_array_equal(stored["action"], action[:2])
    np.testing.assert_array_equal(stored["done"], done[:2])
    np.testing.assert_array_equal(stored["success"], success[:2])
    # metadata as given, and the action mask of the level: motor slot 0 (one revolute joint) and thruster slot 4
    np.testing.assert_array_equal(stored["meta/level_id"], [10, 11])
    np.testing.assert_array_equal(stored["meta/level_seed"], [10007, 11007])
    np.testing.assert_array_equal(stored["action_mask"], [[1, 0, 0, 0, 1, 0]] * 2)


def test_episode_metadata_matches_the_episode_ends(written, rolled_out):
    dataset, record = written
    done = rolled_out[2]
    stored = dataset.read(["meta/num_episodes", "meta/episode_lengths"], [SLOTS[0]])
    ends = np.flatnonzero(done[0])
    assert stored["meta/num_episodes"][0] == len(ends) > 1
    # the first episode lasts ends[0] + 1 steps, each later one the gap between ends; the rest is padding
    lengths = stored["meta/episode_lengths"][0]
    assert lengths[0] == ends[0] + 1 and list(lengths[1 : len(ends)]) == list(np.diff(ends))
    assert not lengths[len(ends) :].any()
    assert record["levels"][0]["episode_lengths"] == lengths[: len(ends)].tolist()


def test_restart_from_a_stored_mid_trajectory_state_reproduces_the_next_state(written, levels):
    dataset, _ = written
    names = [spec.name for spec in dataset.layout.fields]
    stored = dataset.read(names, [SLOTS[1]])
    t = 100
    at = {}
    for spec in dataset.layout.state_fields:
        value = stored[spec.name][0]
        at[spec.name] = (value[t], value[t + 1]) if spec.per_step else (value, value)
    state_t = unflatten_state(dataset.layout, {name: pair[0] for name, pair in at.items()})
    level = jax.tree.map(lambda x: x[1], levels)
    replayed, _ = step(state_t, stored["action"][0, t], level, PARAMS, STATIC, ACTION_TYPE)
    replayed = flatten_state(replayed)
    for name, (_, want) in at.items():
        np.testing.assert_array_equal(bits(replayed[name]), bits(want), err_msg=name)


def test_per_level_leaves_are_stored_once_per_trajectory(written):
    dataset, _ = written
    num_slots, steps = GEOMETRY.num_slots, dataset.layout.num_steps
    assert dataset.array("env_state/sim/bodies/inverse_mass").shape == (num_slots, 7)
    assert dataset.array("env_state/sim/collision_matrix").shape == (num_slots, 7, 7)
    assert dataset.array("env_state/sim/bodies/position").shape == (num_slots, steps, 7, 2)
    assert dataset.array("action_mask").shape == (num_slots, 6)


def test_a_level_not_kept_leaves_its_slot_empty_and_is_recorded(written):
    dataset, record = written
    stored = dataset.read(["meta/valid", "meta/level_id", "env_state/sim/bodies/position", "done"], [SLOTS[2]])
    assert not stored["meta/valid"][0] and stored["meta/level_id"][0] == -1
    assert np.isnan(stored["env_state/sim/bodies/position"]).all() and not stored["done"].any()
    assert record["num_kept"] == 2
    assert record["levels"][2] | {"episode_lengths": None} == {
        "slot": 8,
        "kept": False,
        "outcome": "unsolved",
        "level_id": 12,
        "level_seed": 12007,
        "expert_success_rate": 0.0,
        "episode_lengths": None,
        "expert_env_steps": 4000,
    }


def test_a_batch_with_nothing_kept_writes_no_data_files_but_commits(tmp_path, rolled_out):
    dataset = create_dataset(tmp_path / "ds", dataset_spec())
    result = batch_result(rolled_out)
    result = dataclasses.replace(result, kept=np.zeros(3, bool), outcome=("unsolved",) * 3)
    record = write_level_batch(dataset, 0, 1, result)
    assert record["num_kept"] == 0 and committed_batches(dataset.root, 0) == [1]
    assert all(entry["file"] is None for entry in record["arrays"].values())
    assert not any(p.is_file() for p in (Path(dataset.root) / "data").rglob("c/*"))


def test_crash_before_the_commit_is_uncommitted_and_cleaned(written, rolled_out):
    dataset, _ = written
    root = Path(dataset.root)
    # shard 1 batch 1 (global batch 3): data written, then the process died before the manifest record
    arrays = stored_arrays(dataset.layout, GEOMETRY.levels_per_batch, batch_result(rolled_out))
    dataset.write_batch(GEOMETRY.global_batch(SHARD, 1), arrays)
    position = batch_file(dataset, "env_state/sim/bodies/position", 3)
    lock = position.with_name(position.name + LOCAL_PARTIAL_SUFFIX)
    lock.write_bytes(b"partial")
    temp = (root / record_key(SHARD, 1)).with_name("batch-001.json.tmp-abc")
    temp.write_text("{")
    assert committed_batches(dataset.root, SHARD) == [BATCH]
    stray = {p for p in (root / "data").rglob("*") if p.is_file() and "/c/3" in p.as_posix()}
    assert position in stray and len(stray) > 40  # one shard file per array (all-fill arrays write none)

    with Lease.acquire(dataset.root) as lease:
        removed = clean_uncommitted(dataset.root, SHARD, lease.holder.job_id)
        assert {root / key for key in removed} == stray | {temp}
        assert not any((root / key).exists() for key in removed)
        # the committed batch is untouched
        assert batch_file(dataset, "env_state/sim/bodies/position", 2).exists()
        assert committed_batches(dataset.root, SHARD) == [BATCH]
        assert clean_uncommitted(dataset.root, SHARD, lease.holder.job_id) == []


def test_cleanup_refuses_to_run_without_the_jobs_lease(written, rolled_out):
    dataset, _ = written
    arrays = stored_arrays(dataset.layout, GEOMETRY.levels_per_batch, batch_result(rolled_out))
    dataset.write_batch(GEOMETRY.global_batch(SHARD, 1), arrays)
    position = batch_file(dataset, "env_state/sim/bodies/position", 3)
    with pytest.raises(LeaseLost, match="job other does not hold the lease .no job does"):
        clean_uncommitted(dataset.root, SHARD, "other")
    with Lease.acquire(dataset.root, job_id="first"):
        with pytest.raises(LeaseLost, match=r"job other does not hold the lease \(job first \(host"):
            clean_uncommitted(dataset.root, SHARD, "other")
    assert position.exists()


def test_a_retry_overwrites_the_same_files_without_duplicates(written, rolled_out):
    dataset, record = written
    root = Path(dataset.root)
    files_before = sorted(p for p in (root / "data").rglob("*") if p.is_file())
    again = write_level_batch(dataset, SHARD, BATCH, batch_result(rolled_out))
    files_after = sorted(p for p in (root / "data").rglob("*") if p.is_file())
    assert files_after == files_before
    assert read_record(dataset.root, SHARD, BATCH).to_json() | {"record_version": 1} == again
    assert {k: v["sha256"] for k, v in again["arrays"].items()} == {k: v["sha256"] for k, v in record["arrays"].items()}
    assert len(list((root / record_key(SHARD, BATCH)).parent.iterdir())) == 1


def test_a_kept_trajectory_must_end_its_episodes_in_success(tmp_path, rolled_out):
    dataset = create_dataset(tmp_path / "ds", dataset_spec())
    result = batch_result(rolled_out)
    failing = dataclasses.replace(result, kept=np.ones(3, bool), outcome=(Outcome.KEPT,) * 3)
    with pytest.raises(DatasetError, match="level 2: kept but episodes ending at steps .* are not successes"):
        write_level_batch(dataset, 0, 0, failing)
    assert committed_batches(dataset.root, 0) == []


def test_a_per_level_leaf_that_changes_is_refused(tmp_path, rolled_out):
    dataset = create_dataset(tmp_path / "ds", dataset_spec())
    states, action, done, success = rolled_out
    friction = states.sim.bodies.friction.copy()
    friction[0, 5, 2] += 0.5
    changed = states.replace(sim=states.sim.replace(bodies=states.sim.bodies.replace(friction=friction)))
    with pytest.raises(DatasetError, match="level 0: per-level field env_state/sim/bodies/friction changes .* step 5"):
        write_level_batch(dataset, 0, 0, batch_result((changed, action, done, success)))


def test_wrong_shapes_and_ranges_are_named(tmp_path, rolled_out):
    dataset = create_dataset(tmp_path / "ds", dataset_spec())
    states, action, done, success = rolled_out
    with pytest.raises(DatasetError, match=r"action: expected int32\(3, 256, 6\), got int32\(3, 255, 6\)"):
        write_level_batch(dataset, 0, 0, batch_result((states, action[:, :255], done, success)))
    with pytest.raises(ValueError, match=r"shard 2 out of range \[0, 2\)"):
        write_level_batch(dataset, 2, 0, batch_result(rolled_out))


def test_create_is_idempotent_and_refuses_another_spec(tmp_path):
    root = tmp_path / "ds"
    create_dataset(root, dataset_spec())
    assert open_dataset(create_dataset(root, dataset_spec()).root).spec.to_json() == dataset_spec().to_json()
    with pytest.raises(DatasetError, match="different spec already exists"):
        create_dataset(root, dataset_spec(split="test"))


def test_opening_a_bad_or_mismatching_dataset_names_the_problem(tmp_path):
    with pytest.raises(DatasetError, match="not a dataset"):
        open_dataset(tmp_path)
    root = tmp_path / "ds"
    create_dataset(root, dataset_spec())
    meta_path = root / "data" / "zarr.json"
    meta = json.loads(meta_path.read_text())
    fields = meta["attributes"]["kforge_dataset"]["layout"]["fields"]
    next(f for f in fields if f["name"] == "env_state/sim/gravity")["shape"] = [3]
    meta_path.write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match=r"env_state/sim/gravity stored as .*\(3,\).* expects .*\(2,\)"):
        open_dataset(root)
    meta["attributes"]["kforge_dataset"]["format_version"] = 99
    meta_path.write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match=r"ds: dataset format version 99; this code reads version 3$"):
        open_dataset(root)


def test_reading_shard_objects_whole_gives_the_same_values_as_slot_by_slot(dataset_dir):
    """Level batches 0 and 2 read whole and their slots picked, batch 3 slot by slot, in one call, in any order."""
    dataset = open_dataset(dataset_dir)
    names = [spec.name for spec in dataset.layout.fields]
    slots = [7, 1, 10, 6, 0]  # level batches 2, 0, 3, 2, 0 (three levels per batch)
    whole = np.array([True, False, True, False])
    by_slot = dataset.read(names, slots)
    picked = dataset.read(names, slots, whole={name: whole for name in names})
    for name in names:
        np.testing.assert_array_equal(picked[name], by_slot[name], err_msg=name)
    assert by_slot["meta/valid"].all()
