"""A job resolved once, at its start, into the typed settings every part of a run takes: env, PPO and the sections."""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

from kforge.pipeline.generation.schema import (
    CollectConfig,
    ExpertsConfig,
    FilterConfig,
    JobConfig,
    SplitConfig,
    WorkConfig,
)

if TYPE_CHECKING:
    from kforge.agents import PPOConfig
    from kforge.env import EnvParams, StaticEnvParams


@dataclasses.dataclass(frozen=True, eq=False)
class ResolvedJob:
    """A job config with the settings built from it once (`resolve`): the env parameters of its levels and the
    specialists' PPO config, beside the config's sections. Equal, and hashed, by the config's values."""

    config: JobConfig  # the job as loaded; where it runs and writes (output_dir, ray, lease, ...) is read from here
    env_params: EnvParams  # the config's reward shaping and the physics scheme's parameters
    static: StaticEnvParams  # the split's env size under the physics scheme
    ppo: PPOConfig  # the `ppo` section with the split's expert budget and the collection's greedy flag

    @property
    def split(self) -> SplitConfig:
        return self.config.split

    @property
    def work(self) -> WorkConfig:
        return self.config.work

    @property
    def filter(self) -> FilterConfig:
        return self.config.filter

    @property
    def experts(self) -> ExpertsConfig:
        return self.config.experts

    @property
    def collect(self) -> CollectConfig:
        return self.config.collect

    def __eq__(self, other) -> bool:
        return isinstance(other, ResolvedJob) and dataclasses.astuple(self.config) == dataclasses.astuple(other.config)

    def __hash__(self) -> int:
        return hash(dataclasses.astuple(self.config))


def resolve(job: JobConfig) -> ResolvedJob:
    """The job's settings, built once: a run resolves its job at the start and hands the result down (imports JAX)."""
    env_params, static = environment(job)
    return ResolvedJob(config=job, env_params=env_params, static=static, ppo=ppo_config(job))


def ppo_config(job: JobConfig) -> PPOConfig:
    """The specialists' `agents.PPOConfig`: the `ppo` section with the split's expert budget; experts are selected by
    episodes that act as the stored windows do (`collect.greedy`)."""
    from kforge.agents import PPOConfig

    return PPOConfig(
        env_steps_per_level=job.split.expert_budget, select_greedy=job.collect.greedy, **dataclasses.asdict(job.ppo)
    )


def environment(job: JobConfig) -> tuple[EnvParams, StaticEnvParams]:
    """The env parameters (`env.EnvParams`, `env.StaticEnvParams`) of the job's levels: the config's reward shaping
    and physics scheme."""
    from kforge.engine import physics_scheme
    from kforge.env import EnvParams, StaticEnvParams, under_scheme

    params = EnvParams(dense_reward_scale=job.env.dense_reward_scale)
    return under_scheme(physics_scheme(job.env.physics), params, StaticEnvParams.for_size(job.split.size))
