"""Fencing: a job that lost its dataset's lease cannot change the dataset. A holder paused (SIGSTOP) past the stale
limit, whose lease another job took over meanwhile, raises `LeaseLost` at its next step and commits, uncommits and
deletes nothing; a garbage lease is a lost lease; commits never overwrite a record; a worker that does not hold a
shard can neither claim nor commit its batches."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time

import pytest
from pipeline_test_helpers import (
    assert_keeps_in_every_batch,
    assert_same_dataset,
    committed_count,
    keeping_job,
    run_job_process,
    start_job,
)

from kforge.pipeline.cli import EXIT_DATA
from kforge.pipeline.generation import to_yaml
from kforge.pipeline.generation.coordinator import Coordinator, ShardNotHeld
from kforge.pipeline.storage import (
    Lease,
    LeaseLost,
    commit_age_limit,
    read_record_json,
    record_key,
)
from kforge.pipeline.storage.lease import LEASE_KEY, read_holder
from kforge.pipeline.storage.manifest import commit_record, remove_record
from kforge.pipeline.storage.shard_store import open_dataset
from kforge.pipeline.storage.verify import verify_dataset
from kforge.pipeline.storage.writer import STAGING_DIR, clean_uncommitted, staged_by, staging_key

STALE_AFTER_S = 1.5  # [s] the lease's stale limit in these tests
HEARTBEAT_S = 0.2  # [s]
NUM_SHARDS, BATCHES_PER_SHARD = 2, 2  # the shared test dataset's geometry

PAUSED_JOB = """
import json, sys
from kforge.pipeline.generation.coordinator import Coordinator
from kforge.pipeline.storage import Lease, LeaseLost, commit_age_limit, read_record_json
from kforge.pipeline.storage.manifest import remove_record
from kforge.pipeline.storage.writer import clean_uncommitted

root, stale, beat = sys.argv[1], float(sys.argv[2]), float(sys.argv[3])
records = json.loads(sys.argv[4])
lease = Lease.acquire(root, stale_after_s=stale, heartbeat_s=beat, job_id="paused")
coordinator = Coordinator(root, 2, 2, None, "paused", commit_age_limit(stale, beat))
shard = coordinator.next_shard("w")
print("holding", flush=True)
sys.stdin.readline()  # the test stops this process here, lets the lease go stale, then continues it
outcomes = {}
steps = {
    "check": lease.check,
    "commit": lambda: coordinator.commit(0, 1, records["0/1"], "w"),
    "clean": lambda: clean_uncommitted(root, 0, "paused", commit_age_limit(stale, beat)),
    "fence": lease.fence,
}
for name, step in steps.items():
    try:
        step()
        outcomes[name] = "done"
    except LeaseLost as error:
        outcomes[name] = "LeaseLost: " + str(error)
lease.release()
print(json.dumps(outcomes), flush=True)
"""
"""A job that holds the lease, is paused, and on resuming tries to check its lease, commit, clean up and fence."""


def _uncommitted_copy(dataset_dir, tmp_path):
    """A copy of the shared dataset with shard 0's two records removed (their data files stay: staged, uncommitted)
    and the records, keyed "shard/batch"."""
    root = tmp_path / "ds"
    shutil.copytree(dataset_dir, root)
    records = {f"0/{batch}": read_record_json(root, 0, batch) for batch in range(BATCHES_PER_SHARD)}
    for batch in range(BATCHES_PER_SHARD):
        (root / record_key(0, batch)).unlink()
    return root, records


def test_a_paused_holder_whose_lease_was_taken_over_changes_nothing(dataset_dir, tmp_path):
    root, records = _uncommitted_copy(dataset_dir, tmp_path)
    paused = subprocess.Popen(
        [sys.executable, "-c", PAUSED_JOB, str(root), str(STALE_AFTER_S), str(HEARTBEAT_S), json.dumps(records)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert paused.stdout.readline().strip() == "holding"
        paused.send_signal(signal.SIGSTOP)
        time.sleep(STALE_AFTER_S + 1.0)  # its heartbeat goes stale
        with Lease.acquire(root, stale_after_s=STALE_AFTER_S, heartbeat_s=HEARTBEAT_S, job_id="new") as lease:
            coordinator = Coordinator(root, NUM_SHARDS, BATCHES_PER_SHARD, None, "new", commit_age_limit(10, 1))
            shard = coordinator.next_shard("w")
            assert shard == 0 and coordinator.claim_batch(shard, "w") == 0
            lease.fence()
            assert coordinator.commit(0, 0, records["0/0"], "w")
            paused.send_signal(signal.SIGCONT)
            paused.stdin.write("go\n")
            paused.stdin.flush()
            outcomes = json.loads(paused.stdout.readline())
            assert read_holder(root).job_id == "new"
    finally:
        paused.kill()
        paused.wait()
    assert set(outcomes) == {"check", "commit", "clean", "fence"}
    for step, outcome in outcomes.items():
        assert outcome.startswith("LeaseLost: ") and "\n" not in outcome, (step, outcome)
    assert "this job's lease was taken over by job new" in outcomes["check"]
    assert "does not hold the lease (job new" in outcomes["commit"]
    assert not (root / record_key(0, 1)).exists()  # the paused job committed nothing
    assert json.loads((root / record_key(0, 0)).read_text()) == records["0/0"]  # nor uncommitted the new job's
    reports = verify_dataset(root, allow_incomplete=True)
    assert all(report.ok for report in reports) and reports[0].committed == [0]


def test_cleanup_removes_only_what_its_own_job_staged_and_the_markers_of_committed_batches(dataset_dir, tmp_path):
    root, records = _uncommitted_copy(dataset_dir, tmp_path)  # shard 0's two batches: files without records
    dataset = open_dataset(root)
    keys = {
        batch: [dataset.batch_key(spec.name, dataset.geometry.global_batch(0, batch)) for spec in dataset.layout.fields]
        for batch in range(BATCHES_PER_SHARD)
    }
    files = {batch: [key for key in keys[batch] if (root / key).is_file()] for batch in keys}
    assert files[0] and files[1]
    (root / staging_key(0, 0, "new")).parent.mkdir(parents=True)
    (root / staging_key(0, 0, "new")).write_bytes(b"")  # this job staged batch 0 before a crash
    (root / staging_key(0, 1, "old")).parent.mkdir(parents=True)
    (root / staging_key(0, 1, "old")).write_bytes(b"")  # a job that lost the lease staged batch 1
    with Lease.acquire(root, job_id="new", heartbeat_s=60):
        removed = clean_uncommitted(root, 0, "new")
        assert removed == sorted([*files[0], staging_key(0, 0, "new")])
        assert all((root / key).is_file() for key in files[1]) and staged_by(root, 0) == {1: {"old"}}
        assert commit_record(root, 0, 1, records["0/1"])  # this job staged and committed batch 1 since
        assert clean_uncommitted(root, 0, "new") == [staging_key(0, 1, "old")]  # a committed batch's marker
    assert all((root / key).is_file() for key in files[1]) and staged_by(root, 0) == {}


def test_a_garbage_lease_is_a_lost_lease(tmp_path):
    with Lease.acquire(tmp_path, job_id="mine", heartbeat_s=0.05) as lease:
        (tmp_path / LEASE_KEY).write_bytes(b"\x00 not a lease")
        deadline = time.monotonic() + 10
        while lease.lost is None and time.monotonic() < deadline:
            time.sleep(0.02)
        with pytest.raises(LeaseLost, match="lease was overwritten by an unreadable lease"):
            lease.check()
        coordinator = Coordinator(tmp_path, 1, 1, None, "mine")
        coordinator.next_shard("w")
        with pytest.raises(LeaseLost, match="job mine cannot prove it holds the lease .*unreadable lease"):
            coordinator.commit(0, 0, {"shard": 0, "batch": 0}, "w")
    assert (tmp_path / LEASE_KEY).read_bytes() == b"\x00 not a lease"  # a lost lease is not deleted on release


def test_a_commit_never_overwrites_a_record_and_an_uncommit_removes_only_what_it_read(tmp_path):
    first = {"shard": 0, "batch": 1, "by": "first"}
    assert commit_record(tmp_path, 0, 1, first) == {"record_version": 1, **first}
    assert commit_record(tmp_path, 0, 1, {"shard": 0, "batch": 1, "by": "second"}) is None
    assert json.loads((tmp_path / record_key(0, 1)).read_text())["by"] == "first"
    assert remove_record(tmp_path, 0, 1) and not remove_record(tmp_path, 0, 1)


def test_only_the_worker_holding_a_shard_claims_and_commits_its_batches(tmp_path):
    coordinator = Coordinator(tmp_path, NUM_SHARDS, BATCHES_PER_SHARD)
    shard = coordinator.next_shard("old")
    assert coordinator.claim_batch(shard, "old") == 0
    with pytest.raises(ShardNotHeld, match="shard 0 is leased to old, not new"):
        coordinator.claim_batch(shard, "new")
    coordinator.release(shard)  # the old worker was presumed dead and killed; its successor takes the shard
    assert coordinator.next_shard("new") == shard
    with pytest.raises(ShardNotHeld, match="shard 0 is leased to new, not old: old must write nothing more"):
        coordinator.commit(shard, 0, {"shard": 0, "batch": 0}, "old")
    with pytest.raises(ShardNotHeld, match="leased to new, not old"):
        coordinator.claim_batch(shard, "old")
    assert not (tmp_path / record_key(0, 0)).exists()
    assert coordinator.claim_batch(shard, "new") == 0
    assert coordinator.commit(shard, 0, {"shard": 0, "batch": 0}, "new")


JOB_LEASE = ["lease.stale_after_s=2", "lease.heartbeat_s=0.25"]
"""A lease that goes stale 2 s after its holder stops."""
JOB_TIMEOUT_S = 900.0


@pytest.mark.slow
def test_a_real_job_paused_past_its_lease_is_fenced_and_the_job_that_took_over_finishes_the_dataset(
    uninterrupted_keeping, keeping_cache, tmp_path
):
    output = tmp_path / "dataset"
    config_file = tmp_path / "job.yaml"
    config_file.write_text(to_yaml(keeping_job(output, keeping_cache, "ray.num_workers=0", *JOB_LEASE)))
    paused = start_job(config_file)
    try:
        deadline = time.monotonic() + JOB_TIMEOUT_S
        while committed_count(output) < 1:
            assert paused.poll() is None and time.monotonic() < deadline, "the job ended before its first commit"
            time.sleep(0.05)
        paused_job = read_holder(output).job_id
        os.killpg(paused.pid, signal.SIGSTOP)
        time.sleep(3.0)  # its lease goes stale
        outcome = {}
        taker = threading.Thread(  # a second job takes the lease over and finishes the dataset
            target=lambda: outcome.update(output=run_job_process(config_file))
        )
        taker.start()
        while (holder := read_holder(output)) is None or holder.job_id == paused_job:
            assert taker.is_alive() and time.monotonic() < deadline, "the second job did not take the lease over"
            time.sleep(0.01)
        os.killpg(paused.pid, signal.SIGCONT)  # resumes while the second job works
        text = paused.communicate(timeout=JOB_TIMEOUT_S)[1].decode(errors="replace")
        taker.join(JOB_TIMEOUT_S)
        assert "output" in outcome, "the second job failed"
    finally:
        if paused.poll() is None:
            os.killpg(paused.pid, signal.SIGKILL)
            paused.wait()
    assert paused.returncode == EXIT_DATA, text[-3000:]
    # Fenced at its next step: while the second job runs, or once it has ended and released the lease.
    assert re.search(r"this job's lease was (taken over by job \w+ |removed$)", text.splitlines()[-1]), text[-3000:]
    assert not (output / LEASE_KEY).exists()  # the fenced job left the (released) lease alone
    assert_keeps_in_every_batch(output)
    assert all(report.ok for report in verify_dataset(output))
    assert_same_dataset(uninterrupted_keeping, output)


def _staged_uncommitted(root) -> list[tuple[int, int]]:
    """(shard, batch) of the level batches with a staging marker and no commit record."""
    marked = [(shard, batch) for shard in range(NUM_SHARDS) for batch in staged_by(root, shard)]
    return [(shard, batch) for shard, batch in marked if not (root / record_key(shard, batch)).exists()]


@pytest.mark.slow
def test_a_new_jobs_cleanup_leaves_the_files_a_stopped_job_staged_and_the_stopped_job_commits_nothing(
    uninterrupted_keeping, keeping_cache, tmp_path
):
    output = tmp_path / "dataset"
    config_file = tmp_path / "job.yaml"
    config_file.write_text(to_yaml(keeping_job(output, keeping_cache, "ray.num_workers=0", *JOB_LEASE)))
    stopped = start_job(config_file)
    try:
        deadline = time.monotonic() + JOB_TIMEOUT_S
        staged = []
        while not staged:  # stop the job as it writes a level batch: marked as staged, not committed
            assert stopped.poll() is None and time.monotonic() < deadline, "the job ended before it was stopped"
            if _staged_uncommitted(output):
                os.killpg(stopped.pid, signal.SIGSTOP)
                staged = _staged_uncommitted(output)
                if not staged:  # it committed the batch before the signal landed: catch the next one
                    os.killpg(stopped.pid, signal.SIGCONT)
            time.sleep(0.005)
        (shard, batch), stopped_job = staged[0], read_holder(output).job_id
        assert staged_by(output, shard)[batch] == {stopped_job}
        dataset = open_dataset(output)
        global_batch = dataset.geometry.global_batch(shard, batch)
        keys = [dataset.batch_key(spec.name, global_batch) for spec in dataset.layout.fields]
        files = {key: (output / key).read_bytes() for key in keys if (output / key).is_file()}
        time.sleep(3.0)  # its lease goes stale
        with Lease.acquire(output, stale_after_s=2, heartbeat_s=0.25, job_id="new", log=lambda line: None):
            removed = clean_uncommitted(output, shard, "new", commit_age_limit(2, 0.25))
        assert not set(removed) & set(files)
        assert {key: (output / key).read_bytes() for key in files} == files  # the stopped job's files, untouched
        assert staged_by(output, shard)[batch] == {stopped_job}
        os.killpg(stopped.pid, signal.SIGCONT)
        text = stopped.communicate(timeout=JOB_TIMEOUT_S)[1].decode(errors="replace")
    finally:
        if stopped.poll() is None:
            os.killpg(stopped.pid, signal.SIGKILL)
            stopped.wait()
    assert stopped.returncode == EXIT_DATA, text[-3000:]
    assert "this job's lease was removed" in text.splitlines()[-1], text[-3000:]
    assert not (output / record_key(shard, batch)).exists()  # fenced: the stopped job committed nothing
    run_job_process(config_file)  # a second job finishes the dataset, staging that batch itself
    assert [path for path in (output / STAGING_DIR).rglob("*") if path.is_file()] == []
    assert_keeps_in_every_batch(output)
    assert all(report.ok for report in verify_dataset(output))
    assert_same_dataset(uninterrupted_keeping, output)
