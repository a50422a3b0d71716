"""Loading a job config: the schema's defaults, then a config file, a scale preset and overrides, merged."""

from __future__ import annotations

import dataclasses
import difflib
import sys
import typing
from pathlib import Path

import yaml
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import ConfigKeyError, MissingMandatoryValue, OmegaConfBaseException, ValidationError

from kforge.pipeline.generation.schema import ConfigError, JobConfig, schema_type, type_name
from kforge.pipeline.generation.sources import (
    DATASET_CONFIG_FILE,
    config_path,
    default_output_dir,
    is_url,
    scale_path,
)
from kforge.pipeline.generation.validation import check_config, check_training

OVERRIDES = "overrides"
"""How errors name the `key=value` layer."""


def load_config(path: str | Path | None = None, overrides: list[str] = (), scale: str | None = None) -> JobConfig:
    """The job config: schema defaults, then the YAML file `path`, then the scale preset, then `key=value` overrides
    (later layers win), validated (`read_config`, then `check_training`).

    Raises `ConfigError` naming the layer and the key (and for a wrong type, the expected type).
    """
    job = read_config(path, overrides, scale)
    check_training(job)
    return job


def read_config(path: str | Path | None = None, overrides: list[str] = (), scale: str | None = None) -> JobConfig:
    """The job config of `load_config` with the checks that need no training code (`check_config`); imports neither
    JAX nor Ray. `scale` is a preset name in configs/scales or a YAML path; it is recorded in the config's `scale`
    key. Without an output_dir it is derived from split.name and the scale (`default_output_dir`).

    `path` may name a dataset in object storage, whose `config.yaml` someone else wrote: the keys that say where the
    job runs and what it loads (`WHERE_KEYS`) are taken from the command and the schema, never from it, and its
    output_dir is the dataset named. A notice on stderr names each such key it set to another value that neither the
    scale nor an override sets.
    """
    layers = []
    if path is not None:
        path = config_path(path)
        layers.append((str(path), load_yaml(path)))
    if scale is not None:
        layers.append((str(scale_path(scale)), load_yaml(scale_path(scale))))
    layers.append((OVERRIDES, parse_overrides(overrides)))
    if path is not None and is_url(path):
        layers[0] = (str(path), _without_where_keys(layers[0][1], str(path), [layer for _, layer in layers[1:]]))
    for index, (where, layer) in enumerate(layers):
        if "scale" in layer and not (index == 0 and path is not None):
            raise ConfigError(f"{where}: scale: a scale preset is applied with --scale NAME, not set as a key")
    config = merge_layers(JobConfig, layers)
    try:
        if scale is not None:
            config.scale = scale
        if OmegaConf.is_missing(config, "output_dir") and not OmegaConf.is_missing(config.split, "name"):
            config.output_dir = default_output_dir(config.split.name, config.scale)
    except OmegaConfBaseException as error:
        raise _config_error(error, "config", JobConfig) from error
    job: JobConfig = to_schema_object(config, JobConfig)
    check_config(job)
    return job


WHERE_KEYS = ("output_dir", "ray.address", "compile_cache.dir", "tracking.dir")
"""Keys that say where a job runs, writes or loads code from: a dataset's stored config does not set them."""


def _without_where_keys(layer: DictConfig, where: str, later_layers: list[DictConfig]) -> DictConfig:
    """A remote config layer without `WHERE_KEYS` (a dataset's `config.yaml`: its output_dir the dataset itself); a
    notice on stderr for each key it set to a value the job will not use, unless a later layer sets the key."""
    values = OmegaConf.to_container(layer, resolve=False)
    later = [OmegaConf.to_container(later_layer, resolve=False) for later_layer in later_layers]
    folder, _, file_name = where.rpartition("/")
    dataset = folder if file_name == DATASET_CONFIG_FILE else None
    defaults = OmegaConf.to_container(OmegaConf.structured(JobConfig), resolve=False)
    for key in WHERE_KEYS:
        section, _, name = key.rpartition(".")
        if not _sets(values, section, name):
            continue
        value = (values[section] if section else values).pop(name)
        default = dataset if key == "output_dir" else (defaults[section] if section else defaults)[name]
        if value != default and not any(_sets(later_values, section, name) for later_values in later):
            print(
                f"notice: {where} sets {key}={value!r}; ignored, a dataset does not say where a job runs",
                file=sys.stderr,
            )
    if dataset is not None:
        values["output_dir"] = dataset
    return OmegaConf.create(values)


def _sets(values: dict, section: str, name: str) -> bool:
    """Whether a layer's `values` set key `name` of `section` ("" for the top level)."""
    holder = values.get(section) if section else values
    return isinstance(holder, dict) and name in holder


def merge_layers(schema: type, layers: list[tuple[str, DictConfig]]) -> DictConfig:
    """The structured config of dataclass `schema`: its defaults, then each (where, layer) in order, later winning.

    Raises `ConfigError` naming the layer (`where`) and the key.
    """
    config = OmegaConf.structured(schema)
    for where, layer in layers:
        values = OmegaConf.to_container(layer, resolve=False)
        _check_no_interpolation(values, where)
        _check_sections(values, schema, where)
        try:
            config = OmegaConf.merge(config, layer)
        except OmegaConfBaseException as error:
            raise _config_error(error, where, schema) from error
    return config


def _check_no_interpolation(values, where: str, key: str = "") -> None:
    """A layer's values are taken as written: `${...}` (which OmegaConf would resolve, environment variables
    included) is refused, naming the key."""
    if isinstance(values, dict):
        for name, value in values.items():
            _check_no_interpolation(value, where, f"{key}.{name}" if key else str(name))
    elif isinstance(values, list):
        for index, value in enumerate(values):
            _check_no_interpolation(value, where, f"{key}[{index}]")
    elif isinstance(values, str) and "${" in values:
        raise ConfigError(f"{where}: {key}: interpolations such as {values!r} are not accepted; write the value itself")


def to_schema_object(config: DictConfig, schema: type):
    """The `schema` dataclass instance of a merged config; `ConfigError` names a missing or mistyped key."""
    try:
        return OmegaConf.to_object(config)
    except OmegaConfBaseException as error:
        raise _config_error(error, "config", schema) from error


def load_yaml(path: str | Path) -> DictConfig:
    """A YAML file's mapping; `path` is a local file or an object-store URL (read through the store layer)."""
    try:
        if is_url(path):
            from kforge.pipeline.storage import StoreError, open_store

            folder, _, name = str(path).rpartition("/")
            try:
                text = open_store(folder).read(name)
            except StoreError as error:
                raise ConfigError(f"{path}: cannot read ({error})") from error
            if text is None:
                raise FileNotFoundError(path)
            layer = OmegaConf.create(text.decode())
        else:
            layer = OmegaConf.load(path)
    except FileNotFoundError as error:
        raise ConfigError(f"config file not found: {path}") from error
    except yaml.YAMLError as error:
        raise ConfigError(f"{path}: not valid YAML ({str(error).splitlines()[0]})") from error
    if not isinstance(layer, DictConfig):
        raise ConfigError(f"{path}: expected a mapping of keys at the top level, got a list")
    return layer


def parse_overrides(overrides: list[str]) -> DictConfig:
    for override in overrides:
        if "=" not in override:
            raise ConfigError(f"{OVERRIDES}: {override!r} is not of the form key=value")
    try:
        return OmegaConf.from_dotlist(list(overrides))
    except yaml.YAMLError as error:
        raise ConfigError(f"{OVERRIDES}: a value is not valid YAML ({str(error).splitlines()[0]})") from error


def _check_sections(values: dict, schema: type, where: str, prefix: str = "") -> None:
    """A section of the schema must be given as a mapping (OmegaConf's own message does not name it)."""
    hints = typing.get_type_hints(schema)
    for key, value in values.items():
        hint = hints.get(key)
        if not dataclasses.is_dataclass(hint):
            continue
        if not isinstance(value, dict):
            keys = ", ".join(field.name for field in dataclasses.fields(hint))
            raise ConfigError(f"{where}: {prefix}{key}: expected a section with keys {keys}; got {value!r}")
        _check_sections(value, hint, where, f"{prefix}{key}.")


def _config_error(error: OmegaConfBaseException, where: str, schema: type) -> ConfigError:
    key = getattr(error, "full_key", None) or ""
    if isinstance(error, ConfigKeyError) and key:
        return ConfigError(f"{where}: {_unknown_key_message(key, schema)}")
    if isinstance(error, MissingMandatoryValue) and key:
        return ConfigError(f"{key}: missing; set it in the config file or as an override {key}=...")
    hint = schema_type(key, schema) if key else None
    if isinstance(error, ValidationError) and hint is not None:
        value = getattr(error, "value", None)
        return ConfigError(f"{where}: {key}: expected {type_name(hint)}, got {value!r} ({type(value).__name__})")
    first_line = str(error).splitlines()[0]
    return ConfigError(f"{where}: {key}: {first_line}" if key else f"{where}: {first_line}")


def _unknown_key_message(key: str, root: type) -> str:
    parent, _, name = key.rpartition(".")
    schema = schema_type(parent, root)
    if not dataclasses.is_dataclass(schema):
        return f"unknown key {key}"
    names = [field.name for field in dataclasses.fields(schema)]
    prefix = f"{parent}." if parent else ""
    close = difflib.get_close_matches(name, names, n=1)
    suggestion = f" (did you mean {prefix}{close[0]}?)" if close else ""
    return f"unknown key {key}{suggestion}; {parent or 'the top level'} has: {', '.join(names)}"
