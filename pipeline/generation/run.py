"""Generating a split's dataset with Ray workers, or in one process without Ray (`kforge run`): re-running on the
same directory resumes it (after checking its committed files), a larger `split.num_levels` grows it, SIGINT and
SIGTERM stop it keeping every committed level batch."""

from __future__ import annotations

import collections
import os
import signal
import threading
import time
import warnings
from typing import NamedTuple

from kforge.engine import use_deterministic_ops
from kforge.env import ActionType
from kforge.pipeline.generation.config_yaml import to_yaml
from kforge.pipeline.generation.console import ProgressBar, resume_line, start_log_file
from kforge.pipeline.generation.coordinator import Coordinator, ShardNotHeld
from kforge.pipeline.generation.definition import data_definition, data_fingerprint
from kforge.pipeline.generation.growth import reconcile_dataset
from kforge.pipeline.generation.level_batch import batches_per_shard, num_shards
from kforge.pipeline.generation.resolved import ResolvedJob, resolve
from kforge.pipeline.generation.schema import JobConfig
from kforge.pipeline.generation.tracking import Tracker, start_tracking
from kforge.pipeline.generation.worker import Worker
from kforge.pipeline.storage import (
    CONFIG_FILE,
    DatasetSpec,
    Geometry,
    Lease,
    LeaseLost,
    Outcome,
    all_committed,
    commit_age_limit,
    create_dataset,
    iter_records,
    make_layout,
    open_store,
    require_intact,
)

RAY_NAMESPACE = "kforge"
PROGRESS_POLL_SECONDS = 2.0
COORDINATOR_RESTARTS = -1
"""Ray restarts a dead coordinator actor (and retries the calls to it) without limit: it rebuilds its state from the
commit records, so a restart costs no committed work."""
COORDINATOR_ACTOR = "kforge-coordinator-{job_id}"
"""Name of a job's coordinator actor in its Ray namespace (an operator or a test finds it with `ray.get_actor`)."""
MAX_SHARD_ATTEMPTS = 3
"""A shard whose worker fails this many times in one run is abandoned for the run (committed batches stay)."""
IN_PROCESS = 0
"""`ray.num_workers` that runs the job without Ray: its own process does the work, one level batch after another."""
IN_PROCESS_WORKER = "local"
"""The name the commit records give the job's own process as worker."""
RAY_QUIET_ENV = {"RAY_AUTH_MODE": "disabled", "RAY_USAGE_STATS_ENABLED": "0"}
"""Embedded local Ray: no token auth (a private, single-user instance) and no usage reporting."""


def dataset_spec(job: ResolvedJob) -> DatasetSpec:
    """What the dataset directory must hold for this job: layout, geometry, split, and the data-defining config."""
    return DatasetSpec(
        layout=make_layout(job.static, ActionType.MULTI_DISCRETE, num_steps=job.collect.window_steps),
        geometry=Geometry(num_shards(job), batches_per_shard(job), job.work.levels_per_batch),
        split=job.split.name,
        attributes={
            "data_fingerprint": data_fingerprint(job),
            "data_config": data_definition(job),
        },
    )


def prepare_output(job: ResolvedJob) -> list[tuple[int, int]]:
    """Create the dataset, or check that an existing one was made with the same data-defining config and grow it if
    the job has more levels (`reconcile_dataset`); returns the commits growing withdrew.

    Call it under the job's lease on the dataset (`Lease.acquire`). config.yaml is written as one object (atomic on
    a filesystem and on object stores)."""
    output_dir = job.config.output_dir
    store = open_store(output_dir)
    spec = dataset_spec(job)
    withdrawn = reconcile_dataset(output_dir, spec) if store.exists("data/zarr.json") else []
    create_dataset(store, spec)
    store.write(CONFIG_FILE, to_yaml(job.config).encode())
    return withdrawn


def run_job(
    job: JobConfig,
    max_batches: int | None = None,
    show_progress: bool = True,
    verbose: bool = False,
    report=print,
) -> dict:
    """Generate (or resume, or grow) the job's dataset; returns the summary. `max_batches` stops after that many
    level batches. Third-party logs go to the dataset's log file (and the terminal too if `verbose`); `report` gets
    the lines an operator reads (what a resumed run found). SIGINT and SIGTERM end it with `JobInterrupted`; a
    dataset whose commits name missing or damaged files is refused with `DatasetDamaged`. The job holds the
    dataset's lease while it runs (`LeaseHeld` if another job does). Without Ray (`ray.num_workers=0`), XLA's
    deterministic GPU ops (`ray.deterministic_gpu_ops`) apply to this process only if it has not computed with JAX
    before the call, as under `kforge run`. The job is resolved once, here (`resolve`): the driver and every worker
    take its settings from that."""
    if job.ray.num_workers == IN_PROCESS and job.ray.deterministic_gpu_ops:
        use_deterministic_ops()  # before this process's first computation (XLA reads its flags once)
    resolved = resolve(job)  # computes nothing with JAX: plain values, which workers receive as they are
    lease = Lease.acquire(job.output_dir, job.lease.stale_after_s, job.lease.heartbeat_s)
    try:
        return _run_leased(resolved, lease, max_batches, show_progress, verbose, report)
    finally:
        lease.release()


def _run_leased(
    resolved: ResolvedJob, lease: Lease, max_batches: int | None, show_progress: bool, verbose: bool, report
):
    """`run_job` while holding the dataset's lease."""
    job = resolved.config
    withdrawn = prepare_output(resolved)
    require_intact(job.output_dir, then="this command again", read_objects=False)  # records and a listing
    total = num_shards(job) * batches_per_shard(job)
    found = _committed_count(job)
    if (line := resume_line(found, total, len(withdrawn))) is not None:
        report(line)
    if found == total:  # nothing to do: no Ray, no tracked run, no log file
        return _run_summary(job, (found, total), 0.0, WorkerFailures(), None)
    log_file = start_log_file(job.output_dir, verbose)
    previous_handler = signal.signal(signal.SIGTERM, _terminate_as_interrupt) if _main_thread() else None
    started = time.perf_counter()
    failures = WorkerFailures()
    tracker = None
    try:
        tracker = start_tracking(resolved)
        max_lease_age_s = commit_age_limit(job.lease.stale_after_s, job.lease.heartbeat_s)
        shards = (
            job.output_dir,
            num_shards(job),
            batches_per_shard(job),
            max_batches,
            lease.holder.job_id,
            max_lease_age_s,
        )
        bar = ProgressBar(found, total, enabled=show_progress)
        try:
            if job.ray.num_workers == IN_PROCESS:
                _work_in_process(resolved, _Observed(Coordinator(*shards), lease, tracker, bar), failures)
            else:
                _work_on_ray(resolved, shards, _Driver(lease, tracker, bar, failures), verbose, previous_handler)
        finally:
            bar.close()
    except KeyboardInterrupt:
        if tracker is not None:
            tracker.finish()  # marks the tracked run failed
        committed = _committed_count(job)
        raise JobInterrupted(job.output_dir, committed, total, committed - found) from None
    except BaseException:
        if tracker is not None:
            tracker.finish()  # marks the tracked run failed
        raise
    finally:
        if previous_handler is not None:
            signal.signal(signal.SIGTERM, previous_handler)
    summary = _run_summary(job, (found, total), time.perf_counter() - started, failures, log_file)
    tracker.finish(summary)
    return summary


class WorkerFailures:
    """The failed attempts of workers at shards in one run, each with its cause in one line (`failure_cause`)."""

    def __init__(self):
        self.records: list[dict] = []  # {"shard", "worker", "error": the cause}, in the order they failed
        self.attempts: collections.Counter = collections.Counter()  # shard -> failed attempts

    def add(self, shard: int, worker: str, cause: str) -> bool:
        """Record a failed attempt; returns whether the shard is now abandoned (`MAX_SHARD_ATTEMPTS`)."""
        self.attempts[shard] += 1
        self.records.append({"shard": shard, "worker": worker, "error": cause})
        return self.attempts[shard] >= MAX_SHARD_ATTEMPTS

    def abandoned(self) -> list[int]:
        """The shards abandoned for this run, in order."""
        return sorted(shard for shard, count in self.attempts.items() if count >= MAX_SHARD_ATTEMPTS)

    def by_cause(self) -> list[str]:
        """The failures counted by cause ("2 ActorDiedError: The actor died unexpectedly ..."), the most frequent
        first (ties in the order they first happened)."""
        causes = collections.Counter(record["error"] for record in self.records)
        return [f"{count} {cause}" for cause, count in causes.most_common()]


def failure_cause(error: BaseException) -> str:
    """Why a worker's attempt failed, in one line: the exception's type and the first line of its message; for an
    exception raised in the worker's own code (Ray's `RayTaskError` wraps it as its `cause`), that exception's."""
    cause = getattr(error, "cause", None)
    shown = cause if isinstance(cause, BaseException) else error
    message = str(shown).strip().splitlines()
    return f"{type(shown).__name__}: {message[0]}" if message else type(shown).__name__


class _Driver(NamedTuple):
    """What the driver keeps up while Ray workers run: the dataset's lease, the tracked run, the progress bar, and
    the workers' failures."""

    lease: Lease
    tracker: Tracker
    bar: ProgressBar
    failures: WorkerFailures


def _work_on_ray(job: ResolvedJob, shards: tuple, driver: _Driver, verbose: bool, sigterm_handler) -> None:
    """Run the coordinator (`Coordinator(*shards)`) as an actor and `ray.num_workers` worker actors until no shard
    is left: a failed shard is recorded in `driver.failures` and handed out again, up to `MAX_SHARD_ATTEMPTS` times;
    a dead or unreachable worker is killed (`ray.kill`: one unreachable but alive must not write beside its
    successor) and replaced. Ray restarts a dead coordinator, which rebuilds its state from the commit records. The
    actors are killed when the run ends, also when the caller started Ray (an interrupt leaves no worker writing)."""
    import ray

    for name, value in RAY_QUIET_ENV.items():
        os.environ.setdefault(name, value)
    started_ray = not ray.is_initialized()
    if started_ray:
        _init_ray(job.config, verbose)
        if sigterm_handler is not None:  # Ray's own SIGTERM handler (a crash report) replaced ours
            signal.signal(signal.SIGTERM, _terminate_as_interrupt)
    actors = _RayActors(job)
    try:
        coordinator = actors.start_coordinator(shards, driver.lease.holder.job_id)
        for i in range(job.config.ray.num_workers):
            actors.assign(actors.start_worker(f"worker-{i}"), f"worker-{i}")
        while actors.in_flight:
            driver.lease.check()
            ready, _ = ray.wait(list(actors.in_flight), timeout=PROGRESS_POLL_SECONDS)
            for ref in ready:
                actors.finished(ref, driver)
            driver.tracker.log_commits(ray.get(coordinator.take_commits.remote()))
            driver.bar.show(ray.get(coordinator.progress.remote())[0], ray.get(coordinator.in_flight.remote()))
    finally:
        if started_ray:
            ray.shutdown()
        else:
            actors.kill_all()


class _RayActors:
    """A run's coordinator actor and worker actors on Ray, and the shard task each busy worker runs."""

    def __init__(self, job: ResolvedJob):
        import ray

        self._ray = ray
        self._job = job
        self._worker_class = None
        self.coordinator = None
        self.started: list = []  # every actor started, to kill when the run ends
        self.in_flight: dict = {}  # shard task -> (worker, its name, shard)

    def start_coordinator(self, shards: tuple, job_id: str):
        """Start the coordinator actor, `Coordinator(*shards)` (named after `job_id`; Ray restarts it if it dies),
        before any worker."""
        coordinator_class = self._ray.remote(Coordinator).options(
            name=COORDINATOR_ACTOR.format(job_id=job_id),
            num_cpus=0,
            max_restarts=COORDINATOR_RESTARTS,
            max_task_retries=COORDINATOR_RESTARTS,
        )
        self.coordinator = coordinator_class.remote(*shards)
        self.started.append(self.coordinator)
        self._worker_class = self._ray.remote(Worker).options(
            num_cpus=self._job.config.ray.cpus_per_worker, num_gpus=self._job.config.ray.gpus_per_worker
        )
        return self.coordinator

    def start_worker(self, name: str):
        """Start a worker actor called `name`, with the driver's resolved job."""
        worker = self._worker_class.remote(self._job, name)
        self.started.append(worker)
        return worker

    def assign(self, worker, name: str) -> None:
        """Give the worker its next shard, or kill it if none is left (its CPUs go to a replacement still waiting
        for a node with room)."""
        shard = self._ray.get(self.coordinator.next_shard.remote(name))
        if shard is not None:
            self.in_flight[worker.run_shard.remote(self.coordinator, shard)] = (worker, name, shard)
        else:
            self._ray.kill(worker, no_restart=True)

    def finished(self, ref, driver: _Driver) -> None:
        """Settle a finished shard task: record a failure, release the shard, replace a dead or unreachable worker,
        and give the worker its next shard."""
        worker, name, shard = self.in_flight.pop(ref)
        error = None
        try:
            self._ray.get(ref)
        except self._ray.exceptions.RayError as raised:
            error = raised
            self._record_failure(error, shard, name, driver)
        self._ray.get(self.coordinator.release.remote(shard, name))
        if isinstance(error, self._ray.exceptions.RayActorError):  # dead, or unreachable and maybe alive
            self._ray.kill(worker, no_restart=True)
            name = f"{name.partition('-restart')[0]}-restart{len(self.started)}"
            worker = self.start_worker(name)
        self.assign(worker, name)

    def _record_failure(self, error: BaseException, shard: int, name: str, driver: _Driver) -> None:
        """Count a failed task as an attempt at its shard, abandoning a poison shard for the run, unless the worker
        lost the lease or the shard (not the shard's fault)."""
        cause = getattr(error, "cause", None)
        if isinstance(cause, LeaseLost):
            driver.lease.fence()  # raises if another job took the lease; else the worker saw an old heartbeat
        if not isinstance(cause, LeaseLost | ShardNotHeld):
            if driver.failures.add(shard, name, failure_cause(error)):
                self._ray.get(self.coordinator.abandon.remote(shard))  # a poison shard: left for a later run

    def kill_all(self) -> None:
        """Kill every actor this run started."""
        for started in self.started:
            self._ray.kill(started, no_restart=True)


def _work_in_process(job: ResolvedJob, coordinator: _Observed, failures: WorkerFailures) -> None:
    """The work of `_work_on_ray` in this process, without Ray: one worker takes shard after shard; a shard whose
    work raises is recorded and handed out again as on Ray (a crash of the process ends the run, as an interrupt)."""
    worker = Worker(job, IN_PROCESS_WORKER)
    while (shard := coordinator.next_shard(IN_PROCESS_WORKER)) is not None:
        try:
            worker.run_shard(coordinator, shard)
        except LeaseLost:
            raise
        except Exception as error:  # contained as a failed Ray task would be
            if failures.add(shard, IN_PROCESS_WORKER, failure_cause(error)):
                coordinator.abandon(shard)
        coordinator.release(shard, IN_PROCESS_WORKER)


class _Observed:
    """A coordinator in this process whose claims check the lease (`Lease.check`) and whose commits fence it
    (`Lease.fence`), and which logs the commits and redraws the progress bar (what the driver's polling loop does on
    Ray)."""

    def __init__(self, coordinator: Coordinator, lease: Lease, tracker, bar: ProgressBar):
        self._coordinator, self._lease, self._tracker, self._bar = coordinator, lease, tracker, bar
        self.release = coordinator.release
        self.abandon = coordinator.abandon
        self.job_id = coordinator.job_id

    def next_shard(self, worker: str) -> int | None:
        self._lease.check()
        return self._coordinator.next_shard(worker)

    def claim_batch(self, shard: int, worker: str) -> int | None:
        self._lease.check()
        return self._coordinator.claim_batch(shard, worker)

    def commit(self, shard: int, batch: int, record: dict, worker: str) -> bool:
        self._lease.fence()
        committed = self._coordinator.commit(shard, batch, record, worker)
        self._tracker.log_commits(self._coordinator.take_commits())
        self._show()
        return committed

    def report_training(self, shard: int, batch: int, updates_done: int, num_updates: int) -> None:
        self._coordinator.report_training(shard, batch, updates_done, num_updates)
        self._show()

    def _show(self) -> None:
        self._bar.show(self._coordinator.progress()[0], self._coordinator.in_flight())


def _run_summary(job, batches: tuple[int, int], seconds: float, failures: WorkerFailures, log_file) -> dict:
    """`summarize` of the dataset, with what this run did: batches committed (`batches`: committed before the run,
    and in all), time, worker failures (each, and counted by cause), abandoned shards, and the log file."""
    found, total = batches
    summary = summarize(job.output_dir)
    summary["total_batches"] = total
    summary["committed_in_run"] = summary["committed_batches"] - found
    summary["seconds"] = seconds
    summary["worker_failures"] = failures.records
    summary["worker_failure_causes"] = failures.by_cause()
    summary["abandoned_shards"] = failures.abandoned()
    summary["log_file"] = None if log_file is None else str(log_file)
    return summary


class JobInterrupted(Exception):
    """The run was stopped by SIGINT or SIGTERM; committed level batches stay, re-running resumes."""

    def __init__(self, output_dir: str, committed: int, total: int, committed_in_run: int):
        super().__init__(f"interrupted: {committed} of {total} level batches committed in {output_dir}")
        self.output_dir, self.committed, self.total = output_dir, committed, total
        self.committed_in_run = committed_in_run


def _committed_count(job: JobConfig) -> int:
    return sum(len(batches) for batches in all_committed(job.output_dir).values())


def _terminate_as_interrupt(signum, frame) -> None:
    raise KeyboardInterrupt


def _main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


def _init_ray(job: JobConfig, verbose: bool) -> None:
    """Start embedded local Ray, or connect to `ray.address`; Ray's own logs go to the run's log file (the "ray"
    logger, see `start_log_file`), workers' output to the terminal only if `verbose`."""
    import ray

    with warnings.catch_warnings():
        # Ray starts its processes with fork + exec, which JAX's fork warning cannot tell from a bare fork.
        warnings.filterwarnings("ignore", message="os.fork\\(\\) was called", category=RuntimeWarning)
        options = {"namespace": RAY_NAMESPACE, "log_to_driver": verbose, "configure_logging": False}
        if job.ray.address is None:
            ray.init(address="local", include_dashboard=False, **options)
        else:
            ray.init(address=job.ray.address, **options)


def summarize(root) -> dict:
    """Counts over the committed level batches: levels by outcome, kept trajectories, batches."""
    outcomes = collections.Counter()
    batches = 0
    for record in iter_records(root):
        batches += 1
        outcomes.update(str(level.outcome) for level in record.levels)
    levels = sum(count for outcome, count in outcomes.items() if outcome != Outcome.PADDING)
    return {"committed_batches": batches, "levels": levels, "outcomes": dict(sorted(outcomes.items()))}
