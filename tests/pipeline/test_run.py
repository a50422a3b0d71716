"""Jobs: resume after an interruption or a crash gives the same dataset, array for array; changed configs are refused.

The fast tests drive the coordinator and a worker in-process (the same classes Ray runs as actors); the slow tests
run the real Ray job (two workers, a worker killed, the whole job killed at several points) and compare the result
with the in-process one.
"""

import dataclasses
from pathlib import Path

import pytest
from pipeline_test_helpers import assert_same_dataset, run_in_process, run_job_process, tiny_job

import pipeline.generation.config
from engine import SimParams
from env import EnvParams
from pipeline.generation.config import to_yaml
from pipeline.generation.level_batch import run_level_batch
from pipeline.generation.run import ResumeRefused, prepare_output, run_job
from pipeline.generation.worker import FAULT_INJECTION_ENV
from pipeline.storage.manifest import committed_batches, iter_records
from pipeline.storage.shard_store import open_dataset
from pipeline.storage.verify import verify_dataset
from pipeline.storage.writer import stage_level_batch


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    root = tmp_path_factory.mktemp("uninterrupted")
    run_in_process(tiny_job(root))
    return root


def test_uninterrupted_run_commits_every_batch_and_verifies(uninterrupted):
    assert [committed_batches(uninterrupted, shard) for shard in range(2)] == [[0, 1], [0, 1]]
    assert all(report.ok for report in verify_dataset(uninterrupted))
    outcomes = [level.outcome for record in iter_records(uninterrupted) for level in record.levels]
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


def test_a_dataset_made_with_other_physics_is_refused(tmp_path, monkeypatch):
    prepare_output(tiny_job(tmp_path))
    stiffer = dataclasses.replace(SimParams(), joint_hertz=SimParams().joint_hertz + 15.0)
    other_code = lambda **kwargs: EnvParams(sim=stiffer, **kwargs)  # noqa: E731
    monkeypatch.setattr(pipeline.generation.config, "EnvParams", other_code)
    with pytest.raises(ResumeRefused, match=r"physics\.joint_hertz \("):
        prepare_output(tiny_job(tmp_path))


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


def _committed(root: Path) -> int:
    return sum(len(committed_batches(root, shard)) for shard in range(2)) if (root / "manifest").is_dir() else 0


@pytest.mark.slow
def test_a_job_killed_at_several_points_and_resumed_equals_an_uninterrupted_run(uninterrupted, tmp_path):
    output = tmp_path / "dataset"
    config_file = tmp_path / "job.yaml"
    # A killed job leaves its lease behind: the next run takes it over once its heartbeat is a second old.
    config_file.write_text(to_yaml(tiny_job(output, "lease.stale_after_s=1", "lease.heartbeat_s=0.25")))
    kill_points = {
        "dataset created, nothing committed": lambda: (output / "data" / "zarr.json").exists(),
        "first level batch committed": lambda: _committed(output) >= 1,
        "shard 0 done, shard 1 started": lambda: _committed(output) >= 3,
    }
    for where, reached in kill_points.items():
        assert not reached(), f"already past the kill point '{where}' before the run"
        run_job_process(config_file, until=reached)
        assert reached(), where
    assert _committed(output) < 4  # the last kill came before the end
    run_job_process(config_file)
    assert_same_dataset(uninterrupted, output)
    assert all(report.ok for report in verify_dataset(output))
