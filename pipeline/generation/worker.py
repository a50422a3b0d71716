"""A worker: takes a shard at a time and turns its uncommitted level batches into stored, committed data."""

from __future__ import annotations

import functools
import time
from collections.abc import Iterator

from kforge.engine import use_deterministic_ops
from kforge.pipeline.generation.adaptive import streamed_level_batches
from kforge.pipeline.generation.compile_cache import enable_compile_cache
from kforge.pipeline.generation.level_batch import run_level_batch
from kforge.pipeline.generation.resolved import ResolvedJob
from kforge.pipeline.generation.schema import FIXED_BUDGET_MODE
from kforge.pipeline.storage import PROVENANCE, BatchTrajectories, ShardWriter, commit_age_limit


class Worker:
    """Generates level batches for the shards the coordinator leases to it (one writer per shard), with the settings
    of the job the driver resolved (`resolve`)."""

    def __init__(self, resolved: ResolvedJob, name: str):
        job = resolved.config
        if job.ray.deterministic_gpu_ops:
            use_deterministic_ops()  # before the worker's first computation: the same data on a GPU, run after run
        enable_compile_cache(job.compile_cache.dir)
        self._job = job
        self._resolved = resolved
        self._name = name

    def run_shard(self, coordinator, shard: int) -> list[dict]:
        """Continue `shard` from its last committed level batch; returns a summary per batch it committed.

        `coordinator` is the coordinator actor handle (or a local object with the same methods, for tests).
        """
        # Safe under the job's lease on the dataset; the coordinator's shard lease makes this worker its only writer.
        max_lease_age_s = commit_age_limit(self._job.lease.stale_after_s, self._job.lease.heartbeat_s)
        writer = ShardWriter(self._job.output_dir, shard, _call(coordinator.job_id), max_lease_age_s)
        summaries = []
        started = time.perf_counter()
        for batch, result in self._batches(coordinator, shard):
            written = time.perf_counter()
            record = writer.stage(batch, result)
            provenance = record.setdefault(PROVENANCE, {"seconds": {}})
            provenance["seconds"]["write"] = time.perf_counter() - written
            provenance["seconds"]["total"] = time.perf_counter() - started
            provenance["worker"] = self._name
            _call(coordinator.commit, shard, batch, record, self._name)
            writer.committed(batch)
            summaries.append(
                {
                    "shard": shard,
                    "batch": batch,
                    "worker": self._name,
                    "outcomes": list(result.outcome),
                    "seconds": time.perf_counter() - started,
                }
            )
            started = time.perf_counter()
        return summaries

    def _batches(self, coordinator, shard: int) -> Iterator[tuple[int, BatchTrajectories]]:
        """(batch, its data) for each level batch of `shard` the coordinator hands out, as each is done."""
        claim = functools.partial(_call, coordinator.claim_batch, shard, self._name)
        if self._job.experts.budget_mode != FIXED_BUDGET_MODE:
            report = functools.partial(_notify, coordinator.report_training, shard)
            yield from streamed_level_batches(self._resolved, shard, claim, on_progress=report)
            return
        while (batch := claim()) is not None:
            report = functools.partial(_notify, coordinator.report_training, shard, batch)
            yield batch, run_level_batch(self._resolved, shard, batch, on_progress=report)


def _call(method, *args):
    """Call a Ray actor method and wait for it, or a plain method directly."""
    remote = getattr(method, "remote", None)
    if remote is None:
        return method(*args)
    import ray

    return ray.get(remote(*args))


def _notify(method, *args) -> None:
    """Call a Ray actor method without waiting for it (safe from any thread), or a plain method directly."""
    remote = getattr(method, "remote", None)
    if remote is None:
        method(*args)
    else:
        remote(*args)
