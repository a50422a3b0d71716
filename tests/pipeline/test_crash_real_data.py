"""Crash tests on real data: the job that keeps trajectories (`KEEPING_JOB`: at least 2 kept levels in every level
batch), run without Ray, killed with SIGKILL after each of its first three commits and resumed, ends with the
dataset of its uninterrupted run: every stored array, the kept trajectories' bytes included, and every record. (On
Ray: `test_run.py`, `test_lost_actors.py`, `test_multinode.py`; on S3: `test_object_storage.py`.)"""

from __future__ import annotations

import pytest
from pipeline_test_helpers import (
    KEEPING_BATCHES,
    assert_keeps_in_every_batch,
    assert_same_dataset,
    committed_count,
    keeping_job,
    kill_at_points,
    run_job_process,
)

from kforge.pipeline.generation import to_yaml
from kforge.pipeline.storage.verify import verify_dataset

STALE_AFTER_S = 5.0  # [s] the job's lease stale limit (heartbeats every 0.25 s)


@pytest.mark.slow
def test_a_job_keeping_trajectories_killed_after_each_commit_and_resumed_equals_its_uninterrupted_run(
    uninterrupted_keeping, keeping_cache, tmp_path
):
    output = tmp_path / "dataset"
    config_file = tmp_path / "job.yaml"
    # Without Ray the heartbeat thread shares the process with the work: a stale limit of seconds, not one.
    job = keeping_job(
        output, keeping_cache, "ray.num_workers=0", f"lease.stale_after_s={STALE_AFTER_S}", "lease.heartbeat_s=0.25"
    )
    config_file.write_text(to_yaml(job))
    kill_points = {
        f"{count} level batches committed": lambda count=count: committed_count(output) >= count for count in (1, 2, 3)
    }
    kill_at_points(config_file, kill_points, STALE_AFTER_S)
    assert committed_count(output) < KEEPING_BATCHES  # the last kill came before the end
    run_job_process(config_file)
    assert_keeps_in_every_batch(output)
    assert all(report.ok for report in verify_dataset(output))
    assert_same_dataset(uninterrupted_keeping, output)
