"""What an operator sees of a run: the progress bar, what a resumed run found, the closing summary, and the log file
that third-party chatter (Ray, wandb) goes to instead of the terminal."""

from __future__ import annotations

import logging
import os
import sys
import time
from pathlib import Path

from tqdm import tqdm

from kforge.pipeline.generation.coordinator import COMPILING, STARTING
from kforge.pipeline.storage import (
    CONFIG_FILE,
    DATA_DIR,
    FILTERED_PREFIX,
    MANIFEST_DIR,
    Outcome,
    is_remote,
    join,
)

LOG_DIR = "logs"
"""The dataset's folder of run logs (`run-<UTC time>.log`) and, by default, wandb's run folders."""

REMOTE_LOG_ROOT = Path("outputs") / "remote-logs"
"""Local folder of the logs of datasets on object storage: REMOTE_LOG_ROOT/<bucket>/<prefix>/logs."""


def log_dir(output_dir: str | os.PathLike) -> Path:
    """The local folder of a dataset's run logs: `<output_dir>/logs` on a filesystem; for a dataset on object storage
    (`s3://bucket/prefix`), `outputs/remote-logs/bucket/prefix/logs` on this machine (logs stay out of the bucket;
    "." and ".." parts of the URL are dropped, so the folder stays under `REMOTE_LOG_ROOT`)."""
    if is_remote(output_dir):
        parts = str(output_dir).split("://", 1)[1].split("/")
        return REMOTE_LOG_ROOT.joinpath(*(part for part in parts if part not in ("", ".", ".."))) / LOG_DIR
    return Path(output_dir) / LOG_DIR


THIRD_PARTY_LOGGERS = ("ray", "wandb", "jax", "absl", "filelock", "urllib3", "git")
"""Python loggers of libraries whose messages go to the run's log file (the terminal too with --verbose)."""

QUIET_ENV = {"WANDB_SILENT": "true", "RAY_COLOR_PREFIX": "0"}
"""Environment of a quiet run: no wandb banner or run history on the terminal, no colour in Ray's log prefixes."""

LISTED_BATCHES = 4
"""The progress bar lists the training share of up to this many in-flight level batches, then only their mean."""


def start_log_file(output_dir: str | os.PathLike, verbose: bool) -> Path:
    """Send the third-party loggers to `run-<UTC time>.log` in the dataset's log folder (`log_dir`; and to the
    terminal if `verbose`); returns the log file's path."""
    directory = log_dir(output_dir)
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / time.strftime("run-%Y%m%d-%H%M%S.log", time.gmtime())
    handler = logging.FileHandler(path)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    for name in THIRD_PARTY_LOGGERS:
        logger = logging.getLogger(name)
        logger.handlers = [handler] + ([logging.StreamHandler()] if verbose else [])
        logger.propagate = False
    if not verbose:
        for name, value in QUIET_ENV.items():
            os.environ.setdefault(name, value)
    return path


def count(number: int, singular: str, plural: str | None = None) -> str:
    """ "1 level batch", "2 level batches"."""
    return f"{number} {singular if number == 1 else plural or singular + 's'}"


def resume_line(committed: int, total: int, withdrawn: int) -> str | None:
    """What a run found in its output directory: None for a new dataset."""
    if committed == 0 and withdrawn == 0:
        return None
    grown = f" ({count(withdrawn, 'level batch', 'level batches')} withdrawn to grow the split)" if withdrawn else ""
    return f"resuming: found {committed} of {count(total, 'level batch', 'level batches')} committed{grown}; " + (
        f"{total - committed} remain" if committed < total else "nothing remains"
    )


def in_flight_summary(in_flight: dict[tuple[int, int], float | str]) -> str:
    """The level batches in flight, by state: "compiling 1 batch, training 2 batches: 40% 95%, collecting 1 batch"
    (a batch whose experts have done all their training is rolling out its windows and being written)."""
    states = {key: "collecting" if share == 1.0 else share for key, share in in_flight.items()}
    parts = []
    for state in (COMPILING, STARTING):
        waiting = [key for key, share in states.items() if share == state]
        if waiting:
            parts.append(f"{state} {count(len(waiting), 'batch', 'batches')}")
    shares = [share for _, share in sorted(states.items()) if not isinstance(share, str)]
    if shares:
        listed = (
            " ".join(f"{share:.0%}" for share in shares)
            if len(shares) <= LISTED_BATCHES
            else f"mean {sum(shares) / len(shares):.0%}"
        )
        parts.append(f"training {count(len(shares), 'batch', 'batches')}: {listed}")
    collecting = sum(1 for share in states.values() if share == "collecting")
    if collecting:
        parts.append(f"collecting {count(collecting, 'batch', 'batches')}")
    return ", ".join(parts)


def seconds_left(since: tuple[float, float] | None, now: float, done: float, total: float) -> float | None:
    """Time left at the pace measured since `since` = (time, work done then), the moment start-up (compiling) ended,
    so that the compile's time does not count as work; None before work advanced after it."""
    if since is None:
        return None
    start_time, start_done = since
    if done <= start_done or now <= start_time:
        return None
    return (total - done) * (now - start_time) / (done - start_done)


class ProgressBar:
    """Level batches done, counting the training share of those in flight (so the bar moves within a batch), the
    batches in flight and the time left at the pace measured since compiling ended, in the postfix."""

    BAR_FORMAT = "{desc}: {percentage:3.0f}%|{bar}| {n:.1f}/{total_fmt} [{elapsed}{postfix}]"

    def __init__(self, committed: int, total: int, enabled: bool):
        self._since: tuple[float, float] | None = None
        self._bar = tqdm(
            total=total,
            initial=committed,
            unit="batch",
            desc="level batches",
            bar_format=self.BAR_FORMAT,
            disable=not enabled,
            file=sys.stderr,
        )

    def show(self, committed: int, in_flight: dict[tuple[int, int], float | str]) -> None:
        """Redraw with `committed` batches done and the batches in flight."""
        now = time.perf_counter()
        shares = [share for share in in_flight.values() if not isinstance(share, str)]
        done = committed + sum(shares)
        if self._since is None and shares and len(shares) == len(in_flight):  # every batch in flight compiled
            self._since = (now, done)
        left = seconds_left(self._since, now, done, self._bar.total)
        parts = [f"left {'?' if left is None else tqdm.format_interval(left)}", in_flight_summary(in_flight)]
        self._bar.n = done
        self._bar.set_postfix_str(", ".join(part for part in parts if part), refresh=False)
        self._bar.refresh()

    def close(self) -> None:
        self._bar.close()


def closing_summary(summary: dict, output_dir: str | os.PathLike) -> str:
    """The lines a finished run prints: levels by outcome, where the dataset is and its size, the next commands."""
    outcomes = summary["outcomes"]
    filtered = {key.removeprefix(FILTERED_PREFIX): n for key, n in outcomes.items() if key.startswith(FILTERED_PREFIX)}
    by_reason = ", ".join(f"{reason} {n}" for reason, n in sorted(filtered.items()))
    remote = is_remote(output_dir)
    root = str(output_dir) if remote else Path(output_dir)
    total, remaining = summary["total_batches"], summary["total_batches"] - summary["committed_batches"]
    status = "complete" if remaining == 0 else f"incomplete: {remaining} of {total} level batches remain"
    lines = [
        f"dataset {status}: {root} ({'on object storage' if remote else _size(root)})",
        f"levels: {summary['levels']} sampled, {sum(filtered.values())} filtered"
        + (f" ({by_reason})" if by_reason else "")
        + f", {outcomes.get(Outcome.KEPT, 0)} kept, {outcomes.get(Outcome.UNSOLVED, 0)} unsolved"
        + f", {outcomes.get(Outcome.FAILED, 0)} failed",
        f"this run: {count(summary['committed_in_run'], 'level batch', 'level batches')} committed in "
        f"{tqdm.format_interval(summary['seconds'])}, {count(len(summary['worker_failures']), 'worker failure')}"
        + (f" ({'; '.join(summary['worker_failure_causes'])})" if summary.get("worker_failure_causes") else "")
        + (f"; shards left for a later run: {summary['abandoned_shards']}" if summary["abandoned_shards"] else ""),
    ]
    if summary.get("log_file"):
        lines.append(f"third-party logs: {summary['log_file']}")
    lines.append("next:")
    if remaining:
        lines.append(f"  kforge run {join(root, CONFIG_FILE)}    # continue")
    lines += [
        f"  kforge verify {root}",
        f"  kforge stats {root}",
        f'  python -c "from kforge import TrajectoryDatasetManager as M; '
        f"print(M('{root}', batch_size=2, seed=0).load_next_batch().action.shape)\"",
        f"  kforge bc train {root}    # behaviour cloning on it, then kforge evaluate on the run it prints",
    ]
    return "\n".join(lines)


def _size(root: Path) -> str:
    """Bytes of the dataset's data and manifest on disk, human readable."""
    size = sum(
        path.stat().st_size
        for folder in (DATA_DIR, MANIFEST_DIR)
        for path in (root / folder).rglob("*")
        if path.is_file()
    )
    units = ("B", "KiB", "MiB", "GiB", "TiB")
    power = 0
    while size >= 1024 ** (power + 1) and power < len(units) - 1:
        power += 1
    return f"{size} B" if power == 0 else f"{size / 1024**power:.1f} {units[power]}"
