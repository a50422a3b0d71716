"""Jobs: resume after an interruption or a crash gives the same dataset, array for array; changed configs are refused.

The fast tests drive the coordinator and a worker in-process (the same classes Ray runs as actors); the slow tests
run the real Ray job (two workers, a worker killed, the whole job killed at several points) and compare the result
with the in-process one.
"""

import contextlib
import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import zarr
from pipeline_test_helpers import run_in_process, tiny_job

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
from pipeline.storage.writer import PROVENANCE, stage_level_batch


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


def _session_processes(session: int) -> list[int]:
    """Pids of the live processes of a Unix session (the job's driver and everything Ray started under it)."""
    pids = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (FileNotFoundError, ProcessLookupError, IndexError):
            continue
        if int(fields[3]) == session and fields[0] != "Z":  # fields after ")": state, ppid, pgrp, session
            pids.append(int(stat.parent.name))
    return pids


def _kill_session(session: int) -> None:
    """SIGKILL every process of the session (a job killed without warning), and wait until they are gone."""
    deadline = time.monotonic() + KILL_WAIT_SECONDS
    while (pids := _session_processes(session)) and time.monotonic() < deadline:
        for pid in pids:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        time.sleep(0.1)
    assert not _session_processes(session), "processes of the killed job survived"


KILL_WAIT_SECONDS = 30.0
POLL_SECONDS = 0.05
JOB_TIMEOUT_SECONDS = 900.0


def _run_job_process(config_file: Path, until=None) -> None:
    """Run `python -m pipeline run` in a session of its own; with `until`, SIGKILL the whole session as soon as
    `until()` holds (the job dies mid-work), else wait for it to finish and check it succeeded."""
    process = subprocess.Popen(
        [sys.executable, "-m", "pipeline", "run", str(config_file), "--no-progress"],
        start_new_session=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        env={**os.environ, "RAY_AUTH_MODE": "disabled"},
    )
    deadline = time.monotonic() + JOB_TIMEOUT_SECONDS
    try:
        while process.poll() is None and time.monotonic() < deadline:
            if until is not None and until():
                _kill_session(process.pid)
                process.wait()
                return
            time.sleep(POLL_SECONDS)
        output = process.communicate(timeout=KILL_WAIT_SECONDS)[0].decode(errors="replace")
        assert until is None, f"the job ended before the kill point:\n{output[-3000:]}"
        assert process.returncode == 0, output[-3000:]
    finally:
        _kill_session(process.pid)


def _committed(root: Path) -> int:
    return sum(len(committed_batches(root, shard)) for shard in range(2)) if (root / "manifest").is_dir() else 0


@pytest.mark.slow
def test_a_job_killed_at_several_points_and_resumed_equals_an_uninterrupted_run(uninterrupted, tmp_path):
    output = tmp_path / "dataset"
    config_file = tmp_path / "job.yaml"
    config_file.write_text(to_yaml(tiny_job(output)))
    kill_points = {
        "dataset created, nothing committed": lambda: (output / "data" / "zarr.json").exists(),
        "first level batch committed": lambda: _committed(output) >= 1,
        "shard 0 done, shard 1 started": lambda: _committed(output) >= 3,
    }
    for where, reached in kill_points.items():
        assert not reached(), f"already past the kill point '{where}' before the run"
        _run_job_process(config_file, until=reached)
        assert reached(), where
    assert _committed(output) < 4  # the last kill came before the end
    _run_job_process(config_file)
    assert_same_dataset(uninterrupted, output)
    assert all(report.ok for report in verify_dataset(output))
