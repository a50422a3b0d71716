"""Lost actors on Ray: the coordinator's process killed mid-run is restarted by Ray and rebuilt from the commit
records, and the job ends with the dataset of an uninterrupted run; the job's actors are gone afterwards, also when
the caller started Ray itself. (A worker's process killed mid-shard: `test_run.py`.)"""

from __future__ import annotations

import json
import threading
import time

import pytest
from pipeline_test_helpers import assert_same_dataset, tiny_job

from kforge.pipeline.generation.run import COORDINATOR_ACTOR, run_job
from kforge.pipeline.storage import all_committed
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
    uninterrupted, tmp_path, monkeypatch
):
    import ray

    monkeypatch.setenv("RAY_AUTH_MODE", "disabled")
    ray.init(address="local", include_dashboard=False, namespace="kforge-test", num_cpus=2)
    try:
        job = tiny_job(tmp_path, "ray.num_workers=1")
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
        assert outcome["summary"]["committed_batches"] == 4
        with pytest.raises(ValueError):  # the job killed its actors on its way out, though Ray stays up
            ray.get_actor(COORDINATOR_ACTOR.format(job_id=job_id))
    finally:
        ray.shutdown()
    assert not (tmp_path / LEASE_KEY).exists()
    assert all(report.ok for report in verify_dataset(tmp_path))
    assert_same_dataset(uninterrupted, tmp_path)
