"""Job configuration: an OmegaConf structured schema, loading with dotlist overrides, and the data-defining hash."""

from __future__ import annotations

import dataclasses
import hashlib
import json
from pathlib import Path

from omegaconf import MISSING, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from agents import PPOConfig
from engine import KINETIX_SIZES


@dataclasses.dataclass
class SplitConfig:
    """Which levels make up the dataset split."""

    name: str = MISSING  # split name as in the release, e.g. "1M/s"
    size: str = "s"  # env size: s, m or l
    seed: int = 0  # split seed; level i's PRNG key derives from (seed, i)
    num_levels: int = 64  # levels sampled for the split (kept trajectories are at most this many)
    expert_budget: int = 1_000_000  # PPO env steps per level (the release's "1M" / "10M")


@dataclasses.dataclass
class WorkConfig:
    """How levels are cut into units of work; both sizes are part of the data's identity."""

    levels_per_shard: int = 64  # levels per shard (one writer per shard)
    levels_per_batch: int = 16  # levels trained together in one vmapped program; divides levels_per_shard


@dataclasses.dataclass
class FilterConfig:
    """The trivial-level filter applied before training."""

    enabled: bool = True  # drop flagged levels before paying for PPO (they are recorded with the reason)
    noop_steps: int = 256  # env steps of the no-op rollout that detects levels solved by doing nothing


@dataclasses.dataclass
class PPOSection:
    """Specialist PPO settings (see configs/ppo_specialist.yaml for the evidence behind the defaults)."""

    num_envs: int = 16
    num_steps: int = 125
    update_epochs: int = 4
    num_minibatches: int = 4
    learning_rate: float = 3e-4
    adam_eps: float = 1e-5
    max_grad_norm: float = 1.0
    gamma: float = 0.995
    gae_lambda: float = 0.9
    clip_eps: float = 0.2
    ent_coef: float = 0.01
    vf_coef: float = 0.5
    hidden_size: int = 64
    num_hidden_layers: int = 2
    bootstrap_truncation: bool = False


@dataclasses.dataclass
class CollectConfig:
    """The stored window of each expert."""

    window_steps: int = 256  # env steps per stored trajectory
    greedy: bool = False  # act with the most probable choice per slot instead of sampling


@dataclasses.dataclass
class EnvSection:
    dense_reward_scale: float = 0.2  # shaping scale used for training (Kinetix's repository configs use 0.2)


@dataclasses.dataclass
class RayConfig:
    """Where the job runs; none of these change the data."""

    address: str | None = None  # None: embedded local Ray; "auto" or host:port: a running cluster
    num_workers: int = 1  # worker actors
    cpus_per_worker: float = 1.0
    gpus_per_worker: float = 0.0


@dataclasses.dataclass
class JobConfig:
    """A generation job: the split, how it is cut and trained, and where it runs and writes."""

    output_dir: str = MISSING  # dataset directory (created; re-running on it resumes)
    split: SplitConfig = dataclasses.field(default_factory=SplitConfig)
    work: WorkConfig = dataclasses.field(default_factory=WorkConfig)
    filter: FilterConfig = dataclasses.field(default_factory=FilterConfig)
    env: EnvSection = dataclasses.field(default_factory=EnvSection)
    ppo: PPOSection = dataclasses.field(default_factory=PPOSection)
    collect: CollectConfig = dataclasses.field(default_factory=CollectConfig)
    ray: RayConfig = dataclasses.field(default_factory=RayConfig)


DATA_SECTIONS = ("split", "work", "filter", "env", "ppo", "collect")
"""Config sections that determine the dataset's content; a resumed job must agree on all of them."""


class ConfigError(ValueError):
    """A job config that cannot be used; the message names the key."""


def load_config(path: str | Path | None = None, overrides: list[str] = ()) -> JobConfig:
    """The job config from the schema defaults, a YAML file and `key=value` overrides, validated."""
    try:
        config = OmegaConf.structured(JobConfig)
        if path is not None:
            config = OmegaConf.merge(config, OmegaConf.load(path))
        config = OmegaConf.merge(config, OmegaConf.from_dotlist(list(overrides)))
        job: JobConfig = OmegaConf.to_object(config)
    except FileNotFoundError as error:
        raise ConfigError(f"config file not found: {path}") from error
    except OmegaConfBaseException as error:
        raise ConfigError(str(error).splitlines()[0] + _key_suffix(error)) from error
    check_config(job)
    return job


def _key_suffix(error: OmegaConfBaseException) -> str:
    key = getattr(error, "full_key", None)
    return f" (key: {key})" if key else ""


def check_config(job: JobConfig) -> None:
    """Errors naming the key for values the schema's types cannot rule out."""
    if job.split.size not in KINETIX_SIZES:
        raise ConfigError(f"split.size must be one of {sorted(KINETIX_SIZES)}, got {job.split.size!r}")
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
    if job.ray.num_workers < 1:
        raise ConfigError(f"ray.num_workers must be >= 1, got {job.ray.num_workers}")
    try:
        ppo_config(job)
    except ValueError as error:
        raise ConfigError(f"ppo / split.expert_budget: {error}") from error


def ppo_config(job: JobConfig) -> PPOConfig:
    """The specialists' PPO config: the `ppo` section with the split's expert budget."""
    return PPOConfig(env_steps_per_level=job.split.expert_budget, **dataclasses.asdict(job.ppo))


def data_fingerprint(job: JobConfig) -> str:
    """Hash of the sections that define the data: equal fingerprints mean identical datasets."""
    data = {section: dataclasses.asdict(getattr(job, section)) for section in DATA_SECTIONS}
    return hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()[:16]


def to_yaml(job: JobConfig) -> str:
    """The resolved config as YAML (saved with the dataset)."""
    return OmegaConf.to_yaml(OmegaConf.structured(job))
