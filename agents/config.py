"""PPO hyperparameters of a specialist: one hashable, immutable config; derived sizes are properties."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

from kforge.agents.bc_networks import Architecture, NetworkConfig
from kforge.agents.hyperparameters import PPOHyperparameters
from kforge.env import ObservationType

SUPPORTED_OBSERVATIONS = (ObservationType.SYMBOLIC_FLAT,)
"""Observation types the actor-critic can read (flat vectors: the critic is an MLP, and rollouts hold arrays)."""


@dataclasses.dataclass(frozen=True)
class PPOConfig(PPOHyperparameters):
    """The hyperparameters (`PPOHyperparameters`, declared there) and the observation the networks read; static under
    `jit`, and every level of a batch shares them."""

    observation_type: ObservationType = ObservationType.SYMBOLIC_FLAT  # what the networks read; the MLP: flat only
    actor: NetworkConfig | None = None  # a BC network as the actor (PPO fine-tuning from BC); null: the tanh MLP

    def __post_init__(self):
        super().__post_init__()
        if self.observation_type not in SUPPORTED_OBSERVATIONS:
            raise ValueError(
                f"PPOConfig.observation_type {self.observation_type!r} is not supported by the MLP actor-critic; "
                f"expected one of {SUPPORTED_OBSERVATIONS}"
            )
        if self.actor is not None and self.actor.architecture.observation_type is not self.observation_type:
            architecture = self.actor.architecture
            raise ValueError(
                f"PPOConfig.actor: a {architecture.value} reads {architecture.observation_type.value} observations, "
                f"but PPO plays on {self.observation_type.value} (the critic and the rollouts read flat ones)"
            )

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any]) -> PPOConfig:
        """A config from plain values (e.g. parsed YAML): unknown keys are errors, observation types by name."""
        known = {field.name for field in dataclasses.fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ValueError(f"unknown PPOConfig keys {unknown}; known keys: {sorted(known)}")
        values = dict(values)
        if isinstance(values.get("observation_type"), str):
            values["observation_type"] = ObservationType(values["observation_type"])
        if isinstance(values.get("actor"), Mapping):
            actor = dict(values["actor"])
            actor["architecture"] = Architecture(actor.get("architecture", NetworkConfig.architecture.value))
            values["actor"] = NetworkConfig(**actor)
        return cls(**values)
