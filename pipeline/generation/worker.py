"""A worker: takes a shard at a time and turns its uncommitted level batches into stored, committed data."""

from __future__ import annotations

import functools
import os
import time
from pathlib import Path

from pipeline.generation.config import JobConfig
from pipeline.generation.level_batch import run_level_batch
from pipeline.storage import PROVENANCE, clean_uncommitted, open_dataset, stage_level_batch

FAULT_INJECTION_ENV = "KFORGE_WORKER_FAULT"
"""Fault drill: "N:PATH" makes the first worker that finds no file at PATH create it and kill its own process
right after writing the data files of its N-th level batch, before the commit (the worst moment to die)."""


def _maybe_inject_fault(staged: int) -> None:
    plan = os.environ.get(FAULT_INJECTION_ENV)
    if not plan:
        return
    count, marker = plan.split(":", 1)
    if staged == int(count):
        try:
            Path(marker).touch(exist_ok=False)
        except FileExistsError:
            return
        os._exit(1)


class Worker:
    """Generates level batches for the shards the coordinator leases to it (one writer per shard)."""

    def __init__(self, job: JobConfig, name: str):
        self._job = job
        self._name = name
        self._staged = 0

    def run_shard(self, coordinator, shard: int) -> list[dict]:
        """Continue `shard` from its last committed level batch; returns a summary per batch it committed.

        `coordinator` is the coordinator actor handle (or a local object with the same methods, for tests).
        """
        dataset = open_dataset(self._job.output_dir)
        # Safe under the job's lease on the dataset; the coordinator's shard lease makes this worker its only writer.
        clean_uncommitted(dataset.store, shard, _call(coordinator.job_id))
        summaries = []
        while (batch := _call(coordinator.claim_batch, shard)) is not None:
            started = time.perf_counter()
            result = run_level_batch(
                self._job,
                shard,
                batch,
                on_progress=functools.partial(_notify, coordinator.report_training, shard, batch),
            )
            written = time.perf_counter()
            record = stage_level_batch(dataset, shard, batch, result)
            provenance = record.setdefault(PROVENANCE, {"seconds": {}})
            provenance["seconds"]["write"] = time.perf_counter() - written
            provenance["seconds"]["total"] = time.perf_counter() - started
            provenance["worker"] = self._name
            self._staged += 1
            _maybe_inject_fault(self._staged)
            _call(coordinator.commit, shard, batch, record)
            summaries.append(
                {
                    "shard": shard,
                    "batch": batch,
                    "worker": self._name,
                    "outcomes": list(result.outcome),
                    "seconds": time.perf_counter() - started,
                }
            )
        return summaries


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
