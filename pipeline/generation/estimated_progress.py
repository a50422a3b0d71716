"""Progress of a fixed-budget training call, estimated from the time the same compiled program took before.

The training program reports nothing while it runs: a program that calls back into Python is never stored in JAX's
persistent compilation cache, and the training program is the one most worth loading rather than compiling. In the
fixed-budget mode every level batch of a job runs the same program on the same amount of work, so the share of the
previous call's time that has passed estimates the share of updates done.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable, Hashable, Iterator

ProgressListener = Callable[[int, int], None]
"""Called with (updates done, updates in total) per level."""

REPORT_INTERVAL_SECONDS = 1.0
"""[s] Interval between estimates while a call runs."""

_last_seconds: dict[Hashable, float] = {}
_log = logging.getLogger(__name__)


@contextlib.contextmanager
def estimated_progress(program: Hashable, num_updates: int, listener: ProgressListener) -> Iterator[None]:
    """For a call of `program` (a compiled program, or any key that names one) inside the block: tell `listener`
    (0, num_updates) now, an estimate every `REPORT_INTERVAL_SECONDS` while the block runs (from `program`'s previous
    call in this process; none before its first, and never all updates), and (num_updates, num_updates) when the
    block ends. Reports come from another thread; a listener that raises is logged, never propagated. Wait for the
    program's results inside the block: its time is the next call's estimate."""
    previous = _last_seconds.get(program)
    stop = threading.Event()
    started = time.perf_counter()

    def estimate() -> None:
        while not stop.wait(REPORT_INTERVAL_SECONDS):
            share = (time.perf_counter() - started) / previous
            _tell(listener, min(num_updates - 1, int(share * num_updates)), num_updates)

    _tell(listener, 0, num_updates)
    reporter = threading.Thread(target=estimate, name="estimated-progress", daemon=True) if previous else None
    if reporter is not None:
        reporter.start()
    try:
        yield
    finally:
        stop.set()
        if reporter is not None:
            reporter.join()
    _last_seconds[program] = time.perf_counter() - started
    _tell(listener, num_updates, num_updates)


def _tell(listener: ProgressListener, updates_done: int, num_updates: int) -> None:
    try:
        listener(max(updates_done, 0), num_updates)
    except Exception:  # a failing listener must not fail the training it watches
        _log.warning("progress listener failed; training goes on", exc_info=True)
