"""Jobs: resume after an interruption or a crash gives the same dataset, array for array; changed configs are refused.

The fast tests drive the coordinator and a worker in-process (the same classes Ray runs as actors); the slow test
runs the real Ray job with two workers and compares it with the in-process result.
"""

import json

import numpy as np
import pytest
import zarr
from pipeline_test_helpers import tiny_job

from pipeline.coordinator import Coordinator
from pipeline.level_batch import batches_per_shard, num_shards, run_level_batch
from pipeline.manifest import committed_batches, iter_records
from pipeline.run import ResumeRefused, prepare_output, run_job
from pipeline.shard_store import open_dataset
from pipeline.verify import verify_dataset
from pipeline.worker import FAULT_INJECTION_ENV, Worker
from pipeline.writer import PROVENANCE, stage_level_batch


def run_in_process(job, max_batches=None):
    """The job's work loop without Ray: one worker takes shards from the coordinator until none is left."""
    prepare_output(job)
    coordinator = Coordinator(job.output_dir, num_shards(job), batches_per_shard(job), max_batches)
    worker = Worker(job, "local")
    while (shard := coordinator.next_shard("local")) is not None:
        worker.run_shard(coordinator, shard)
        coordinator.release(shard)


def dataset_contents(root):
    """Every stored array and every commit record of a dataset directory."""
    group = zarr.open_group(str(root / "data"), mode="r")
    arrays = {name: np.asarray(array[...]) for name, array in group.arrays()}
    for name, array in group.groups():
        arrays.update({f"{name}/{k}": np.asarray(v[...]) for k, v in array.arrays()})
    records = sorted(
        json.dumps({key: value for key, value in record.items() if key != PROVENANCE}, sort_keys=True)
        for record in iter_records(root)
    )
    return arrays, records


def assert_same_dataset(first, second):
    arrays_a, records_a = dataset_contents(first)
    arrays_b, records_b = dataset_contents(second)
    assert sorted(arrays_a) == sorted(arrays_b)
    for name in arrays_a:
        np.testing.assert_array_equal(arrays_a[name], arrays_b[name], err_msg=name)
    assert records_a == records_b


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    root = tmp_path_factory.mktemp("uninterrupted")
    run_in_process(tiny_job(root))
    return root


def test_uninterrupted_run_commits_every_batch_and_verifies(uninterrupted):
    assert [committed_batches(uninterrupted, shard) for shard in range(2)] == [[0, 1], [0, 1]]
    assert all(report.ok for report in verify_dataset(uninterrupted))
    outcomes = [level["outcome"] for record in iter_records(uninterrupted) for level in record["levels"]]
    assert outcomes.count("padding") == 2 and len(outcomes) == 8


def test_interrupted_and_resumed_run_gives_the_same_dataset(uninterrupted, tmp_path):
    job = tiny_job(tmp_path)
    run_in_process(job, max_batches=3)
    assert sum(len(committed_batches(tmp_path, shard)) for shard in range(2)) == 3
    run_in_process(job)
    assert_same_dataset(uninterrupted, tmp_path)


def test_crash_between_data_and_commit_is_cleaned_and_redone(uninterrupted, tmp_path):
    job = tiny_job(tmp_path)
    run_in_process(job, max_batches=2)  # shard 0 complete
    dataset = open_dataset(tmp_path)
    # A worker wrote shard 1's first batch's data files and died before the coordinator wrote the record.
    stage_level_batch(dataset, 1, 0, run_level_batch(job, 1, 0))
    assert committed_batches(tmp_path, 1) == []
    run_in_process(job)
    assert_same_dataset(uninterrupted, tmp_path)


def test_a_config_that_changes_the_data_is_refused(tmp_path):
    prepare_output(tiny_job(tmp_path))
    prepare_output(tiny_job(tmp_path, "ray.num_workers=3"))  # where it runs does not change the data
    with pytest.raises(ResumeRefused, match=r"split\.seed \(0 -> 1\)"):
        prepare_output(tiny_job(tmp_path, "split.seed=1"))


@pytest.mark.slow
def test_ray_job_with_two_workers_matches_the_in_process_run(uninterrupted, tmp_path, monkeypatch):
    monkeypatch.setenv("RAY_AUTH_MODE", "disabled")
    summary = run_job(tiny_job(tmp_path, "ray.num_workers=2"), show_progress=False)
    assert summary["worker_failures"] == [] and summary["committed_batches"] == 4
    assert_same_dataset(uninterrupted, tmp_path)


@pytest.mark.slow
def test_a_worker_killed_mid_shard_is_replaced_and_nothing_is_lost_or_duplicated(uninterrupted, tmp_path, monkeypatch):
    monkeypatch.setenv("RAY_AUTH_MODE", "disabled")
    marker = tmp_path / "fault-fired"
    # The first worker to write its 1st level batch dies before the commit, leaving uncommitted data files.
    monkeypatch.setenv(FAULT_INJECTION_ENV, f"1:{marker}")
    output = tmp_path / "dataset"
    summary = run_job(tiny_job(output, "ray.num_workers=2"), show_progress=False)
    assert marker.exists() and len(summary["worker_failures"]) == 1
    assert summary["abandoned_shards"] == [] and summary["committed_batches"] == 4
    assert_same_dataset(uninterrupted, output)
