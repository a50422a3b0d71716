"""Checks of a job config beyond its types, each refusing a value in one line that names the key."""

from __future__ import annotations

import dataclasses
import math

from kforge.agents import PPOHyperparameters
from kforge.pipeline.generation.resolved import ppo_config
from kforge.pipeline.generation.schema import (
    BUDGET_MODES,
    ENV_SIZES,
    FIXED_BUDGET_MODE,
    PHYSICS_SCHEME_NAMES,
    TRACKING_MODES,
    ConfigError,
    JobConfig,
)


def check_config(job: JobConfig) -> None:
    """Errors naming the key for values the schema's types cannot rule out (no training code needed)."""
    _check_finite(job)
    if job.split.size not in ENV_SIZES:
        raise ConfigError(f"split.size must be one of {list(ENV_SIZES)}, got {job.split.size!r}")
    for key in ("split.num_levels", "work.levels_per_shard", "work.levels_per_batch", "collect.window_steps"):
        section, name = key.split(".")
        if getattr(getattr(job, section), name) < 1:
            raise ConfigError(f"{key} must be >= 1, got {getattr(getattr(job, section), name)}")
    if job.work.levels_per_shard % job.work.levels_per_batch:
        raise ConfigError(
            f"work.levels_per_batch ({job.work.levels_per_batch}) must divide work.levels_per_shard "
            f"({job.work.levels_per_shard})"
        )
    if not 1 <= job.filter.noop_steps <= 256:
        raise ConfigError(f"filter.noop_steps must be in [1, 256], got {job.filter.noop_steps}")
    if job.ray.num_workers < 0:
        raise ConfigError(f"ray.num_workers must be >= 0 (0: no Ray, in this process), got {job.ray.num_workers}")
    if job.ray.num_workers == 0 and job.ray.address is not None:
        raise ConfigError(f"ray.address ({job.ray.address!r}) needs ray.num_workers >= 1; 0 runs without Ray")
    if not 0 < job.lease.heartbeat_s < job.lease.stale_after_s:
        raise ConfigError(
            f"lease.heartbeat_s ({job.lease.heartbeat_s}) must be > 0 and below lease.stale_after_s "
            f"({job.lease.stale_after_s})"
        )
    if job.experts.budget_mode not in BUDGET_MODES:
        raise ConfigError(
            f"experts.budget_mode must be one of {', '.join(BUDGET_MODES)}, got {job.experts.budget_mode!r}"
        )
    if job.experts.solved_evaluations < 1:
        raise ConfigError(f"experts.solved_evaluations must be >= 1, got {job.experts.solved_evaluations}")
    if job.experts.give_up_env_steps < 0:
        raise ConfigError(f"experts.give_up_env_steps must be >= 0, got {job.experts.give_up_env_steps}")
    if job.env.physics not in PHYSICS_SCHEME_NAMES:
        raise ConfigError(f"env.physics must be one of {', '.join(PHYSICS_SCHEME_NAMES)}, got {job.env.physics!r}")
    if job.tracking.wandb not in TRACKING_MODES:
        raise ConfigError(f"tracking.wandb must be one of {', '.join(TRACKING_MODES)}, got {job.tracking.wandb!r}")
    _check_ppo_sizes(job)


def _check_ppo_sizes(job: JobConfig) -> None:
    """What the PPO declaration (`agents.PPOHyperparameters`) refuses and, for streamed and adaptive budgets, an
    evaluation period that does not divide the updates, named by key before JAX is imported (`check_training`
    remains the authority)."""
    values = dataclasses.asdict(job.ppo)
    try:
        ppo = PPOHyperparameters(
            env_steps_per_level=job.split.expert_budget, select_greedy=job.collect.greedy, **values
        )
    except ValueError as error:
        raise ConfigError(f"ppo / split.expert_budget: {error}") from error
    every = ppo.select_every_updates
    if job.experts.budget_mode != FIXED_BUDGET_MODE and (every < 1 or ppo.num_updates % every):
        raise ConfigError(
            f"experts.budget_mode={job.experts.budget_mode}: ppo.select_every_updates ({every}) must be >= 1 and "
            f"divide the {ppo.num_updates} updates of the budget"
        )


def _check_finite(section, prefix: str = "") -> None:
    """No float of the config is NaN or infinite (none has a meaning there), naming the key."""
    for field in dataclasses.fields(section):
        value = getattr(section, field.name)
        if dataclasses.is_dataclass(value):
            _check_finite(value, f"{prefix}{field.name}.")
        elif isinstance(value, float) and not math.isfinite(value):
            raise ConfigError(f"{prefix}{field.name} must be a finite number, got {value}")


def check_training(job: JobConfig) -> None:
    """Errors naming the keys for PPO settings the training code cannot run (imports it: JAX)."""
    from kforge.agents import check_segmented

    try:
        config = ppo_config(job)
    except ValueError as error:
        raise ConfigError(f"ppo / split.expert_budget: {error}") from error
    if job.experts.budget_mode != FIXED_BUDGET_MODE:
        try:
            check_segmented(config)
        except ValueError as error:
            raise ConfigError(f"experts.budget_mode={job.experts.budget_mode}: {error}") from error
