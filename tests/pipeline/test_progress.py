"""What a run shows while it works: worker reports, the coordinator's view of the batches in flight (compiling,
training), the progress bar's text and time left, the --max-batches budget, the closing summary and the log file."""

import logging
from pathlib import Path

from pipeline_test_helpers import tiny_job

from kforge.pipeline.generation.console import (
    QUIET_ENV,
    THIRD_PARTY_LOGGERS,
    closing_summary,
    in_flight_summary,
    log_dir,
    resume_line,
    start_log_file,
)
from kforge.pipeline.generation.coordinator import Coordinator
from kforge.pipeline.generation.level_batch import batches_per_shard, num_shards
from kforge.pipeline.generation.resolved import resolve
from kforge.pipeline.generation.run import prepare_output
from kforge.pipeline.generation.worker import Worker
from kforge.pipeline.storage import Lease


def _coordinator(tmp_path, max_batches=None):
    return Coordinator(tmp_path, num_shards=2, batches_per_shard=2, max_batches=max_batches)


def test_the_coordinator_keeps_reports_of_claimed_batches_until_commit_or_release(tmp_path):
    coordinator = _coordinator(tmp_path)
    coordinator.report_training(0, 0, 5, 10)  # not claimed: ignored
    assert coordinator.training() == {}
    shard = coordinator.next_shard("w")
    first, second = coordinator.claim_batch(shard, "w"), coordinator.claim_batch(shard, "w")
    coordinator.report_training(shard, first, 5, 10)
    coordinator.report_training(shard, second, 1, 4)
    assert coordinator.training() == {(shard, first): 0.5, (shard, second): 0.25}
    coordinator.commit(shard, first, {"levels": []}, "w")
    coordinator.report_training(shard, first, 10, 10)  # arrived after its commit: ignored
    assert coordinator.training() == {(shard, second): 0.25}
    coordinator.release(shard)  # the worker failed: its batch is no longer in flight
    assert coordinator.training() == {}


def test_batches_in_flight_are_compiling_until_their_worker_reports_or_has_committed(tmp_path):
    coordinator = _coordinator(tmp_path)
    a, b = coordinator.next_shard("a"), coordinator.next_shard("b")
    coordinator.claim_batch(a, "a"), coordinator.claim_batch(b, "b")
    assert coordinator.in_flight() == {(0, 0): "compiling", (1, 0): "compiling"}
    coordinator.report_training(a, 0, 2, 8)
    assert coordinator.in_flight() == {(0, 0): 0.25, (1, 0): "compiling"}
    coordinator.commit(a, 0, {"levels": []}, "a")
    coordinator.claim_batch(a, "a")  # worker a's programs are compiled: its next batch is only starting
    assert coordinator.in_flight() == {(0, 1): "starting", (1, 0): "compiling"}


def test_the_progress_text_shows_compiling_and_training_batches_apart():
    assert in_flight_summary({}) == ""
    assert in_flight_summary({(0, 0): "compiling", (1, 0): "compiling"}) == "compiling 2 batches"
    assert in_flight_summary({(0, 1): 0.4}) == "training 1 batch: 40%"
    mixed = {(1, 0): 0.95, (0, 3): 0.4, (2, 0): "compiling", (3, 0): "starting", (4, 0): 1.0}
    expected = "compiling 1 batch, starting 1 batch, training 2 batches: 40% 95%, collecting 1 batch"
    assert in_flight_summary(mixed) == expected
    many = {(shard, 0): share for shard, share in enumerate([0.1, 0.2, 0.3, 0.4, 0.5])}
    assert in_flight_summary(many) == "training 5 batches: mean 30%"


def test_a_resumed_run_says_what_it_found():
    assert resume_line(0, 4, 0) is None  # a new dataset
    assert resume_line(3, 4, 0) == "resuming: found 3 of 4 level batches committed; 1 remain"
    assert resume_line(4, 4, 0) == "resuming: found 4 of 4 level batches committed; nothing remains"
    grown = resume_line(2, 6, 1)
    assert (
        grown == "resuming: found 2 of 6 level batches committed (1 level batch withdrawn to grow the split); 4 remain"
    )


def test_max_batches_counts_commits_so_a_failed_claim_does_not_use_up_the_budget(tmp_path):
    coordinator = _coordinator(tmp_path, max_batches=2)
    shard = coordinator.next_shard("w")
    assert coordinator.claim_batch(shard, "w") == 0
    coordinator.release(shard)  # the worker died before committing
    shard = coordinator.next_shard("w2")
    assert (coordinator.claim_batch(shard, "w2"), coordinator.claim_batch(shard, "w2")) == (0, 1)
    assert coordinator.claim_batch(shard, "w2") is None  # two in flight: the budget is reached
    coordinator.commit(shard, 0, {"levels": []}, "w2")
    coordinator.commit(shard, 1, {"levels": []}, "w2")
    coordinator.release(shard)
    assert coordinator.next_shard("w2") is None  # exactly two committed
    assert coordinator.progress() == (2, 4)


class _RecordingCoordinator(Coordinator):
    def __init__(self, *args):
        super().__init__(*args)
        self.reports = []

    def report_training(self, shard, batch, updates_done, num_updates):
        self.reports.append((shard, batch, updates_done, num_updates))
        super().report_training(shard, batch, updates_done, num_updates)


def test_a_worker_reports_each_batch_fully_trained_before_it_commits(tmp_path):
    job = resolve(tiny_job(tmp_path / "out"))
    with Lease.acquire(job.config.output_dir) as lease:  # a worker writes under its job's lease
        prepare_output(job)
        args = (job.config.output_dir, num_shards(job), batches_per_shard(job), None, lease.holder.job_id)
        coordinator = _RecordingCoordinator(*args)
        shard = coordinator.next_shard("local")
        Worker(job, "local").run_shard(coordinator, shard)
    # The tiny job: 256 env steps of 4 envs x 16 steps = 4 updates per level. Each batch reports 0 of 4 once its
    # program is compiled, all 4 once trained, and between them, where the program ran before in this process,
    # estimates from its time then (never all 4, never going back).
    for batch in (0, 1):
        reports = [report[2:] for report in coordinator.reports if report[:2] == (shard, batch)]
        done = [updates_done for updates_done, _ in reports]
        assert reports[0] == (0, 4) and reports[-1] == (4, 4) and {total for _, total in reports} == {4}
        assert done[1:-1] == sorted(done[1:-1]) and all(0 <= d < 4 for d in done[1:-1]), reports
    assert [report[1] for report in coordinator.reports] == sorted(report[1] for report in coordinator.reports)
    assert coordinator.training() == {}  # both committed
    assert coordinator.progress() == (2, 4)


def test_the_closing_summary_says_what_was_made_where_and_what_to_run_next(tmp_path):
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "chunk").write_bytes(b"x" * 3000)
    (tmp_path / "manifest").mkdir()
    summary = {
        "committed_batches": 3,
        "total_batches": 4,
        "committed_in_run": 2,
        "levels": 6,
        "outcomes": {"kept": 2, "unsolved": 1, "failed": 0, "filtered:trivial": 2, "filtered:no_actuator": 1},
        "seconds": 75.0,
        "worker_failures": [{"shard": 1}, {"shard": 2}, {"shard": 2}],
        "worker_failure_causes": [
            "2 OutOfMemoryError: Task was killed due to the node running low on memory.",
            "1 ActorDiedError: The actor died unexpectedly before finishing this task.",
        ],
        "abandoned_shards": [],
        "log_file": str(tmp_path / "logs" / "run-1.log"),
    }
    assert closing_summary(summary, tmp_path).splitlines() == [
        f"dataset incomplete: 1 of 4 level batches remain: {tmp_path} (2.9 KiB)",
        "levels: 6 sampled, 3 filtered (no_actuator 1, trivial 2), 2 kept, 1 unsolved, 0 failed",
        "this run: 2 level batches committed in 01:15, 3 worker failures (2 OutOfMemoryError: Task was killed due to "
        "the node running low on memory.; 1 ActorDiedError: The actor died unexpectedly before finishing this task.)",
        f"third-party logs: {tmp_path / 'logs' / 'run-1.log'}",
        "next:",
        f"  kforge run {tmp_path / 'config.yaml'}    # continue",
        f"  kforge verify {tmp_path}",
        f"  kforge stats {tmp_path}",
        f"  python -c \"from kforge import TrajectoryDatasetManager as M; print(M('{tmp_path}', "
        'batch_size=2, seed=0).load_next_batch().action.shape)"',
        f"  kforge bc train {tmp_path}    # behaviour cloning on it, then kforge evaluate on the run it prints",
    ]


def test_third_party_logs_go_to_the_log_file_and_to_the_terminal_only_when_verbose(tmp_path, capfd, monkeypatch):
    for name, value in QUIET_ENV.items():
        monkeypatch.setenv(name, value)  # restored after the test
    for name in THIRD_PARTY_LOGGERS:
        logger = logging.getLogger(name)
        monkeypatch.setattr(logger, "handlers", list(logger.handlers))
        monkeypatch.setattr(logger, "propagate", logger.propagate)
    quiet = start_log_file(tmp_path / "quiet", verbose=False)
    logging.getLogger("ray").warning("raylet says hello")
    assert "raylet says hello" in quiet.read_text() and "raylet says hello" not in capfd.readouterr().err
    assert quiet.parent == tmp_path / "quiet" / "logs"
    loud = start_log_file(tmp_path / "loud", verbose=True)
    logging.getLogger("wandb").warning("wandb says hello")
    assert "wandb says hello" in loud.read_text() and "wandb says hello" in capfd.readouterr().err


def test_a_remote_datasets_log_folder_stays_under_the_remote_log_root():
    assert log_dir("s3://bucket/runs/a") == Path("outputs/remote-logs/bucket/runs/a/logs")
    assert log_dir("s3://bucket/../../etc/./x/") == Path("outputs/remote-logs/bucket/etc/x/logs")
    assert log_dir("gs://bucket/..") == Path("outputs/remote-logs/bucket/logs")
