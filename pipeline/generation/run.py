"""Generating a split's dataset with Ray workers (`kforge run`); re-running on the same directory resumes it."""

from __future__ import annotations

import collections
import os
import time
import warnings

from tqdm import tqdm

from env import ActionType
from pipeline.generation.config import (
    JobConfig,
    data_definition,
    data_fingerprint,
    environment,
    to_yaml,
)
from pipeline.generation.coordinator import Coordinator
from pipeline.generation.level_batch import batches_per_shard, num_shards
from pipeline.generation.tracking import start_tracking
from pipeline.generation.worker import Worker
from pipeline.storage import (
    CONFIG_FILE,
    DatasetSpec,
    Geometry,
    Lease,
    Outcome,
    create_dataset,
    iter_records,
    make_layout,
    open_dataset,
    open_store,
)

RAY_NAMESPACE = "kforge"
PROGRESS_POLL_SECONDS = 2.0
MAX_SHARD_ATTEMPTS = 3
"""A shard whose worker fails this many times in one run is abandoned for the run (committed batches stay)."""
RAY_QUIET_ENV = {"RAY_AUTH_MODE": "disabled", "RAY_USAGE_STATS_ENABLED": "0"}
"""Embedded local Ray: no token auth (a private, single-user instance) and no usage reporting."""


class ResumeRefused(ValueError):
    """The output directory holds a dataset made with a config that would change the data."""


def dataset_spec(job: JobConfig) -> DatasetSpec:
    """What the dataset directory must hold for this job: layout, geometry, split, and the data-defining config."""
    _, static = environment(job)
    return DatasetSpec(
        layout=make_layout(static, ActionType.MULTI_DISCRETE, num_steps=job.collect.window_steps),
        geometry=Geometry(num_shards(job), batches_per_shard(job), job.work.levels_per_batch),
        split=job.split.name,
        attributes={
            "data_fingerprint": data_fingerprint(job),
            "data_config": data_definition(job),
        },
    )


def prepare_output(job: JobConfig) -> None:
    """Create the dataset, or check that an existing one was made with the same data-defining config.

    Call it under the job's lease on the dataset (`Lease.acquire`)."""
    store = open_store(job.output_dir)
    root = store.location
    spec = dataset_spec(job)
    if store.exists("data/zarr.json"):
        stored = open_dataset(store).spec
        if stored.attributes.get("data_fingerprint") != spec.attributes["data_fingerprint"]:
            changed = _changed_keys(stored.attributes.get("data_config", {}), spec.attributes["data_config"])
            raise ResumeRefused(
                f"{root} holds a dataset generated with a different config; these keys would change the data: "
                f"{', '.join(changed) or '(unknown: older dataset)'}. Use another output_dir or the original values."
            )
    create_dataset(store, spec)
    store.write(CONFIG_FILE, to_yaml(job).encode())


def _changed_keys(old: dict, new: dict, prefix: str = "") -> list[str]:
    keys = []
    for key in sorted(set(old) | set(new)):
        a, b = old.get(key), new.get(key)
        if isinstance(a, dict) and isinstance(b, dict):
            keys += _changed_keys(a, b, f"{prefix}{key}.")
        elif a != b:
            keys.append(f"{prefix}{key} ({a!r} -> {b!r})")
    return keys


def run_job(job: JobConfig, max_batches: int | None = None, show_progress: bool = True) -> dict:
    """Generate (or resume) the job's dataset; returns the summary. `max_batches` stops after that many batches."""

    lease = Lease.acquire(job.output_dir, job.lease.stale_after_s, job.lease.heartbeat_s)
    try:
        return _run_leased(job, lease, max_batches, show_progress)
    finally:
        lease.release()


def _run_leased(job: JobConfig, lease: Lease, max_batches: int | None, show_progress: bool) -> dict:
    """`run_job` while holding the dataset's lease."""
    import ray

    prepare_output(job)
    tracker = start_tracking(job)
    for name, value in RAY_QUIET_ENV.items():
        os.environ.setdefault(name, value)
    started_ray = not ray.is_initialized()
    if started_ray:
        with warnings.catch_warnings():
            # Ray starts its processes with fork + exec, which JAX's fork warning cannot tell from a bare fork.
            warnings.filterwarnings("ignore", message="os.fork\\(\\) was called", category=RuntimeWarning)
            if job.ray.address is None:
                ray.init(address="local", include_dashboard=False, log_to_driver=False, namespace=RAY_NAMESPACE)
            else:
                ray.init(address=job.ray.address, namespace=RAY_NAMESPACE)
    started = time.perf_counter()
    failures = []
    attempts = collections.Counter()
    try:
        coordinator = (
            ray.remote(Coordinator)
            .options(num_cpus=0)
            .remote(job.output_dir, num_shards(job), batches_per_shard(job), max_batches, lease.holder.job_id)
        )
        worker_class = ray.remote(Worker).options(num_cpus=job.ray.cpus_per_worker, num_gpus=job.ray.gpus_per_worker)
        in_flight = {}

        def assign(worker, name):
            shard = ray.get(coordinator.next_shard.remote(name))
            if shard is not None:
                in_flight[worker.run_shard.remote(coordinator, shard)] = (worker, name, shard)

        for i in range(job.ray.num_workers):
            assign(worker_class.remote(job, f"worker-{i}"), f"worker-{i}")
        done, total = ray.get(coordinator.progress.remote())
        with tqdm(total=total, initial=done, unit="batch", desc="level batches", disable=not show_progress) as bar:
            while in_flight:
                lease.check()
                ready, _ = ray.wait(list(in_flight), timeout=PROGRESS_POLL_SECONDS)
                for ref in ready:
                    worker, name, shard = in_flight.pop(ref)
                    try:
                        ray.get(ref)
                    except ray.exceptions.RayError as error:
                        attempts[shard] += 1
                        failures.append({"shard": shard, "worker": name, "error": str(error).splitlines()[0]})
                        if attempts[shard] >= MAX_SHARD_ATTEMPTS:
                            ray.get(coordinator.abandon.remote(shard))  # a poison shard: left for a later run
                        if isinstance(error, ray.exceptions.RayActorError):  # the worker process died: replace it
                            name = f"{name}-restart{attempts.total()}"
                            worker = worker_class.remote(job, name)
                    ray.get(coordinator.release.remote(shard))
                    assign(worker, name)
                tracker.log_commits(ray.get(coordinator.take_commits.remote()))
                committed = ray.get(coordinator.progress.remote())[0]
                training = ray.get(coordinator.training.remote())
                bar.update(round(committed + sum(training.values()), 2) - bar.n)  # in-flight batches count in part
                bar.set_postfix_str(_training_summary(training), refresh=False)
    except BaseException:
        tracker.finish()  # marks the tracked run failed
        raise
    finally:
        if started_ray:
            ray.shutdown()
    summary = summarize(job.output_dir)
    summary["seconds"] = time.perf_counter() - started
    summary["worker_failures"] = failures
    summary["abandoned_shards"] = sorted(shard for shard, count in attempts.items() if count >= MAX_SHARD_ATTEMPTS)
    tracker.finish(summary)
    return summary


LISTED_TRAINING_BATCHES = 4
"""The progress bar lists the training share of up to this many in-flight level batches, then only their mean."""


def _training_summary(training: dict[tuple[int, int], float]) -> str:
    """How far the experts of the level batches in flight have trained: "training 2 batches: 40% 95%"."""
    if not training:
        return ""
    shares = [share for _, share in sorted(training.items())]
    listed = (
        " ".join(f"{share:.0%}" for share in shares)
        if len(shares) <= LISTED_TRAINING_BATCHES
        else f"mean {sum(shares) / len(shares):.0%}"
    )
    return f"training {len(shares)} batch{'es' if len(shares) > 1 else ''}: {listed}"


def summarize(root) -> dict:
    """Counts over the committed level batches: levels by outcome, kept trajectories, batches."""
    outcomes = collections.Counter()
    batches = 0
    for record in iter_records(root):
        batches += 1
        outcomes.update(str(level.outcome) for level in record.levels)
    levels = sum(count for outcome, count in outcomes.items() if outcome != Outcome.PADDING)
    return {"committed_batches": batches, "levels": levels, "outcomes": dict(sorted(outcomes.items()))}
