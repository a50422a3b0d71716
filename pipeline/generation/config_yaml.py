"""The resolved job config as YAML, each key commented with its type and meaning from the schema."""

from __future__ import annotations

import dataclasses
import typing

from omegaconf import OmegaConf

from kforge.pipeline.generation.schema import JobConfig, field_docs, type_name


def to_yaml(job: JobConfig) -> str:
    """The resolved config as YAML, each key commented with its type and meaning (saved with the dataset as
    config.yaml; `kforge run --print-config` prints it). Loading it gives the same config."""
    return "\n".join(_yaml_lines(job, "")) + "\n"


def _yaml_lines(section, indent: str) -> list[str]:
    hints = typing.get_type_hints(type(section))
    docs = field_docs(type(section))
    lines = []
    for field in dataclasses.fields(section):
        value, hint = getattr(section, field.name), hints[field.name]
        if dataclasses.is_dataclass(hint):
            lines += [f"{indent}{field.name}:  # {hint.__doc__.splitlines()[0]}", *_yaml_lines(value, indent + "  ")]
        else:
            entry = OmegaConf.to_yaml({field.name: value}).strip()
            lines.append(f"{indent}{entry}  # {type_name(hint)}: {docs[field.name]}")
    return lines


SPECIALIST_YAML_HEADER = """\
# PPO hyperparameters of a specialist (one parameter set per level), read by `agents.PPOConfig.from_mapping`.
# Generated from their declaration (`agents.PPOHyperparameters` and `agents.PPOConfig`) by
# `kforge.pipeline.generation.config_yaml.specialist_yaml`; a test keeps this file equal to it.
# Why these values (Kinetix's where marked, our choice otherwise) and how well the experts do: docs/experts.md.
"""


def specialist_yaml() -> str:
    """configs/ppo_specialist.yaml: `agents.PPOConfig`'s defaults, each key after the comment it is declared with
    (imports JAX)."""
    from kforge.agents import PPOConfig, PPOHyperparameters

    docs = field_docs(PPOHyperparameters) | field_docs(PPOConfig)
    lines = [SPECIALIST_YAML_HEADER]
    for field in dataclasses.fields(PPOConfig):
        value = getattr(PPOConfig(), field.name)
        entry = OmegaConf.to_yaml({field.name: getattr(value, "value", value)}).strip()
        lines.append(f"# {docs[field.name][0].upper()}{docs[field.name][1:]}.\n{entry}\n")
    return "".join(lines)
