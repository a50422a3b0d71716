"""Jobs: resume after an interruption or a crash gives the same dataset, array for array; changed configs are refused.

The fast tests drive the coordinator and a worker in-process (the same classes Ray runs as actors); the slow tests
run the real Ray job (two workers, a worker killed, the whole job killed at several points) and compare the result
with the in-process one.
"""

import contextlib
import dataclasses
import json
import os
import shutil
import signal
import subprocess
import sys
import time
import traceback
from pathlib import Path

import jax.numpy as jnp
import pytest
from pipeline_test_helpers import (
    JOB_TIMEOUT_SECONDS,
    KEEPING_BATCHES,
    KILL_WAIT_SECONDS,
    POLL_SECONDS,
    actor_processes,
    as_a_terminal_job,
    assert_keeps_in_every_batch,
    assert_same_dataset,
    committed_count,
    dataset_contents,
    json_summary,
    keeping_job,
    kill_at_points,
    kill_session,
    run_in_process,
    run_job_process,
    session_processes,
    start_job,
    tiny_job,
)

import kforge.pipeline.generation.level_batch
import kforge.pipeline.generation.worker
from kforge.engine import SimParams
from kforge.env import EnvParams
from kforge.pipeline.cli import EXIT_DATA, EXIT_INTERRUPTED
from kforge.pipeline.cli.verify import main as verify_main
from kforge.pipeline.generation import load_config, to_yaml
from kforge.pipeline.generation.definition import data_fingerprint
from kforge.pipeline.generation.growth import ResumeRefused
from kforge.pipeline.generation.level_batch import run_level_batch
from kforge.pipeline.generation.resolved import resolve
from kforge.pipeline.generation.run import (
    WorkerFailures,
    failure_cause,
    prepare_output,
    run_job,
)
from kforge.pipeline.storage.manifest import committed_batches, iter_records, record_key
from kforge.pipeline.storage.repair import DatasetDamaged
from kforge.pipeline.storage.shard_store import MANIFEST_DIR, open_dataset
from kforge.pipeline.storage.verify import verify_dataset
from kforge.pipeline.storage.writer import STAGING_DIR, stage_level_batch


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
    stage_level_batch(dataset, 1, 0, run_level_batch(resolve(job), 1, 0))
    assert committed_batches(tmp_path, 1) == []
    run_in_process(job)
    assert_same_dataset(uninterrupted, tmp_path)


def test_a_failing_shard_of_a_job_without_ray_is_retried_abandoned_and_finished_by_a_later_run(
    uninterrupted, tmp_path, monkeypatch
):
    def failing_on_shard_1(job, shard, batch, **kwargs):
        if shard == 1:
            raise FloatingPointError("injected")
        return run_level_batch(job, shard, batch, **kwargs)

    monkeypatch.setattr(kforge.pipeline.generation.worker, "run_level_batch", failing_on_shard_1)
    summary = run_in_process(tiny_job(tmp_path))
    assert summary["worker_failures"] == [{"shard": 1, "worker": "local", "error": "FloatingPointError: injected"}] * 3
    assert summary["worker_failure_causes"] == ["3 FloatingPointError: injected"]
    assert summary["abandoned_shards"] == [1] and summary["committed_in_run"] == 2
    assert (committed_batches(tmp_path, 0), committed_batches(tmp_path, 1)) == ([0, 1], [])
    monkeypatch.undo()
    run_in_process(tiny_job(tmp_path))
    assert_same_dataset(uninterrupted, tmp_path)


def test_a_failure_on_ray_is_named_by_its_cause_and_failures_are_counted_by_cause():
    import ray.exceptions

    try:
        raise FloatingPointError("injected\nsecond line")
    except FloatingPointError as raised:  # as Ray reports an exception of the worker's code: wrapped, the cause kept
        in_task = ray.exceptions.RayTaskError("run_shard", traceback.format_exc(), raised).as_instanceof_cause()
    out_of_memory = ray.exceptions.OutOfMemoryError("Task was killed due to the node running low on memory.\nMore")
    failures = WorkerFailures()
    for shard, error in enumerate([ray.exceptions.ActorDiedError(), out_of_memory, ray.exceptions.ActorDiedError()]):
        failures.add(shard, "worker-0", failure_cause(error))
    assert failure_cause(in_task) == "FloatingPointError: injected"
    assert failures.by_cause() == [
        "2 ActorDiedError: The actor died unexpectedly before finishing this task.",
        "1 OutOfMemoryError: Task was killed due to the node running low on memory.",
    ]


def test_a_level_whose_data_makes_training_nan_fails_alone_and_is_recorded(uninterrupted, tmp_path, monkeypatch):
    outcomes = {level.level_id: str(level.outcome) for record in iter_records(uninterrupted) for level in record.levels}
    poisoned = min(level for level, outcome in outcomes.items() if outcome == "unsolved")  # a level that is trained
    sample = kforge.pipeline.generation.level_batch.sample_batch

    def with_nan_gravity(job, indices):  # the poisoned level's gravity is NaN: its training and window turn NaN
        levels = sample(job, indices)
        hit = jnp.asarray(indices) == poisoned
        return levels.replace(sim=levels.sim.replace(gravity=jnp.where(hit[:, None], jnp.nan, levels.sim.gravity)))

    monkeypatch.setattr(kforge.pipeline.generation.level_batch, "sample_batch", with_nan_gravity)
    summary = run_in_process(tiny_job(tmp_path))
    assert summary["worker_failures"] == [] and summary["committed_batches"] == 4  # contained to the level
    found = {level.level_id: str(level.outcome) for record in iter_records(tmp_path) for level in record.levels}
    assert found == outcomes | {poisoned: "failed"}
    assert all(report.ok for report in verify_dataset(tmp_path))


WITHOUT_RAY = """
import runpy, sys
class NoRay:  # as on a machine where Ray is not installed
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] == "ray":
            raise ModuleNotFoundError("No module named 'ray'")
sys.meta_path.insert(0, NoRay())
sys.argv = ["kforge", *sys.argv[1:]]
runpy.run_module("kforge", run_name="__main__")
"""
"""`python -c` code that runs `python -m kforge` with every import of Ray failing."""


def test_a_job_without_ray_runs_where_ray_cannot_be_imported_and_makes_the_same_data(uninterrupted, tmp_path):
    output = tmp_path / "dataset"
    config_file = tmp_path / "job.yaml"
    config_file.write_text(to_yaml(tiny_job(output, "ray.num_workers=0")))
    command = [sys.executable, "-c", WITHOUT_RAY, "run", str(config_file), "--no-progress", "--json", "--max-batches=1"]
    finished = subprocess.run(command, capture_output=True, text=True, timeout=JOB_TIMEOUT_SECONDS)
    assert finished.returncode == EXIT_DATA, finished.stderr[-3000:]  # incomplete: 1 of 4 level batches
    assert json.loads(finished.stdout)["committed_in_run"] == 1
    (record,) = dataset_contents(output)[1]  # with the digests of its data
    assert record in dataset_contents(uninterrupted)[1]


def test_a_config_that_changes_the_data_is_refused(tmp_path):
    prepare_output(resolve(tiny_job(tmp_path)))
    prepare_output(resolve(tiny_job(tmp_path, "ray.num_workers=3")))  # where it runs does not change the data
    with pytest.raises(ResumeRefused, match=r"split\.seed \(0 -> 1\)"):
        prepare_output(resolve(tiny_job(tmp_path, "split.seed=1")))


def test_a_dataset_made_with_other_physics_is_refused(tmp_path, monkeypatch):
    prepare_output(resolve(tiny_job(tmp_path)))
    stiffer = dataclasses.replace(SimParams(), joint_hertz=SimParams().joint_hertz + 15.0)
    other_code = lambda **kwargs: EnvParams(sim=stiffer, **kwargs)  # noqa: E731
    monkeypatch.setattr("kforge.env.EnvParams", other_code)
    with pytest.raises(ResumeRefused, match=r"physics\.joint_hertz \("):
        prepare_output(resolve(tiny_job(tmp_path)))


def test_a_dataset_resumed_under_another_physics_scheme_is_refused(tmp_path):
    prepare_output(resolve(tiny_job(tmp_path)))
    prepare_output(resolve(tiny_job(tmp_path, "env.physics=kinetix")))  # the default, named
    with pytest.raises(ResumeRefused, match=r"physics\.num_substeps \(1 -> 4\)"):
        prepare_output(resolve(tiny_job(tmp_path, "env.physics=kforge")))


@pytest.mark.slow  # the tiny job's programs compiled for another solver scheme (minutes)
def test_a_job_under_the_kforge_physics_scheme_makes_a_dataset_of_its_own_that_verifies(tmp_path, uninterrupted):
    job = tiny_job(tmp_path, "env.physics=kforge")
    assert run_in_process(job)["committed_batches"] == 4
    attributes = open_dataset(tmp_path).spec.attributes
    physics = attributes["data_config"]["physics"]
    assert (physics["scheme"], physics["num_substeps"], physics["num_iterations"]) == ("kforge", 4, 1)
    assert attributes["data_fingerprint"] == data_fingerprint(resolve(job))
    assert attributes["data_fingerprint"] != open_dataset(uninterrupted).spec.attributes["data_fingerprint"]
    verify_main([str(tmp_path)])  # exits non-zero on any problem


@pytest.mark.slow
def test_ray_job_with_two_workers_matches_the_in_process_run(uninterrupted, tmp_path, monkeypatch):
    monkeypatch.setenv("RAY_AUTH_MODE", "disabled")
    summary = run_job(tiny_job(tmp_path, "ray.num_workers=2"), show_progress=False)
    assert summary["worker_failures"] == [] and summary["committed_batches"] == 4
    assert_same_dataset(uninterrupted, tmp_path)


def _staging_uncommitted(root: Path) -> list[str]:
    """Level batches ("shard-000000/batch-001") with a staging marker and no commit record: a worker is writing."""
    staging = root / STAGING_DIR
    marked = {f"{shard.name}/{batch.name}" for shard in staging.glob("shard-*") for batch in shard.glob("batch-*")}
    return sorted(key for key in marked if not (root / MANIFEST_DIR / f"{key}.json").exists())


@pytest.mark.slow
def test_a_worker_killed_while_staging_is_replaced_and_nothing_is_lost_or_duplicated(
    uninterrupted_keeping, keeping_cache, tmp_path
):
    output = tmp_path / "dataset"
    config_file = tmp_path / "job.yaml"
    config_file.write_text(to_yaml(keeping_job(output, keeping_cache, "ray.num_workers=1")))
    process = start_job(config_file, "--json")
    killed = None
    try:
        deadline = time.monotonic() + JOB_TIMEOUT_SECONDS
        while killed is None and process.poll() is None and time.monotonic() < deadline:
            if _committed(output) >= 1 and (staging := _staging_uncommitted(output)):
                killed = staging, actor_processes(process.pid)
                for pid in killed[1]:  # SIGKILL of the worker's process while it writes a level batch
                    os.kill(pid, signal.SIGKILL)
            time.sleep(0.01)
        out, err = process.communicate(timeout=JOB_TIMEOUT_SECONDS)
    finally:
        kill_session(process.pid)
    assert killed is not None and len(killed[1]) == 1, (killed, err.decode()[-3000:])
    assert process.returncode == 0, err.decode()[-3000:]
    summary = json_summary(out)
    assert len(summary["worker_failures"]) == 1 and summary["abandoned_shards"] == []
    cause = summary["worker_failures"][0]["error"]
    assert cause.startswith("ActorDiedError: ") and summary["worker_failure_causes"] == [f"1 {cause}"], cause
    assert [path for path in (output / STAGING_DIR).rglob("*") if path.is_file()] == []  # every marker committed
    assert_keeps_in_every_batch(output)
    assert all(report.ok for report in verify_dataset(output))
    assert_same_dataset(uninterrupted_keeping, output)


def _committed(root: Path) -> int:
    return committed_count(root)


@pytest.mark.slow
def test_a_job_killed_at_several_points_and_resumed_equals_an_uninterrupted_run(
    uninterrupted_keeping, keeping_cache, tmp_path
):
    output = tmp_path / "dataset"
    config_file = tmp_path / "job.yaml"
    # A killed job leaves its lease behind: the next run takes it over once its heartbeat is a second old.
    job = keeping_job(output, keeping_cache, "lease.stale_after_s=1", "lease.heartbeat_s=0.25")
    config_file.write_text(to_yaml(job))
    kill_points = {
        "dataset created, nothing committed": lambda: (output / "data" / "zarr.json").exists(),
        "first level batch committed": lambda: _committed(output) >= 1,
        "shard 0 done, shard 1 started": lambda: _committed(output) >= 3,
    }
    kill_at_points(config_file, kill_points)
    assert _committed(output) < KEEPING_BATCHES  # the last kill came before the end
    run_job_process(config_file)
    assert_keeps_in_every_batch(output)
    assert all(report.ok for report in verify_dataset(output))
    assert_same_dataset(uninterrupted_keeping, output)


# ------------------------------------------------------------------------------------------- repair and growth


def _flip_byte(path: Path, offset: int = 10) -> None:
    data = bytearray(path.read_bytes())
    data[offset] ^= 0xFF
    path.write_bytes(bytes(data))


def test_a_damaged_commit_is_refused_by_run_repaired_by_verify_and_regenerated_identically(
    uninterrupted, tmp_path, capsys
):
    root = tmp_path / "dataset"
    shutil.copytree(uninterrupted, root)
    _flip_byte(Path(root) / record_key(1, 0))  # the tiny job keeps no trajectory, so its damage is in a commit record
    with pytest.raises(
        DatasetDamaged,
        match=r"1 committed level batches have missing, unreadable or damaged files .*"
        r"run `kforge verify --repair",
    ):
        run_job(tiny_job(root), show_progress=False)  # refused before anything starts
    with pytest.raises(SystemExit) as exit_info:
        verify_main([str(root)])
    assert exit_info.value.code == EXIT_DATA
    assert f"kforge verify --repair {root}" in capsys.readouterr().err
    verify_main([str(root), "--repair"])
    out = capsys.readouterr().out
    assert "withdrew the commit of shard-000001 batch 0: unreadable record" in out
    assert f"repaired: 1 level batches to regenerate; next: kforge run {root / 'config.yaml'}" in out
    assert committed_batches(root, 1) == [1]
    run_in_process(tiny_job(root))
    assert_same_dataset(uninterrupted, root)


def test_a_complete_dataset_is_reported_without_starting_ray_or_tracking(uninterrupted, tmp_path):
    root = tmp_path / "dataset"
    shutil.copytree(uninterrupted, root)
    logs = sorted((root / "logs").iterdir())  # the first run's
    lines = []
    summary = run_job(tiny_job(root), show_progress=False, report=lines.append)
    assert lines == ["resuming: found 4 of 4 level batches committed; nothing remains"]
    assert (summary["committed_batches"], summary["committed_in_run"], summary["log_file"]) == (4, 0, None)
    assert sorted((root / "logs").iterdir()) == logs


def test_a_job_without_ray_told_to_asks_for_deterministic_gpu_ops_in_its_process(uninterrupted, tmp_path, monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", "--xla_force_host_platform_device_count=1")  # restored after the test
    root = tmp_path / "dataset"
    shutil.copytree(uninterrupted, root)
    run_job(tiny_job(root, "ray.num_workers=0"), show_progress=False)  # by default it leaves XLA's flags alone
    assert os.environ["XLA_FLAGS"] == "--xla_force_host_platform_device_count=1"
    told = tiny_job(root, "ray.num_workers=0", "ray.deterministic_gpu_ops=true")
    run_job(told, show_progress=False)  # the dataset is complete: it computes nothing, but asks first
    assert os.environ["XLA_FLAGS"].split() == [
        "--xla_force_host_platform_device_count=1",
        "--xla_gpu_deterministic_ops=true",
    ]


def test_raising_num_levels_grows_the_dataset_to_equal_one_made_at_the_larger_count(uninterrupted, tmp_path):
    root = tmp_path / "dataset"
    run_in_process(tiny_job(root, "split.num_levels=3"))  # one shard: levels 0-1, then 2 and a padding slot
    assert committed_batches(root, 0) == [0, 1]
    withdrawn = prepare_output(resolve(tiny_job(root)))  # 6 levels: the padding slot becomes level 3, shard 1 is added
    assert withdrawn == [(0, 1)] and committed_batches(root, 0) == [0]
    assert open_dataset(root).geometry.num_shards == 2
    run_in_process(tiny_job(root))
    assert_same_dataset(uninterrupted, root)
    with pytest.raises(ResumeRefused, match=r"holds 6 levels; split\.num_levels=4 would shrink it"):
        prepare_output(resolve(tiny_job(root, "split.num_levels=4")))


def test_an_interrupted_growth_leaves_a_dataset_that_opens_and_growing_again_finishes_it(tmp_path):
    prepare_output(resolve(tiny_job(tmp_path, "split.num_levels=4")))
    small_group = (tmp_path / "data" / "zarr.json").read_text()
    prepare_output(resolve(tiny_job(tmp_path)))
    (tmp_path / "data" / "zarr.json").write_text(small_group)  # arrays grown, the group's spec not yet
    dataset = open_dataset(tmp_path)
    assert dataset.geometry.num_shards == 1 and dataset.array("done").shape[0] == 8  # longer arrays open
    assert dataset.read(["done"], range(0, 4))["done"].shape == (4, 24)
    prepare_output(resolve(tiny_job(tmp_path)))
    assert open_dataset(tmp_path).geometry.num_shards == 2


def test_the_config_is_written_atomically(tmp_path):
    prepare_output(resolve(tiny_job(tmp_path)))
    # No temp file left; manifest/ comes with the first commit.
    assert sorted(path.name for path in tmp_path.iterdir()) == ["config.yaml", "data"]
    assert load_config(tmp_path / "config.yaml").output_dir == str(tmp_path)


def test_a_failed_ray_start_finishes_the_tracked_run(tmp_path, monkeypatch):
    import wandb

    monkeypatch.delenv("WANDB_MODE")
    job = tiny_job(tmp_path, "tracking.wandb=offline", "ray.address=not-an-address")
    with pytest.raises(ValueError, match="not-an-address"):
        run_job(job, show_progress=False)
    assert wandb.run is None  # finished (marked failed), not left open
    assert len(list((tmp_path / "logs" / "wandb").glob("offline-run-*"))) == 1


# ------------------------------------------------------------------------------------ interrupting a real job


def _worker_started(session: int) -> bool:
    """A Ray worker actor of the job's session has started (the job is at work)."""
    for pid in session_processes(session):
        with contextlib.suppress(OSError):
            if b"ray::Worker" in Path(f"/proc/{pid}/cmdline").read_bytes():
                return True
    return False


def _run_logs(output: Path) -> int:
    return len(list((output / "logs").glob("run-*.log")))


@pytest.mark.parametrize(
    "whom, workers",
    [
        ("SIGINT to the terminal's process group", 1),
        ("SIGTERM to the driver", 1),
        ("SIGTERM to a job without Ray", 0),
    ],
)
def test_a_signal_ends_the_job_with_one_line_naming_what_was_committed_and_how_to_resume(whom, workers, tmp_path):
    output = tmp_path / "dataset"
    config_file = tmp_path / "job.yaml"
    config_file.write_text(to_yaml(tiny_job(output, f"ray.num_workers={workers}")))
    run_in_process(tiny_job(output), max_batches=1)
    logs = _run_logs(output)
    command = [sys.executable, "-m", "kforge", "run", str(config_file), "--no-progress"]
    process = subprocess.Popen(
        command,
        start_new_session=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env={**os.environ, "RAY_AUTH_MODE": "disabled"},
        preexec_fn=as_a_terminal_job,
    )
    try:
        deadline = time.monotonic() + JOB_TIMEOUT_SECONDS
        # At work: a Ray worker actor has started, or the job without Ray has opened its run's log.
        at_work = (lambda: _worker_started(process.pid)) if workers else (lambda: _run_logs(output) > logs)
        while not at_work() and process.poll() is None and time.monotonic() < deadline:
            time.sleep(POLL_SECONDS)
        if whom.startswith("SIGINT"):
            os.killpg(process.pid, signal.SIGINT)  # what Ctrl-C does
        else:
            os.kill(process.pid, signal.SIGTERM)  # what a scheduler does
        out, err = process.communicate(timeout=KILL_WAIT_SECONDS * 4)
    finally:
        kill_session(process.pid)
    err = err.decode()
    assert process.returncode == EXIT_INTERRUPTED, err[-3000:]
    assert out == b"" and "Traceback" not in err and "\x1b[" not in err  # no colour codes off a terminal
    assert err.splitlines() == [
        "resuming: found 1 of 4 level batches committed; 3 remain",
        f"interrupted: {_committed(output)} of 4 level batches committed in {output} ({_committed(output) - 1} in "
        f"this run); resume with: kforge run {config_file} --no-progress",
    ]
