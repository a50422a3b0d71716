"""One job per dataset: the lease object `lease.json` at a dataset's root.

A running job (`kforge run`) creates the lease atomically (`Store.create_exclusive`), renews its heartbeat from a
background thread, and deletes it when it ends. A second job on the same dataset is refused while the heartbeat is
fresh and takes the lease over (with a message) once it is older than the stale limit, so a crashed job's dataset
resumes without a manual step. Renewal and take-over are conditional on the generation last seen, so of two jobs that
race for a stale lease one wins and the other is refused. Readers take no lease.

Fencing: a job that lost its lease must not change the dataset. Before every commit and every deletion the writer
proves it still holds the lease: the driver by a conditional renewal (`Lease.fence`, a compare-and-swap on the
generation it last wrote, so it fails once another job took over, however long this process was paused), a
coordinator or worker in another process by reading the lease (`require_lease`: this job's id, and a heartbeat
younger than the stale limit less one heartbeat interval, so no other job can take over before the write lands).
`Lease.check` compares the last heartbeat with the clock as well as the heartbeat thread's flag, so a process
resumed after a pause longer than the stale limit fences before it goes on.
"""

from __future__ import annotations

import dataclasses
import json
import os
import socket
import threading
import time
import uuid
from collections.abc import Callable

from kforge.pipeline.storage.layout import DatasetError
from kforge.pipeline.storage.store import Store, StoreError, open_store

LEASE_KEY = "lease.json"
DEFAULT_STALE_AFTER_S = 300.0
"""[s] A lease whose heartbeat is older than this is taken over (the holder is presumed dead)."""
DEFAULT_HEARTBEAT_S = 30.0
"""[s] Interval between heartbeats of a held lease."""


class LeaseHeld(DatasetError):
    """Another job holds the dataset's lease (its heartbeat is fresh)."""


class LeaseLost(DatasetError):
    """This job's lease was taken over or removed by someone else; it must stop writing."""


@dataclasses.dataclass(frozen=True)
class LeaseHolder:
    """Who holds a dataset: host, process, job id, start and last heartbeat (unix seconds)."""

    host: str
    pid: int
    job_id: str
    started: float
    heartbeat: float

    def to_bytes(self) -> bytes:
        return json.dumps(dataclasses.asdict(self), sort_keys=True).encode()

    @classmethod
    def from_bytes(cls, data: bytes, where: str) -> LeaseHolder:
        try:
            value = json.loads(data)
            return cls(
                str(value["host"]),
                int(value["pid"]),
                str(value["job_id"]),
                float(value["started"]),
                float(value["heartbeat"]),
            )
        except (ValueError, KeyError, TypeError) as error:
            raise DatasetError(f"{where}: unreadable lease ({error!r}); remove it if no job runs") from error

    def describe(self, now: float) -> str:
        return f"job {self.job_id} (host {self.host}, pid {self.pid}), last heartbeat {now - self.heartbeat:.0f} s ago"


def read_holder(root: str | os.PathLike | Store) -> LeaseHolder | None:
    """The dataset's lease holder, or None if no job holds it."""
    store = open_store(root)
    data = store.read(LEASE_KEY)
    return None if data is None else LeaseHolder.from_bytes(data, store.url(LEASE_KEY))


def require_lease(root: str | os.PathLike | Store, job_id: str, max_age_s: float | None = None) -> None:
    """Raise `LeaseLost` unless job `job_id` holds the dataset's lease and, with `max_age_s`, its last heartbeat is
    at most that old (what a coordinator or worker checks before it commits or deletes, see the module doc)."""
    store = open_store(root)
    try:
        holder = read_holder(store)
    except DatasetError as error:
        raise LeaseLost(f"{store.url(LEASE_KEY)}: job {job_id} cannot prove it holds the lease ({error})") from error
    now = time.time()
    if holder is None or holder.job_id != job_id:
        who = "no job" if holder is None else holder.describe(now)
        raise LeaseLost(f"{store.url(LEASE_KEY)}: job {job_id} does not hold the lease ({who} does)")
    if max_age_s is not None and now - holder.heartbeat > max_age_s:
        raise LeaseLost(
            f"{store.url(LEASE_KEY)}: job {job_id}'s last heartbeat is {now - holder.heartbeat:.0f} s old (more than "
            f"{max_age_s:.0f} s): another job may take the lease over, so this one writes nothing more"
        )


def commit_age_limit(stale_after_s: float, heartbeat_s: float) -> float:
    """[s] The oldest heartbeat under which another process of the job may still commit (`require_lease`): the stale
    limit less one heartbeat interval, the margin for the write and for clocks that differ between hosts."""
    return stale_after_s - heartbeat_s


class Lease:
    """A held lease: `acquire` it, `release` it in a `finally` (or use it as a context manager)."""

    def __init__(self, store: Store, holder: LeaseHolder, generation: bytes, heartbeat_s: float, stale_after_s: float):
        self.store, self.holder = store, holder
        self._generation = generation
        self._heartbeat_s = heartbeat_s
        self._stale_after_s = stale_after_s
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.lost: str | None = None
        """Why the lease was lost (taken over or removed), or None while it is held."""

    @classmethod
    def acquire(
        cls,
        root: str | os.PathLike | Store,
        stale_after_s: float = DEFAULT_STALE_AFTER_S,
        heartbeat_s: float = DEFAULT_HEARTBEAT_S,
        job_id: str | None = None,
        log: Callable[[str], None] = print,
    ) -> Lease:
        """Take the dataset's lease and start heartbeats; `LeaseHeld` naming the holder if another job's is fresh."""
        store = open_store(root)
        now = time.time()
        holder = LeaseHolder(socket.gethostname(), os.getpid(), job_id or uuid.uuid4().hex[:12], now, now)
        # Read before creating: on a store that ignores the create's condition, a create would overwrite a live lease.
        generation = None
        data, seen = store.read_versioned(LEASE_KEY)
        if data is None:
            generation = store.create_exclusive(LEASE_KEY, holder.to_bytes())
            if generation is None:  # another job created it since our read
                data, seen = store.read_versioned(LEASE_KEY)
        if generation is None and data is not None:
            other = LeaseHolder.from_bytes(data, store.url(LEASE_KEY))
            age = now - other.heartbeat
            if age <= stale_after_s:
                raise LeaseHeld(
                    f"{store.location}: the dataset is in use by {other.describe(now)}; wait for it to end, "
                    f"or for its heartbeat to be older than {stale_after_s:.0f} s to take it over"
                )
            generation = store.replace(LEASE_KEY, holder.to_bytes(), seen)
            if generation is not None:
                log(f"{store.location}: taking over the stale lease of {other.describe(now)}")
        if generation is None:
            raise LeaseHeld(f"{store.location}: another job took the dataset's lease at the same moment")
        lease = cls(store, holder, generation, heartbeat_s, stale_after_s)
        lease._confirm()
        lease._thread = threading.Thread(target=lease._beat, name="lease-heartbeat", daemon=True)
        lease._thread.start()
        return lease

    def _confirm(self) -> None:
        """Read the lease back: on a store that ignores conditional writes, a racing job's write shows here."""
        holder = read_holder(self.store)
        if holder != self.holder:
            raise LeaseHeld(f"{self.store.location}: another job took the dataset's lease at the same moment")

    def _beat(self) -> None:
        while not self._stop.wait(self._heartbeat_s):
            try:
                self.renew()
            except (DatasetError, StoreError) as error:  # a failed heartbeat is retried; the stale limit bounds the gap
                print(f"warning: {self.store.url(LEASE_KEY)}: heartbeat failed ({error})")

    def renew(self) -> None:
        """Write a fresh heartbeat (conditional on our last one); marks the lease lost if someone else wrote it."""
        with self._lock:
            if self.lost is not None or self._stop.is_set():
                return
            self._renew_locked()

    def _renew_locked(self) -> None:
        holder = dataclasses.replace(self.holder, heartbeat=time.time())
        generation = self.store.replace(LEASE_KEY, holder.to_bytes(), self._generation)
        if generation is None:
            try:
                current = read_holder(self.store)
                taker = "removed" if current is None else f"taken over by {current.describe(time.time())}"
            except DatasetError:
                taker = "overwritten by an unreadable lease"
            self.lost = f"{self.store.location}: this job's lease was {taker}"
            return
        self.holder, self._generation = holder, generation

    def fence(self) -> None:
        """Prove that this job holds the lease now, or raise `LeaseLost`: a conditional renewal (compare-and-swap on
        the generation this job wrote last), which fails once another job took the lease over or removed it. Call it
        right before a write that commits or deletes."""
        with self._lock:
            if self.lost is None:
                self._renew_locked()
        self.check()

    def check(self) -> None:
        """Raise `LeaseLost` if the lease was taken over or removed, or, when the last heartbeat is older than the
        stale limit by the clock (this process was paused, or its heartbeats failed), unless a `fence` succeeds."""
        if self.lost is not None:
            raise LeaseLost(self.lost)
        if time.time() - self.holder.heartbeat > self._stale_after_s:
            self.fence()

    def release(self) -> None:
        """Stop heartbeats and delete the lease if it is still ours."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        with self._lock:
            if self.lost is None:
                self.store.replace(LEASE_KEY, None, self._generation)

    def __enter__(self) -> Lease:
        return self

    def __exit__(self, *exc_info) -> None:
        self.release()
