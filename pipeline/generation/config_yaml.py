"""The resolved job config as YAML, each key commented with its type and meaning from the schema."""

from __future__ import annotations

import ast
import dataclasses
import inspect
import io
import textwrap
import tokenize
import typing

from omegaconf import OmegaConf

from kforge.pipeline.generation.schema import JobConfig, type_name


def field_docs(section: type) -> dict[str, str]:
    """Field name -> the comment on its line in the schema source (`name: type = default  # comment`)."""
    source = textwrap.dedent(inspect.getsource(section))
    tokens = tokenize.generate_tokens(io.StringIO(source).readline)
    comments = {token.start[0]: token.string.lstrip("#").strip() for token in tokens if token.type == tokenize.COMMENT}
    body = ast.parse(source).body[0].body
    return {node.target.id: comments.get(node.lineno, "") for node in body if isinstance(node, ast.AnnAssign)}


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
