"""Job configuration: an OmegaConf structured schema, loading with dotlist overrides, and the data-defining hash.

A job composes, later layers winning: the schema defaults, a config file (e.g. a release split,
configs/splits/1M/s.yaml), a scale preset (configs/scales/{tiny,local,full}.yaml) and `key=value` overrides. Every
key is documented by the comment on its line in the schema below; `to_yaml` writes the resolved config with each
key's type and comment.

Loading, merging, validating and writing a config import neither JAX nor Ray, so every config error is answered at
once: the checks that need the training code (`check_training`, run by `load_config` after the cheap ones) and the
functions that build the engine's and the agents' parameters (`environment`, `ppo_config`, `data_definition`) import
it when called.
"""

from __future__ import annotations

import ast
import dataclasses
import difflib
import hashlib
import inspect
import io
import json
import math
import sys
import textwrap
import tokenize
import typing
from pathlib import Path

import yaml
from omegaconf import MISSING, DictConfig, OmegaConf
from omegaconf.errors import ConfigKeyError, MissingMandatoryValue, OmegaConfBaseException, ValidationError

from kforge import configs
from kforge.pipeline.generation.compile_cache import DEFAULT_COMPILE_CACHE_DIR

PHYSICS_SCHEME_NAMES = ("kforge", "kinetix")
"""Names of the engine's physics schemes (`engine.PHYSICS_SCHEMES`), the values of `env.physics`."""

JOB_PHYSICS_SCHEME = "kinetix"
"""The scheme a job plays under unless `env.physics` names another: Kinetix's play, as the data stands for Kinetix's
(the engine's own default scheme, kforge, stays available)."""

ENV_SIZES = ("s", "m", "l")
"""Kinetix env sizes (`engine.KINETIX_SIZES`), the values of `split.size`."""

DATASET_CONFIG_FILE = "config.yaml"
"""The job config a dataset keeps at its root (`pipeline.storage.CONFIG_FILE`)."""


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
    """Specialist PPO settings; the defaults are `agents.PPOConfig`'s (evidence for them: docs/experts.md)."""

    num_envs: int = 16  # parallel episodes per level
    num_steps: int = 125  # env steps per env between two updates (rollout length)
    update_epochs: int = 4  # passes over each rollout
    num_minibatches: int = 4  # minibatches per epoch; must divide num_envs * num_steps
    learning_rate: float = 3e-4  # Adam step size, constant
    adam_eps: float = 1e-5  # Adam epsilon (Kinetix)
    max_grad_norm: float = 1.0  # global-norm gradient clipping before Adam (Kinetix)
    gamma: float = 0.995  # discount per env step (Kinetix)
    gae_lambda: float = 0.9  # GAE lambda (Kinetix)
    clip_eps: float = 0.2  # PPO ratio clip, also the value-clipping range (Kinetix)
    ent_coef: float = 0.01  # entropy bonus weight (Kinetix)
    vf_coef: float = 0.5  # value loss weight (Kinetix)
    hidden_size: int = 64  # units per hidden layer, actor and critic (Kinetix: 128)
    num_hidden_layers: int = 2  # tanh hidden layers of each MLP (Kinetix: 5)
    bootstrap_truncation: bool = False  # time-limit ends bootstrap from the last value
    select_every_updates: int = 50  # evaluate every this many updates and after the last
    select_episodes: int = 16  # episodes per evaluation (acting as collect.greedy says)


@dataclasses.dataclass
class ExpertsConfig:
    """How long each expert trains (docs/experts.md, adaptive budgets)."""

    budget_mode: str = "fixed"  # fixed, streamed (filtered levels take no slot) or adaptive: docs/experts.md
    solved_evaluations: int = 2  # adaptive: stop after this many consecutive evaluations with every episode successful
    solved_window: bool = True  # adaptive: ... and only once the window the expert would store succeeds
    give_up_env_steps: int = 250_000  # adaptive: give up once trained this long without any successful episode


@dataclasses.dataclass
class CollectConfig:
    """The stored window of each expert."""

    window_steps: int = 256  # env steps per stored trajectory
    greedy: bool = False  # act with the most probable choice per slot instead of sampling


@dataclasses.dataclass
class EnvSection:
    """Environment parameters of the experts' training episodes."""

    dense_reward_scale: float = 0.2  # shaping scale used for training (Kinetix's repository configs use 0.2)
    physics: str = JOB_PHYSICS_SCHEME  # kinetix (Kinetix's play) or kforge (the engine's own), engine.PHYSICS_SCHEMES


@dataclasses.dataclass
class RayConfig:
    """Where the job runs; none of these change the data."""

    address: str | None = None  # None: embedded local Ray; "auto" or host:port: a running cluster
    num_workers: int = 1  # worker actors; 0: no Ray, the job's own process does the work
    cpus_per_worker: float = 1.0  # CPUs Ray reserves per worker actor
    gpus_per_worker: float = 0.0  # GPUs Ray reserves per worker actor (1.0: one GPU each; JAX then runs on it)
    deterministic_gpu_ops: bool = False  # workers turn on XLA's deterministic GPU ops (not needed: jobs repeat without)


@dataclasses.dataclass
class LeaseConfig:
    """The job's lease on its dataset (one job per dataset, docs/object-storage.md); none of these change the data.
    The defaults are `pipeline.storage`'s."""

    stale_after_s: float = 300.0  # [s] a lease whose heartbeat is older is taken over
    heartbeat_s: float = 30.0  # [s] interval between the running job's heartbeats


TRACKING_MODES = ("offline", "online", "disabled")
"""Values of `tracking.wandb`."""


@dataclasses.dataclass
class TrackingConfig:
    """Experiment tracking of a run (pipeline/generation/tracking.py); none of these change the data."""

    wandb: str = "offline"  # offline: local run files (`wandb sync` uploads them); online: needs a login; disabled
    project: str = "kforge"  # wandb project
    name: str | None = None  # wandb run name; None: wandb picks one
    dir: str | None = None  # directory that receives wandb/<run>; None: the dataset's log folder, beside the run logs


@dataclasses.dataclass
class CompileCacheConfig:
    """JAX's persistent compilation cache of the workers (on a cluster: storage the nodes share); none of these change
    the data."""

    dir: str | None = DEFAULT_COMPILE_CACHE_DIR  # folder of compiled programs reused by workers and re-runs; null: off


@dataclasses.dataclass
class JobConfig:
    """A generation job: the split, how it is cut and trained, and where it runs and writes."""

    output_dir: str = MISSING  # dataset directory (created; re-running resumes); unset: outputs/<split name>-<scale>
    scale: str | None = None  # scale preset applied over the config file (kforge run --scale); recorded, not re-applied
    split: SplitConfig = dataclasses.field(default_factory=SplitConfig)
    work: WorkConfig = dataclasses.field(default_factory=WorkConfig)
    filter: FilterConfig = dataclasses.field(default_factory=FilterConfig)
    env: EnvSection = dataclasses.field(default_factory=EnvSection)
    ppo: PPOSection = dataclasses.field(default_factory=PPOSection)
    experts: ExpertsConfig = dataclasses.field(default_factory=ExpertsConfig)
    collect: CollectConfig = dataclasses.field(default_factory=CollectConfig)
    ray: RayConfig = dataclasses.field(default_factory=RayConfig)
    lease: LeaseConfig = dataclasses.field(default_factory=LeaseConfig)
    tracking: TrackingConfig = dataclasses.field(default_factory=TrackingConfig)
    compile_cache: CompileCacheConfig = dataclasses.field(default_factory=CompileCacheConfig)


DATA_SECTIONS = ("split", "work", "filter", "env", "ppo", "experts", "collect")
"""Config sections that determine the dataset's content; a resumed job must agree on all of them."""

FIXED_BUDGET_MODE, STREAMED_BUDGET_MODE, ADAPTIVE_BUDGET_MODE = "fixed", "streamed", "adaptive"
BUDGET_MODES = (FIXED_BUDGET_MODE, STREAMED_BUDGET_MODE, ADAPTIVE_BUDGET_MODE)
"""Values of `experts.budget_mode`; a fixed-budget job's data definition leaves the `experts` section out (no key of
it changes a fixed-budget job's data)."""


class ConfigError(ValueError):
    """A job config that cannot be used; the message names the key."""


DEFAULT_OUTPUT_ROOT = "outputs"
"""Folder of the default output_dir, `outputs/<split name, '/' as '-'>-<scale>` (e.g. outputs/1M-s-tiny)."""

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
    if path is not None and _is_url(path):
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


def scale_path(scale: str) -> Path:
    """The YAML file of a scale: a preset name (see `configs.scale_names`) or a path ending in .yaml."""
    path = Path(scale) if scale.endswith(configs.YAML_SUFFIXES) else configs.scale_path(scale)
    if path is None or not path.is_file():
        raise ConfigError(
            f"scale {scale!r}: expected one of {', '.join(configs.scale_names())} or a path to a YAML file"
        )
    return path


def config_path(config: str | Path) -> Path | str:
    """The job YAML of CONFIG: an existing file, a dataset (a folder, or an `s3://`, `gs://` URL, holding the
    `config.yaml` of its latest run; a URL may also name a YAML object), or a release split's name such as "1M/s"
    (`configs.split_names`)."""
    if _is_url(config):
        from kforge.pipeline.storage import join

        return str(config) if str(config).endswith(configs.YAML_SUFFIXES) else join(config, DATASET_CONFIG_FILE)
    path = Path(config)
    if path.is_file():
        return path
    if (path / DATASET_CONFIG_FILE).is_file():
        return path / DATASET_CONFIG_FILE
    split = configs.split_path(str(config))
    if split is not None:
        return split
    raise ConfigError(
        f"config {str(config)!r}: no such file, and not a split name (splits: {', '.join(configs.split_names())})"
    )


def _is_url(location: str | Path) -> bool:
    """True for an object-store URL (`pipeline.storage.is_remote`)."""
    if not isinstance(location, str) or "://" not in location:
        return False
    from kforge.pipeline.storage import is_remote  # the storage layer imports JAX: only for URLs

    return is_remote(location)


def absolute_output_dir(output_dir: str) -> Path | str:
    """Where a job writes, as every machine names it: a local path made absolute, an `s3://`, `gs://` URL as given."""
    return output_dir if _is_url(output_dir) else Path(output_dir).resolve()


def default_output_dir(split_name: str, scale: str | None) -> str:
    """`outputs/<split name with '/' as '-'>[-<scale name>]`, e.g. outputs/1M-s-tiny."""
    name = split_name.replace("/", "-") + (f"-{Path(scale).stem}" if scale else "")
    return f"{DEFAULT_OUTPUT_ROOT}/{name}"


def load_yaml(path: str | Path) -> DictConfig:
    """A YAML file's mapping; `path` is a local file or an object-store URL (read through the store layer)."""
    try:
        if _is_url(path):
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


def _schema_type(key: str, schema: type = JobConfig):
    """The annotated type of a dotted key in `schema` (`schema` itself for ""); None if there is no such key."""
    hint = schema
    for part in key.split(".") if key else ():
        if not dataclasses.is_dataclass(hint):
            return None
        hint = typing.get_type_hints(hint).get(part)
    return hint


def type_name(hint) -> str:
    """A schema type as users write it: int, float, bool, str, "str or null", "section"."""
    if dataclasses.is_dataclass(hint):
        return "section"
    args = typing.get_args(hint)
    if args:
        return " or ".join("null" if arg is type(None) else type_name(arg) for arg in args)
    return hint.__name__


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
    hint = _schema_type(key, schema) if key else None
    if isinstance(error, ValidationError) and hint is not None:
        value = getattr(error, "value", None)
        return ConfigError(f"{where}: {key}: expected {type_name(hint)}, got {value!r} ({type(value).__name__})")
    first_line = str(error).splitlines()[0]
    return ConfigError(f"{where}: {key}: {first_line}" if key else f"{where}: {first_line}")


def _unknown_key_message(key: str, root: type) -> str:
    parent, _, name = key.rpartition(".")
    schema = _schema_type(parent, root)
    if not dataclasses.is_dataclass(schema):
        return f"unknown key {key}"
    names = [field.name for field in dataclasses.fields(schema)]
    prefix = f"{parent}." if parent else ""
    close = difflib.get_close_matches(name, names, n=1)
    suggestion = f" (did you mean {prefix}{close[0]}?)" if close else ""
    return f"unknown key {key}{suggestion}; {parent or 'the top level'} has: {', '.join(names)}"


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


def data_definition(job: JobConfig) -> dict:
    """What defines the dataset's content, as JSON values: the config's data sections (`experts` only where a budget
    mode reads it), and the physics the levels play under: the scheme's name, every engine parameter of a step and
    every solver setting (set by the code, not the config, so that data made by code with other physics is told
    apart)."""
    sections = [name for name in DATA_SECTIONS if name != "experts" or job.experts.budget_mode != FIXED_BUDGET_MODE]
    data = {section: dataclasses.asdict(getattr(job, section)) for section in sections}
    params, static = environment(job)
    return data | {"physics": physics_definition(job.env.physics, params.sim, static.sim)}


def physics_definition(scheme: str, sim, static_sim) -> dict:
    """The physics entry of the data definition: `{"scheme": scheme, **every field of sim (engine.SimParams),
    **static_sim.physics_options() (engine.StaticSimParams)}`, as JSON values (`json_value`)."""
    fields = {"scheme": scheme, **dataclasses.asdict(sim), **static_sim.physics_options()}
    return {key: json_value(value) for key, value in fields.items()}


NON_FINITE_FLOATS = {math.inf: "inf", -math.inf: "-inf"}
"""How infinite parameters are written in a data definition (JSON has no infinity)."""


def json_value(value):
    """A parameter as a plain JSON value: enums as their ints, infinite floats as "inf" / "-inf"; NaN is refused."""
    if isinstance(value, bool) or isinstance(value, str):
        return value
    if isinstance(value, int):
        return int(value)
    value = float(value)
    if math.isnan(value):
        raise ValueError("a physics parameter is NaN; a data definition holds numbers only")
    return NON_FINITE_FLOATS.get(value, value)


GROWABLE_KEY = ("split", "num_levels")
"""The one data-defining key a dataset may change after it is made: raising it appends levels (level i is the same
level whatever the count), so the data fingerprint leaves it out."""


def data_fingerprint(job: JobConfig) -> str:
    """Hash of `data_definition` without `split.num_levels`: equal fingerprints mean that level i's data is the same
    in both datasets, whatever their level counts."""
    return definition_fingerprint(data_definition(job))


def definition_fingerprint(definition: dict) -> str:
    """The data fingerprint of a stored `data_definition` (`data_config` among a dataset's attributes)."""
    section, key = GROWABLE_KEY
    countless = definition | {section: {k: v for k, v in definition.get(section, {}).items() if k != key}}
    return hashlib.sha256(json.dumps(countless, sort_keys=True, allow_nan=False).encode()).hexdigest()[:16]


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
