"""A job's settings resolved from its config: the engine's and the agents' parameters."""

from __future__ import annotations

import dataclasses

from kforge.pipeline.generation.schema import JobConfig


def ppo_config(job: JobConfig):
    """The specialists' `agents.PPOConfig`: the `ppo` section with the split's expert budget; experts are selected by
    episodes that act as the stored windows do (`collect.greedy`)."""
    from kforge.agents import PPOConfig

    return PPOConfig(
        env_steps_per_level=job.split.expert_budget, select_greedy=job.collect.greedy, **dataclasses.asdict(job.ppo)
    )


def environment(job: JobConfig):
    """The env parameters (`env.EnvParams`, `env.StaticEnvParams`) of the job's levels: the config's reward shaping
    and physics scheme."""
    from kforge.engine import physics_scheme
    from kforge.env import EnvParams, StaticEnvParams, under_scheme

    params = EnvParams(dense_reward_scale=job.env.dense_reward_scale)
    return under_scheme(physics_scheme(job.env.physics), params, StaticEnvParams.for_size(job.split.size))
