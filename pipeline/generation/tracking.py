"""Experiment tracking: per-level-batch and per-shard metrics of a generation run, logged to wandb by the driver.

The driver feeds the tracker the commits the coordinator reports (`Coordinator.take_commits`), so each level batch
is logged as it commits and each shard when its last batch commits; the numbers come from the commit records (the
manifest), so a shard's metrics cover its batches from earlier, resumed runs too. Mode `tracking.wandb`: offline
by default (a local run directory per run under `tracking.dir`, uploaded later with `wandb sync <run dir>`), online, or
disabled (wandb is not even imported). The `WANDB_MODE` environment variable, when set, overrides it; the tests set
it to "disabled". Only the driver calls wandb: workers report through the coordinator.
"""

from __future__ import annotations

import collections
import dataclasses
import os
import time
from collections.abc import Iterable, Sequence
from pathlib import Path

from kforge.env import FilterReason
from kforge.pipeline.generation.console import log_dir
from kforge.pipeline.generation.coordinator import Commit
from kforge.pipeline.generation.definition import data_fingerprint
from kforge.pipeline.generation.level_batch import batches_per_shard
from kforge.pipeline.generation.resolved import ResolvedJob
from kforge.pipeline.generation.schema import TRACKING_MODES, ConfigError, JobConfig
from kforge.pipeline.storage import FILTERED_PREFIX, PROVENANCE, Outcome, read_record_json

WANDB_MODE_ENV = "WANDB_MODE"
"""Environment variable that overrides `tracking.wandb` when set (wandb's own name for it)."""

WANDB_DISABLE_WEAVE_ENV = "WANDB_DISABLE_WEAVE"
"""Set by the tracker: wandb takes our `agents` package for the LLM library of that name and advertises Weave."""

BATCH_STEP = "committed_batches"
"""Step axis of the per-batch and progress metrics: level batches committed in this run."""
SHARD_STEP = "completed_shards"
"""Step axis of the per-shard metrics: shards completed in this run."""

TOTAL_SECONDS = "total"
"""Key of a batch's whole wall time among its record's `provenance.seconds` (the others are its phases)."""

KNOWN_OUTCOMES = (Outcome.KEPT, Outcome.UNSOLVED, Outcome.FAILED) + tuple(
    f"{FILTERED_PREFIX}{reason.name.lower()}" for reason in FilterReason if reason != FilterReason.KEPT
)
"""Outcomes of levels in the split, always logged (as 0 when absent) so every chart has a point per step."""


def tracking_mode(job) -> str:
    """The run's wandb mode: `WANDB_MODE` if set, else the config's `tracking.wandb` (a job's or a BC run's,
    validated with the config)."""
    mode = os.environ.get(WANDB_MODE_ENV) or job.tracking.wandb
    if mode not in TRACKING_MODES:
        raise ConfigError(f"environment variable {WANDB_MODE_ENV}={mode!r} must be one of {', '.join(TRACKING_MODES)}")
    return mode


def env_steps_per_level(job: JobConfig) -> int:
    """Env steps simulated for one level slot of a batch: the no-op filter rollout, PPO training (every slot is
    trained, filtered and padding ones too, since the batch is one fixed-shape program) and the stored window."""
    return job.filter.noop_steps + job.split.expert_budget + job.collect.window_steps


def outcome_key(outcome: str) -> str:
    """Metric name of a level outcome: "filtered:no_actuator" -> "filtered/no_actuator"."""
    return outcome.replace(":", "/")


def batch_metrics(records: Sequence[dict], job: JobConfig) -> dict[str, float]:
    """Metrics of one or more level batches from their commit records.

    levels: levels of the split (padding slots excluded); <outcome>: levels per outcome (kept, unsolved, failed,
    filtered/<reason>); kept_rate: kept / levels; solve_rate: kept / trained levels (not filtered);
    expert_success_rate: mean evaluation success rate of the trained levels' selected experts; env_steps and transitions
    (stored steps: kept trajectories x window); seconds and seconds/<phase>: wall time from the records' provenance;
    env_steps_per_s and transitions_per_s over the batches that have it. Ratios without a denominator are left out.
    """
    levels = [level for record in records for level in record["levels"] if level["outcome"] != Outcome.PADDING]
    counts = collections.Counter(level["outcome"] for level in levels)
    trained = [level for level in levels if not level["outcome"].startswith(FILTERED_PREFIX)]
    metrics: dict[str, float] = {"levels": len(levels)}
    metrics |= {outcome_key(outcome): counts[outcome] for outcome in (*KNOWN_OUTCOMES, *sorted(counts))}
    if levels:
        metrics["kept_rate"] = counts[Outcome.KEPT] / len(levels)
    if trained:
        metrics["solve_rate"] = counts[Outcome.KEPT] / len(trained)
    rates = [level["expert_success_rate"] for level in trained if level["expert_success_rate"] is not None]
    if rates:
        metrics["expert_success_rate"] = sum(rates) / len(rates)
    steps_per_slot = env_steps_per_level(job)
    metrics["env_steps"] = steps_per_slot * sum(len(record["levels"]) for record in records)
    metrics["transitions"] = job.collect.window_steps * sum(record["num_kept"] for record in records)

    timed = [record for record in records if TOTAL_SECONDS in record.get(PROVENANCE, {}).get("seconds", {})]
    phases = collections.Counter()
    for record in timed:
        phases.update(record[PROVENANCE]["seconds"])
    seconds = phases.pop(TOTAL_SECONDS, 0.0)
    if seconds > 0:
        metrics["seconds"] = seconds
        metrics |= {f"seconds/{phase}": value for phase, value in sorted(phases.items())}
        metrics["env_steps_per_s"] = steps_per_slot * sum(len(record["levels"]) for record in timed) / seconds
        metrics["transitions_per_s"] = job.collect.window_steps * sum(r["num_kept"] for r in timed) / seconds
    return metrics


def summary_metrics(summary: dict, prefix: str = "run/") -> dict[str, float]:
    """A run summary (`run_job`) as flat numbers: nested dicts become `a/b`, lists their length."""
    flat = {}
    for key, value in summary.items():
        name = prefix + outcome_key(str(key))
        if isinstance(value, dict):
            flat |= summary_metrics(value, f"{name}/")
        elif isinstance(value, list | tuple):
            flat[name] = len(value)
        elif isinstance(value, int | float):
            flat[name] = value
    return flat


@dataclasses.dataclass
class _Totals:
    """What this run committed so far (for the progress metrics)."""

    batches: int = 0
    shards: int = 0
    env_steps: int = 0
    transitions: int = 0
    kept: int = 0


class Tracker:
    """Logs a run's metrics to a wandb run; every method is a no-op when tracking is disabled (`run` None)."""

    def __init__(self, job: JobConfig, run=None):
        """`run` is a started wandb run (`start_tracking` makes one), or None to log nothing."""
        self._job = job
        self._run = run
        self._started = time.perf_counter()
        self._totals = _Totals()

    def log_commits(self, commits: Iterable[Commit]) -> None:
        """Log each committed level batch (`batch/*`, `progress/*`) and each shard it completed (`shard/*`)."""
        if self._run is None:
            return
        for commit in commits:
            metrics = batch_metrics([commit.record], self._job)
            totals = self._totals
            totals.batches += 1
            totals.env_steps += metrics["env_steps"]
            totals.transitions += metrics["transitions"]
            totals.kept += metrics[Outcome.KEPT]
            elapsed = time.perf_counter() - self._started
            progress = {
                BATCH_STEP: totals.batches,
                "progress/elapsed_s": elapsed,
                "progress/kept": totals.kept,
                "progress/env_steps_per_s": totals.env_steps / elapsed,  # all workers together, wall clock
                "progress/transitions_per_s": totals.transitions / elapsed,
            }
            self._run.log(progress | {f"batch/{key}": value for key, value in metrics.items()})
            if commit.shard_complete:
                totals.shards += 1
                self._log_shard(commit.record["shard"])

    def _log_shard(self, shard: int) -> None:
        """Log a completed shard's metrics over all its level batches, read from the manifest."""
        records = [
            read_record_json(self._job.output_dir, shard, batch) for batch in range(batches_per_shard(self._job))
        ]
        metrics = batch_metrics(records, self._job)
        self._run.log(
            {SHARD_STEP: self._totals.shards, "shard/index": shard}
            | {f"shard/{key}": value for key, value in metrics.items()}
        )

    def finish(self, summary: dict | None = None) -> None:
        """End the wandb run with the run's summary (`run/*`), None marking it failed, and stop wandb in this process
        (the driver has no other wandb user), which also flushes the run's files to disk."""
        if self._run is None:
            return
        if summary is not None:
            self._run.summary.update(summary_metrics(summary))
        self._run.finish(exit_code=0 if summary is not None else 1)
        self._run = None
        import wandb

        wandb.teardown()  # finish() may return before wandb's service process has written the .wandb file


def start_tracking(resolved: ResolvedJob) -> Tracker:
    """A tracker for the job: a started wandb run in the job's mode, or a disabled one."""
    job = resolved.config
    mode = tracking_mode(job)
    if mode == "disabled":
        return Tracker(job)
    import wandb

    directory = Path(job.tracking.dir) if job.tracking.dir else log_dir(job.output_dir)
    directory.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault(WANDB_DISABLE_WEAVE_ENV, "true")
    run = wandb.init(
        mode=mode,
        project=job.tracking.project,
        name=job.tracking.name,
        dir=str(directory),
        job_type="datagen",
        config=dataclasses.asdict(job) | {"data_fingerprint": data_fingerprint(resolved)},
        settings=wandb.Settings(console="off", save_code=False, disable_git=True),
    )
    run.define_metric(BATCH_STEP)
    run.define_metric(SHARD_STEP)
    for prefix in ("batch", "progress"):
        run.define_metric(f"{prefix}/*", step_metric=BATCH_STEP)
    run.define_metric("shard/*", step_metric=SHARD_STEP)
    return Tracker(job, run)
