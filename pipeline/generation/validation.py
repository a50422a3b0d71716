"""Checks of a job config beyond its types, each refusing a value in one line that names the key."""

from __future__ import annotations

import dataclasses
import math

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


PPO_COUNTS = ("num_envs", "num_steps", "update_epochs", "num_minibatches", "hidden_size", "num_hidden_layers")
"""`ppo` keys that count something and must be >= 1 (`select_episodes` too, `select_every_updates` >= 0)."""
PPO_POSITIVE = ("learning_rate", "adam_eps", "max_grad_norm", "clip_eps")
PPO_SHARES = ("gamma", "gae_lambda")
PPO_WEIGHTS = ("ent_coef", "vf_coef")


def _check_ppo_sizes(job: JobConfig) -> None:
    """What `agents.PPOConfig` (and, for adaptive budgets, training in segments) would refuse, on the config's plain
    values and named by key, so that the error comes before JAX is imported (`check_training` remains the
    authority)."""
    ppo = job.ppo
    for name in (*PPO_COUNTS, "select_episodes"):
        if getattr(ppo, name) < 1:
            raise ConfigError(f"ppo.{name} must be >= 1, got {getattr(ppo, name)}")
    checks = [(PPO_POSITIVE, lambda x: x > 0, "> 0"), (PPO_SHARES, lambda x: 0 <= x <= 1, "in [0, 1]")]
    for names, holds, rule in [*checks, (PPO_WEIGHTS, lambda x: x >= 0, ">= 0")]:
        for name in names:
            if not holds(getattr(ppo, name)):
                raise ConfigError(f"ppo.{name} must be {rule}, got {getattr(ppo, name)}")
    if ppo.select_every_updates < 0:
        raise ConfigError(f"ppo.select_every_updates must be >= 0, got {ppo.select_every_updates}")
    steps = ppo.num_envs * ppo.num_steps
    budget = job.split.expert_budget
    if budget < steps or budget % steps:
        raise ConfigError(
            f"split.expert_budget ({budget}) must be a multiple of one update's ppo.num_envs * ppo.num_steps = "
            f"{ppo.num_envs} * {ppo.num_steps} = {steps}"
        )
    if steps % ppo.num_minibatches:
        raise ConfigError(
            f"ppo.num_minibatches ({ppo.num_minibatches}) must divide ppo.num_envs * ppo.num_steps = {steps}"
        )
    updates = budget // steps
    if job.experts.budget_mode != FIXED_BUDGET_MODE and (
        ppo.select_every_updates < 1 or updates % ppo.select_every_updates
    ):
        raise ConfigError(
            f"experts.budget_mode={job.experts.budget_mode}: ppo.select_every_updates ({ppo.select_every_updates}) "
            f"must be >= 1 and divide the {updates} updates of the budget"
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
