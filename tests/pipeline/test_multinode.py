"""Multi-node on one machine: a head node and a second node started with `ray start` on 127.0.0.1, a job on the
cluster with one worker per node, the second node killed mid-run (SIGKILL of its every process); the job finishes on
the head node, verifies and equals an uninterrupted run byte for byte, kept trajectories included (the operator's
recipe in docs/operating.md)."""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time

import pytest
from pipeline_test_helpers import assert_keeps_in_every_batch, assert_same_dataset, keeping_job, kill_session

from kforge.pipeline.generation import to_yaml
from kforge.pipeline.storage import all_committed
from kforge.pipeline.storage.verify import verify_dataset

JOB_TIMEOUT_S = 900.0
NODE_START_S = 120.0  # [s] at most, for `ray start` to bring a node up
RAY = [sys.executable, "-m", "ray.scripts.scripts"]
"""The `ray` command of this interpreter's environment."""
RAY_ENV = {"RAY_AUTH_MODE": "disabled", "RAY_USAGE_STATS_ENABLED": "0"}


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def _start_node(*args: str) -> subprocess.Popen:
    """`ray start --block ...` in a session of its own (killing the session kills the node)."""
    return subprocess.Popen(
        [*RAY, "start", "--block", "--node-ip-address=127.0.0.1", "--num-cpus=1", *args],
        start_new_session=True,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        env={**os.environ, **RAY_ENV},
    )


def _nodes_alive(address: str) -> int:
    status = subprocess.run(
        [*RAY, "status", f"--address={address}"], capture_output=True, text=True, env={**os.environ, **RAY_ENV}
    )
    active = status.stdout.partition("Active:")[2].partition("Pending:")[0]
    return sum(1 for line in active.splitlines() if "node_" in line)


@pytest.mark.slow
def test_a_job_on_two_nodes_survives_the_loss_of_one_and_equals_an_uninterrupted_run(
    uninterrupted_keeping, keeping_cache, tmp_path
):
    port = _free_port()
    address = f"127.0.0.1:{port}"
    temp_dir = tempfile.mkdtemp(prefix="kfray-")  # short: Ray's socket paths live below it
    head = _start_node("--head", f"--port={port}", "--include-dashboard=false", f"--temp-dir={temp_dir}")
    second = None
    try:
        deadline = time.monotonic() + NODE_START_S
        while _nodes_alive(address) < 1:
            assert head.poll() is None and time.monotonic() < deadline, "the head node did not start"
            time.sleep(1.0)
        second = _start_node(f"--address={address}")
        while _nodes_alive(address) < 2:
            assert second.poll() is None and time.monotonic() < deadline, "the second node did not join"
            time.sleep(1.0)
        output = tmp_path / "dataset"
        config_file = tmp_path / "job.yaml"
        job = keeping_job(output, keeping_cache, f"ray.address={address}", "ray.num_workers=2")
        config_file.write_text(to_yaml(job))
        job = subprocess.Popen(
            [sys.executable, "-m", "kforge", "run", str(config_file), "--no-progress"],
            start_new_session=True,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            env={**os.environ, **RAY_ENV},
        )
        try:
            deadline = time.monotonic() + JOB_TIMEOUT_S
            while not (output / "manifest").is_dir() or not all_committed(output):
                assert job.poll() is None and time.monotonic() < deadline, "the job ended before its first commit"
                time.sleep(0.05)
            kill_session(second.pid)  # kill -9 of the second node: its raylet, its object store, its worker
            text = job.communicate(timeout=JOB_TIMEOUT_S)[0].decode(errors="replace")
        finally:
            kill_session(job.pid)
        assert job.returncode == 0, text[-3000:]
    finally:
        if second is not None:
            kill_session(second.pid)
        kill_session(head.pid)
        shutil.rmtree(temp_dir, ignore_errors=True)
    assert_keeps_in_every_batch(output)
    assert all(report.ok for report in verify_dataset(output))
    assert_same_dataset(uninterrupted_keeping, output)
