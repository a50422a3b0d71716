"""Crash tests on real data: a job that keeps trajectories (the tiny job over 16 levels without the trivial-level
filter keeps 4, in 3 of its 8 level batches), killed with SIGKILL at several points and resumed, ends with the
dataset of its uninterrupted run: every stored array, the kept trajectories' bytes included, and every record."""

from __future__ import annotations

import pytest
from pipeline_test_helpers import assert_same_dataset, kill_at_points, run_in_process, run_job_process, tiny_job

from kforge.pipeline.generation import to_yaml
from kforge.pipeline.storage import all_committed, iter_records
from kforge.pipeline.storage.verify import verify_dataset

KEEPS_TRAJECTORIES = ["split.num_levels=16", "filter.enabled=false"]
"""Levels 9-12 of split seed 0 are kept: batches 0 and 1 of shard 2 and batch 0 of shard 3."""
KEPT = 4


@pytest.fixture(scope="module")
def uninterrupted_with_trajectories(tmp_path_factory):
    root = tmp_path_factory.mktemp("uninterrupted-with-trajectories")
    run_in_process(tiny_job(root, *KEEPS_TRAJECTORIES))
    assert sum(record.num_kept for record in iter_records(root)) == KEPT
    return root


def _committed(root) -> int:
    return sum(map(len, all_committed(root).values())) if (root / "manifest").is_dir() else 0


@pytest.mark.slow
def test_a_job_keeping_trajectories_killed_at_several_points_and_resumed_equals_its_uninterrupted_run(
    uninterrupted_with_trajectories, tmp_path
):
    output = tmp_path / "dataset"
    config_file = tmp_path / "job.yaml"
    job = tiny_job(output, *KEEPS_TRAJECTORIES, "lease.stale_after_s=1", "lease.heartbeat_s=0.25")
    config_file.write_text(to_yaml(job))
    kill_points = {
        "first level batch committed": lambda: _committed(output) >= 1,
        "in shard 2, after its first kept trajectory": lambda: _committed(output) >= 5,
        "in shard 3, after the batch that kept two": lambda: _committed(output) >= 7,
    }
    kill_at_points(config_file, kill_points)
    assert _committed(output) < 8  # the last kill came before the end
    run_job_process(config_file)
    assert sum(record.num_kept for record in iter_records(output)) == KEPT
    assert all(report.ok for report in verify_dataset(output))
    assert_same_dataset(uninterrupted_with_trajectories, output)
