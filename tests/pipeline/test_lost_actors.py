"""Lost actors on Ray: the coordinator's process killed mid-run is restarted by Ray and rebuilt from the commit
records, and the job ends with the dataset of an uninterrupted run; the job's actors are gone afterwards, also when
the caller started Ray itself. A worker's process stopped (SIGSTOP: alive, unreachable) and continued later makes
no shard commit twice and the dataset equals an uninterrupted run. Both on the job that keeps trajectories. (A
worker's process killed while staging: `test_run.py`.)"""

from __future__ import annotations

import collections
import json
import os
import signal
import threading
import time

import pytest
from pipeline_test_helpers import (
    JOB_TIMEOUT_SECONDS,
    KEEPING_BATCHES,
    actor_processes,
    assert_keeps_in_every_batch,
    assert_same_dataset,
    committed_count,
    json_summary,
    keeping_job,
    kill_session,
    start_job,
)

from kforge.pipeline.generation import to_yaml
from kforge.pipeline.generation.run import COORDINATOR_ACTOR, run_job
from kforge.pipeline.storage import all_committed, iter_records
from kforge.pipeline.storage.lease import LEASE_KEY
from kforge.pipeline.storage.verify import verify_dataset

WAIT_SECONDS = 600.0
POLL_SECONDS = 0.05


def _wait_for(condition, what: str) -> None:
    deadline = time.monotonic() + WAIT_SECONDS
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(POLL_SECONDS)


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore:os.fork:RuntimeWarning")  # ray.init starts its processes with fork + exec
def test_a_killed_coordinator_is_restarted_and_the_job_ends_with_the_uninterrupted_dataset(
    uninterrupted_keeping, keeping_cache, tmp_path, monkeypatch
):
    import ray

    monkeypatch.setenv("RAY_AUTH_MODE", "disabled")
    ray.init(address="local", include_dashboard=False, namespace="kforge-test", num_cpus=2)
    try:
        job = keeping_job(tmp_path, keeping_cache, "ray.num_workers=1")
        outcome = {}

        def run():
            try:
                outcome["summary"] = run_job(job, show_progress=False, report=lambda line: None)
            except BaseException as error:  # reported below
                outcome["error"] = error

        driver = threading.Thread(target=run)
        driver.start()
        _wait_for(
            lambda: sum(map(len, all_committed(tmp_path).values())) >= 1 if (tmp_path / "manifest").is_dir() else False,
            "the first commit",
        )
        job_id = json.loads((tmp_path / LEASE_KEY).read_text())["job_id"]
        coordinator = ray.get_actor(COORDINATOR_ACTOR.format(job_id=job_id))
        ray.kill(coordinator, no_restart=False)  # its process dies; Ray may restart it
        driver.join(WAIT_SECONDS)
        assert not driver.is_alive() and "error" not in outcome, outcome.get("error")
        assert outcome["summary"]["committed_batches"] == KEEPING_BATCHES
        with pytest.raises(ValueError):  # the job killed its actors on its way out, though Ray stays up
            ray.get_actor(COORDINATOR_ACTOR.format(job_id=job_id))
    finally:
        ray.shutdown()
    assert not (tmp_path / LEASE_KEY).exists()
    assert_keeps_in_every_batch(tmp_path)
    assert all(report.ok for report in verify_dataset(tmp_path))
    assert_same_dataset(uninterrupted_keeping, tmp_path)


STOPPED_S = 30.0
"""[s] how long the worker's process stays stopped (the job's lease stays fresh: its driver beats on)."""


@pytest.mark.slow
def test_a_worker_stopped_and_continued_commits_no_shard_twice_and_the_job_equals_an_uninterrupted_run(
    uninterrupted_keeping, keeping_cache, tmp_path
):
    output = tmp_path / "dataset"
    config_file = tmp_path / "job.yaml"
    config_file.write_text(to_yaml(keeping_job(output, keeping_cache, "ray.num_workers=2")))
    process = start_job(config_file, "--json")
    stopped = []
    try:
        _wait_for(lambda: process.poll() is not None or committed_count(output) >= 1, "the first commit")
        stopped = actor_processes(process.pid)[:1]
        for pid in stopped:
            os.kill(pid, signal.SIGSTOP)  # alive, but it answers nothing
        time.sleep(STOPPED_S)
        for pid in stopped:
            os.kill(pid, signal.SIGCONT)
        out, err = process.communicate(timeout=JOB_TIMEOUT_SECONDS)
    finally:
        kill_session(process.pid)
    assert len(stopped) == 1, err.decode()[-3000:]
    assert process.returncode == 0, err.decode()[-3000:]
    summary = json_summary(out)
    assert summary["committed_batches"] == KEEPING_BATCHES and summary["abandoned_shards"] == []
    records = list(iter_records(output))
    assert len({(record.shard, record.batch) for record in records}) == len(records) == KEEPING_BATCHES
    kept = collections.Counter(level.level_id for record in records for level in record.levels if level.kept)
    assert max(kept.values()) == 1  # no trajectory stored twice
    assert_keeps_in_every_batch(output)
    assert all(report.ok for report in verify_dataset(output))
    assert_same_dataset(uninterrupted_keeping, output)
