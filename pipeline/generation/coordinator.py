"""The coordinator: hands out shards, receives commit records and writes the manifest (the truth for resume).

It runs as a Ray actor, but its state is only a cache of the manifest: a restarted coordinator (Ray restarts it,
`max_restarts`) or a re-run job rebuilds it from the records, so its death loses no committed work. Every claim and
commit names the worker and is refused (`ShardNotHeld`) unless that worker holds the shard, so a worker that was
replaced cannot write beside its successor; every commit is fenced by the job's lease and creates its record only
if none exists (`commit_level_batch`).
"""

from __future__ import annotations

import dataclasses
import os

from kforge.pipeline.storage import DatasetError, all_committed, commit_level_batch

COMPILING = "compiling"
"""State of a claimed level batch before its first training report, while its worker has committed nothing in this
run (the worker is compiling its programs)."""
STARTING = "starting"
"""The same once its worker has committed a batch in this run (the batch is being sampled and filtered)."""


@dataclasses.dataclass(frozen=True)
class Commit:
    """A level batch the coordinator committed, as reported to the driver (for progress and tracking)."""

    record: dict  # the commit record as stored in the manifest
    shard_complete: bool  # with it, every level batch of the record's shard is committed


class ShardNotHeld(DatasetError):
    """A worker claimed or committed a level batch of a shard that is not (or no longer) leased to it."""


class Coordinator:
    """Shard leases and commits for one dataset directory."""

    def __init__(
        self,
        root: str | os.PathLike,
        num_shards: int,
        batches_per_shard: int,
        max_batches: int | None = None,
        job_id: str | None = None,
        max_lease_age_s: float | None = None,
    ):
        """`max_batches` caps the level batches handed out in this run (None: all), e.g. for time-boxed allocations;
        `job_id` names the job whose lease on the dataset the workers write under: every commit first checks that it
        holds the lease with a heartbeat at most `max_lease_age_s` old (`lease.commit_age_limit`)."""
        self._root = root
        self._job_id = job_id
        self._max_lease_age_s = max_lease_age_s
        self._batches_per_shard = batches_per_shard
        committed = all_committed(root)
        self._committed = {shard: set(committed.get(shard, ())) for shard in range(num_shards)}
        self._leased: dict[int, str] = {}
        self._claimed: set[tuple[int, int]] = set()
        self._abandoned: set[int] = set()
        self._budget = max_batches  # batches this run may commit; claims in flight count against it
        self._committed_in_run = 0
        self._committers: set[str] = set()  # workers that committed a batch in this run (their programs are compiled)
        self._unreported: list[Commit] = []
        self._training: dict[tuple[int, int], float] = {}

    def next_shard(self, worker: str) -> int | None:
        """The lowest shard with uncommitted level batches that no worker holds, leased to `worker`; None if done."""
        if not self._within_budget():
            return None
        for shard, done in self._committed.items():
            if shard not in self._leased and shard not in self._abandoned and len(done) < self._batches_per_shard:
                self._leased[shard] = worker
                return shard
        return None

    def release(self, shard: int, worker: str | None = None) -> None:
        """Give a shard back (its worker finished or failed); its uncommitted batches may be claimed again. With
        `worker`, only if that worker still holds it (a shard handed on to another worker stays with it)."""
        if worker is not None and self._leased.get(shard) != worker:
            return
        self._leased.pop(shard, None)
        self._claimed = {(s, b) for s, b in self._claimed if s != shard}
        self._training = {key: share for key, share in self._training.items() if key[0] != shard}

    def abandon(self, shard: int) -> None:
        """Hand `shard` out no more in this run (its workers keep failing); a later run retries it."""
        self._abandoned.add(shard)

    def _require_holder(self, shard: int, worker: str) -> None:
        holder = self._leased.get(shard)
        if holder != worker:
            raise ShardNotHeld(
                f"shard {shard} is leased to {holder or 'no worker'}, not {worker}: {worker} must write nothing more"
            )

    def claim_batch(self, shard: int, worker: str) -> int | None:
        """The next uncommitted, unclaimed level batch of a shard leased to `worker`, in order; None when none is
        left or the run's batch budget is spent; `ShardNotHeld` if the shard is not leased to `worker`."""
        self._require_holder(shard, worker)
        if not self._within_budget():
            return None
        for batch in range(self._batches_per_shard):
            if batch not in self._committed[shard] and (shard, batch) not in self._claimed:
                self._claimed.add((shard, batch))
                return batch
        return None

    def _within_budget(self) -> bool:
        """Another batch may be claimed: the commits of this run and the claims in flight are below the budget (a
        failed claim, released, does not use it up)."""
        if self._budget is None:
            return True
        in_flight = sum(1 for shard, batch in self._claimed if batch not in self._committed[shard])
        return self._committed_in_run + in_flight < self._budget

    def commit(self, shard: int, batch: int, record: dict, worker: str) -> bool:
        """Write the record that commits a level batch whose data files `worker` wrote; False if already committed.

        Refused with `ShardNotHeld` unless `worker` holds the shard, and with `LeaseLost` unless the job still holds
        the dataset's lease. Idempotent: a retried commit of the same batch changes nothing.
        """
        self._require_holder(shard, worker)
        stored = commit_level_batch(self._root, shard, batch, record, self._job_id, self._max_lease_age_s)
        if stored is None:
            self._committed[shard].add(batch)
            return False
        self._committed[shard].add(batch)
        self._committed_in_run += 1
        if shard in self._leased:
            self._committers.add(self._leased[shard])
        self._training.pop((shard, batch), None)
        self._unreported.append(Commit(stored, len(self._committed[shard]) == self._batches_per_shard))
        return True

    def job_id(self) -> str | None:
        """The job whose lease the workers write under (their cleanup checks that it still holds it)."""
        return self._job_id

    def take_commits(self) -> list[Commit]:
        """The commits since the last call, in commit order (a restarted coordinator forgets unreported ones; the
        manifest stays the truth)."""
        commits, self._unreported = self._unreported, []
        return commits

    def progress(self) -> tuple[int, int]:
        """(committed level batches, all level batches)."""
        done = sum(len(batches) for batches in self._committed.values())
        return done, len(self._committed) * self._batches_per_shard

    def report_training(self, shard: int, batch: int, updates_done: int, num_updates: int) -> None:
        """A worker's report on a claimed level batch: its experts have done `updates_done` of `num_updates`."""
        if (shard, batch) in self._claimed and batch not in self._committed[shard]:
            self._training[shard, batch] = updates_done / num_updates

    def in_flight(self) -> dict[tuple[int, int], float | str]:
        """Every claimed level batch not yet committed, by (shard, batch): its share of training done, or "compiling"
        (its worker has committed nothing in this run yet) or "starting" before its first training report; 1.0 once
        trained (rolling out and writing)."""
        states = {}
        for shard, batch in sorted(self._claimed):
            if batch in self._committed[shard]:
                continue
            worker = self._leased.get(shard)
            waiting = STARTING if worker in self._committers else COMPILING
            states[shard, batch] = self._training.get((shard, batch), waiting)
        return states

    def training(self) -> dict[tuple[int, int], float]:
        """The share of training done, by (shard, batch), of each claimed level batch not yet committed that has
        reported (a batch at 1.0 is being rolled out or written)."""
        return dict(self._training)
