"""Training progress of the level batches in flight: worker reports, the coordinator's view, the progress bar."""

from pipeline_test_helpers import tiny_job

from pipeline.generation.coordinator import Coordinator
from pipeline.generation.level_batch import batches_per_shard, num_shards
from pipeline.generation.run import _training_summary, prepare_output
from pipeline.generation.worker import Worker
from pipeline.storage import Lease


def _coordinator(tmp_path):
    return Coordinator(tmp_path, num_shards=2, batches_per_shard=2)


def test_the_coordinator_keeps_reports_of_claimed_batches_until_commit_or_release(tmp_path):
    coordinator = _coordinator(tmp_path)
    coordinator.report_training(0, 0, 5, 10)  # not claimed: ignored
    assert coordinator.training() == {}
    shard = coordinator.next_shard("w")
    first, second = coordinator.claim_batch(shard), coordinator.claim_batch(shard)
    coordinator.report_training(shard, first, 5, 10)
    coordinator.report_training(shard, second, 1, 4)
    assert coordinator.training() == {(shard, first): 0.5, (shard, second): 0.25}
    coordinator.commit(shard, first, {"levels": []})
    coordinator.report_training(shard, first, 10, 10)  # arrived after its commit: ignored
    assert coordinator.training() == {(shard, second): 0.25}
    coordinator.release(shard)  # the worker failed: its batch is no longer in flight
    assert coordinator.training() == {}


class _RecordingCoordinator(Coordinator):
    def __init__(self, *args):
        super().__init__(*args)
        self.reports = []

    def report_training(self, shard, batch, updates_done, num_updates):
        self.reports.append((shard, batch, updates_done, num_updates))
        super().report_training(shard, batch, updates_done, num_updates)


def test_a_worker_reports_each_batch_fully_trained_before_it_commits(tmp_path):
    job = tiny_job(tmp_path / "out")
    with Lease.acquire(job.output_dir) as lease:  # a worker writes under its job's lease
        prepare_output(job)
        args = (job.output_dir, num_shards(job), batches_per_shard(job), None, lease.holder.job_id)
        coordinator = _RecordingCoordinator(*args)
        shard = coordinator.next_shard("local")
        Worker(job, "local").run_shard(coordinator, shard)
    # The tiny job: 256 env steps of 4 envs x 16 steps = 4 updates per level in one evaluation segment; the program
    # reports its start, the worker the end.
    assert coordinator.reports == [(shard, 0, 0, 4), (shard, 0, 4, 4), (shard, 1, 0, 4), (shard, 1, 4, 4)]
    assert coordinator.training() == {}  # both committed
    assert coordinator.progress() == (2, 4)


def test_the_progress_bar_lists_a_few_batches_and_averages_many():
    assert _training_summary({}) == ""
    assert _training_summary({(0, 1): 0.4}) == "training 1 batch: 40%"
    assert _training_summary({(1, 0): 0.95, (0, 3): 0.4}) == "training 2 batches: 40% 95%"
    many = {(shard, 0): share for shard, share in enumerate([0.1, 0.2, 0.3, 0.4, 0.5])}
    assert _training_summary(many) == "training 5 batches: mean 30%"
