"""One job per dataset: a second run on a leased dataset refuses naming the holder, a stale lease is taken over, the
heartbeat is renewed and a take-over is noticed, the lease is gone after success, an error and SIGINT; racing
processes get the lease once."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time

import pytest
from pipeline_test_helpers import (
    as_a_terminal_job,
    assert_keeps_in_every_batch,
    assert_same_dataset,
    keeping_job,
    run_in_process,
    tiny_job,
)

from kforge.pipeline.generation import ResumeRefused, run_job, to_yaml
from kforge.pipeline.storage import Lease, LeaseLost
from kforge.pipeline.storage.lease import LEASE_KEY, LeaseHeld, LeaseHolder, read_holder
from kforge.pipeline.storage.verify import verify_dataset

RACERS = 4


def test_a_second_job_is_refused_with_the_holder_and_its_heartbeat_age(tmp_path):
    with Lease.acquire(tmp_path, job_id="first") as lease:
        stored = json.loads((tmp_path / LEASE_KEY).read_text())
        assert stored == {
            "host": lease.holder.host,
            "pid": os.getpid(),
            "job_id": "first",
            "started": lease.holder.started,
            "heartbeat": lease.holder.heartbeat,
        }
        with pytest.raises(LeaseHeld, match=r"in use by job first \(host .+, pid \d+\), last heartbeat 0 s ago"):
            Lease.acquire(tmp_path, job_id="second")
    assert not (tmp_path / LEASE_KEY).exists()


def test_a_stale_lease_is_taken_over_with_a_message(tmp_path):
    long_ago = time.time() - 1000
    (tmp_path / LEASE_KEY).write_bytes(LeaseHolder("old-host", 123, "crashed", long_ago, long_ago).to_bytes())
    with pytest.raises(LeaseHeld, match="job crashed .*last heartbeat 1000 s ago.* older than 2000 s"):
        Lease.acquire(tmp_path, stale_after_s=2000)
    messages = []
    with Lease.acquire(tmp_path, stale_after_s=500, job_id="new", log=messages.append):
        assert read_holder(tmp_path).job_id == "new"
    assert len(messages) == 1 and "taking over the stale lease of job crashed (host old-host, pid 123)" in messages[0]


def test_the_heartbeat_is_renewed_and_a_take_over_is_noticed(tmp_path):
    with Lease.acquire(tmp_path, job_id="mine", heartbeat_s=0.05) as lease:
        first = read_holder(tmp_path).heartbeat
        deadline = time.monotonic() + 10
        while read_holder(tmp_path).heartbeat == first and time.monotonic() < deadline:
            time.sleep(0.02)
        assert read_holder(tmp_path).heartbeat > first
        now = time.time()
        (tmp_path / LEASE_KEY).write_bytes(LeaseHolder("other-host", 9, "thief", now, now).to_bytes())
        while lease.lost is None and time.monotonic() < deadline:
            time.sleep(0.02)
        with pytest.raises(LeaseLost, match="this job's lease was taken over by job thief"):
            lease.check()
    assert read_holder(tmp_path).job_id == "thief"  # a lost lease is not deleted on release


RACER = """
import sys, time
from kforge.pipeline.storage.lease import Lease, LeaseHeld
root, start = sys.argv[1], float(sys.argv[2])
time.sleep(max(0.0, start - time.time()))
try:
    lease = Lease.acquire(root, heartbeat_s=60)
except LeaseHeld:
    print("refused")
else:
    print("acquired")
    time.sleep(2.0)  # hold it while the others try
    lease.release()
"""
"""A process that tries to take the lease at a given moment and prints whether it got it."""


def test_processes_racing_for_the_lease_get_it_once(tmp_path):
    start = time.time() + 8.0  # every process is up and waits for the same moment
    racers = [
        subprocess.Popen([sys.executable, "-c", RACER, str(tmp_path), str(start)], stdout=subprocess.PIPE, text=True)
        for _ in range(RACERS)
    ]
    outcomes = sorted(racer.communicate(timeout=120)[0].strip() for racer in racers)
    assert outcomes == ["acquired"] + ["refused"] * (RACERS - 1)
    assert not (tmp_path / LEASE_KEY).exists()


def test_two_runs_at_once_one_refuses_and_the_dataset_equals_an_uninterrupted_run(uninterrupted, tmp_path):
    job = tiny_job(tmp_path)
    first = threading.Thread(target=run_in_process, args=(job,))
    first.start()
    deadline = time.monotonic() + 60
    while not (tmp_path / LEASE_KEY).exists() and time.monotonic() < deadline:
        time.sleep(0.01)
    try:
        with pytest.raises(LeaseHeld, match=f"{tmp_path}: the dataset is in use by job"):
            run_job(job, show_progress=False)
    finally:
        first.join()
    assert not (tmp_path / LEASE_KEY).exists()  # the first run succeeded and removed its lease
    assert all(report.ok for report in verify_dataset(tmp_path))
    assert_same_dataset(uninterrupted, tmp_path)


def test_the_lease_is_gone_after_an_error(tmp_path):
    run_in_process(tiny_job(tmp_path), max_batches=0)
    with pytest.raises(ResumeRefused):
        run_job(tiny_job(tmp_path, "split.seed=1"), show_progress=False)
    assert not (tmp_path / LEASE_KEY).exists()


@pytest.mark.slow
def test_the_lease_is_gone_after_success_and_after_sigint(uninterrupted_keeping, keeping_cache, tmp_path):
    config_file = tmp_path / "job.yaml"
    config_file.write_text(to_yaml(keeping_job(tmp_path / "dataset", keeping_cache)))
    lease = tmp_path / "dataset" / LEASE_KEY
    process = subprocess.Popen(
        [sys.executable, "-m", "kforge", "run", str(config_file), "--no-progress"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        env={**os.environ, "RAY_AUTH_MODE": "disabled"},
        preexec_fn=as_a_terminal_job,
    )
    deadline = time.monotonic() + 300
    while not (tmp_path / "dataset" / "manifest").is_dir() and time.monotonic() < deadline:
        assert process.poll() is None, process.stdout.read().decode()[-3000:]
        time.sleep(0.05)
    assert lease.exists()
    process.send_signal(signal.SIGINT)
    output = process.communicate(timeout=120)[0].decode(errors="replace")
    assert process.returncode != 0, output[-3000:]
    assert not lease.exists(), output[-3000:]
    finished = subprocess.run(
        [sys.executable, "-m", "kforge", "run", str(config_file), "--no-progress"],
        capture_output=True,
        env={**os.environ, "RAY_AUTH_MODE": "disabled"},
        timeout=900,
    )
    assert finished.returncode == 0, finished.stdout[-3000:]
    assert not lease.exists()
    assert_keeps_in_every_batch(tmp_path / "dataset")
    assert_same_dataset(uninterrupted_keeping, tmp_path / "dataset")
