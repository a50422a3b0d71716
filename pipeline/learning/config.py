"""Behaviour-cloning run configuration: an OmegaConf structured schema (configs/bc.yaml holds its defaults), loaded
with `key=value` overrides and written into the run directory with every key's type and meaning.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from omegaconf import MISSING, OmegaConf

from kforge import configs
from kforge.pipeline.generation import (
    TRACKING_MODES,
    ConfigError,
    load_yaml,
    merge_layers,
    parse_overrides,
    to_schema_object,
)

RUN_CONFIG_FILE = "config.yaml"
"""The resolved config in the run directory."""

DEFAULT_RUN_ROOT = "outputs/bc"
"""Folder of the default run directory, `outputs/bc/<dataset folder name>-<architecture>`."""

LEVEL_SETS = ("train", "validation", "unseen", "hand")
"""Level sets `kforge evaluate` plays (pipeline/learning/evaluation.py)."""

ARCHITECTURES = ("mlp", "transformer")
"""Values of `model.architecture` (agents.Architecture's), named here so that checking a config imports no JAX."""

DEFAULT_BATCH_SIZE = 32
"""[trajectories] `train.batch_size` when it is null and the dataset's training trajectories fill it (Kinetix's offline
BC: 8192 transitions per step, 32 trajectories of 256 steps)."""


@dataclasses.dataclass
class ModelSection:
    """The policy network (agents.bc_networks)."""

    architecture: str = "transformer"  # mlp (symbolic flat observations) or transformer (symbolic entity observations)
    hidden_size: int = 256  # mlp: units per hidden layer; transformer: units of the head after pooling
    num_hidden_layers: int = 3  # mlp: hidden ReLU layers
    embed_size: int = 128  # transformer: entity embedding width
    num_heads: int = 4  # transformer: attention heads; divides attention_size
    num_layers: int = 2  # transformer: attention blocks (Kinetix's BC: 2)
    attention_size: int = 16  # transformer: query/key/value width over all heads (Kinetix's BC: 16)


@dataclasses.dataclass
class TrainSection:
    """Optimisation; all of it defines the run's parameters except the step count, which may be raised to continue."""

    num_steps: int = 20000  # most gradient steps (fewer when validation stops at a plateau; raise it to train on)
    batch_size: int | None = None  # trajectories per step, a multiple of the devices; null: 32 or what the data fills
    learning_rate: float = 3.0e-4  # AdamW step size (Kinetix's offline BC: 3e-4)
    anneal: bool = True  # decay the step size linearly to 0 at num_steps
    weight_decay: float = 1.0e-4  # AdamW decoupled weight decay
    max_grad_norm: float = 0.5  # global-norm gradient clipping (Kinetix: 0.5)
    levels: int | None = None  # learn from the first N kept levels by id (validation included); null: all
    seed: int = 0  # parameter initialisation, validation levels and batch order
    prefetch: int = 2  # batches the loader reads ahead in a background thread
    cache_gb: float = 4.0  # [GiB] hold the training trajectories in host memory when they fit (decoded); 0: stream


@dataclasses.dataclass
class ValidationSection:
    """Held-out levels of the dataset: never trained on, scored every `every_steps` steps."""

    fraction: float = 0.1  # share of the dataset's levels held out (at least one level when the dataset has two)
    every_steps: int = 100  # steps between two validations (and after the last step)
    batch_size: int = 32  # trajectories per validation batch
    patience: int = 10  # [validations] stop after this many in a row without an improvement; 0: never stop early
    min_improvement: float = 1.0e-3  # [nats] a loss this much below the best so far is an improvement


@dataclasses.dataclass
class CheckpointSection:
    """Checkpoints in <run>/checkpoints; a re-run resumes from the latest."""

    every_steps: int = 200  # steps between two checkpoints (and after the last step, and on Ctrl-C)
    keep: int = 2  # most recent checkpoints kept


@dataclasses.dataclass
class BCTrackingSection:
    """Experiment tracking; none of these change the run's parameters."""

    wandb: str = "offline"  # offline: local run files (`wandb sync` uploads them); online: needs a login; disabled
    project: str = "kforge"  # wandb project
    name: str | None = None  # wandb run name; None: wandb picks one


@dataclasses.dataclass
class BCConfig:
    """A behaviour-cloning run: which dataset, which network, how it is trained, validated and checkpointed."""

    dataset: str = MISSING  # the dataset to learn from: a local path, s3://... or gs://...
    output_dir: str = (
        MISSING  # run directory (created; re-running resumes); unset: outputs/bc/<dataset name>-<architecture>
    )
    model: ModelSection = dataclasses.field(default_factory=ModelSection)
    train: TrainSection = dataclasses.field(default_factory=TrainSection)
    validation: ValidationSection = dataclasses.field(default_factory=ValidationSection)
    checkpoint: CheckpointSection = dataclasses.field(default_factory=CheckpointSection)
    tracking: BCTrackingSection = dataclasses.field(default_factory=BCTrackingSection)


RESUMABLE_CHANGES = {
    ("train", "num_steps"),
    ("train", "prefetch"),
    ("train", "cache_gb"),
    ("validation", "patience"),
    ("validation", "min_improvement"),
    ("output_dir",),
} | {("tracking", field.name) for field in dataclasses.fields(BCTrackingSection)}
"""Keys a resumed run may change; any other difference from the run directory's config is refused."""


def load_bc_config(dataset: str | None, overrides: list[str] = (), path: str | Path | None = None) -> BCConfig:
    """The BC config: schema defaults, configs/bc.yaml (or `path`), then `dataset`, then `key=value` overrides.

    Raises `ConfigError` naming the layer and the key.
    """
    path = configs.BC if path is None else Path(path)
    layers = [(str(path), load_yaml(path))]
    if dataset is not None:
        layers.append(("DATASET", OmegaConf.create({"dataset": str(dataset)})))
    layers.append(("overrides", parse_overrides(list(overrides))))
    config = merge_layers(BCConfig, layers)
    if OmegaConf.is_missing(config, "output_dir") and not OmegaConf.is_missing(config, "dataset"):
        name = str(config.dataset).rstrip("/").rsplit("/", 1)[-1] or "dataset"
        config.output_dir = f"{DEFAULT_RUN_ROOT}/{name}-{config.model.architecture}"
    bc: BCConfig = to_schema_object(config, BCConfig)
    check_bc_config(bc)
    return bc


def run_config_file(run_dir: str | Path) -> Path:
    """The config file of a BC run directory; `FileNotFoundError` naming the directory when it holds none."""
    path = Path(run_dir) / RUN_CONFIG_FILE
    if not path.is_file():
        raise FileNotFoundError(
            f"{run_dir}: not a BC run directory (no {RUN_CONFIG_FILE}); train one with kforge bc train"
        )
    return path


def network_config(config: BCConfig):
    """The network (`agents.NetworkConfig`) of the `model` section, checked by `check_bc_config`."""
    from kforge.agents import Architecture, NetworkConfig

    model = config.model
    try:
        return NetworkConfig(
            architecture=Architecture(model.architecture),
            hidden_size=model.hidden_size,
            num_hidden_layers=model.num_hidden_layers,
            embed_size=model.embed_size,
            num_heads=model.num_heads,
            num_layers=model.num_layers,
            attention_size=model.attention_size,
        )
    except ValueError as error:
        raise ConfigError(f"model: {error}") from error


def check_bc_config(config: BCConfig) -> None:
    """Errors naming the key for values the schema's types cannot rule out (the network's sizes as
    `agents.NetworkConfig` checks them)."""
    model = config.model
    if model.architecture not in ARCHITECTURES:
        raise ConfigError(f"model.architecture must be one of {', '.join(ARCHITECTURES)}, got {model.architecture!r}")
    for name in ("hidden_size", "num_hidden_layers", "embed_size", "num_heads", "num_layers", "attention_size"):
        if getattr(model, name) < 1:
            raise ConfigError(f"model.{name} must be >= 1, got {getattr(model, name)}")
    if model.attention_size % model.num_heads:
        raise ConfigError(
            f"model.num_heads ({model.num_heads}) must divide model.attention_size ({model.attention_size})"
        )
    if config.train.batch_size is not None and config.train.batch_size < 1:
        raise ConfigError(f"train.batch_size must be >= 1 or null, got {config.train.batch_size}")
    positive = (
        "train.num_steps",
        "validation.every_steps",
        "validation.batch_size",
        "checkpoint.every_steps",
        "checkpoint.keep",
    )
    for key in positive:
        section, name = key.split(".")
        if getattr(getattr(config, section), name) < 1:
            raise ConfigError(f"{key} must be >= 1, got {getattr(getattr(config, section), name)}")
    for key in ("train.learning_rate", "train.max_grad_norm"):
        section, name = key.split(".")
        if not getattr(getattr(config, section), name) > 0:
            raise ConfigError(f"{key} must be > 0, got {getattr(getattr(config, section), name)}")
    if config.train.weight_decay < 0:
        raise ConfigError(f"train.weight_decay must be >= 0, got {config.train.weight_decay}")
    if config.validation.patience < 0:
        raise ConfigError(f"validation.patience must be >= 0, got {config.validation.patience}")
    if config.validation.min_improvement < 0:
        raise ConfigError(f"validation.min_improvement must be >= 0, got {config.validation.min_improvement}")
    if config.train.levels is not None and config.train.levels < 1:
        raise ConfigError(f"train.levels must be >= 1 or null, got {config.train.levels}")
    if config.train.cache_gb < 0:
        raise ConfigError(f"train.cache_gb must be >= 0, got {config.train.cache_gb}")
    if config.train.prefetch < 0:
        raise ConfigError(f"train.prefetch must be >= 0, got {config.train.prefetch}")
    if not 0 <= config.validation.fraction < 1:
        raise ConfigError(f"validation.fraction must be in [0, 1), got {config.validation.fraction}")
    if config.tracking.wandb not in TRACKING_MODES:
        raise ConfigError(f"tracking.wandb must be one of {', '.join(TRACKING_MODES)}, got {config.tracking.wandb!r}")


def fit_batch_size(config: BCConfig, train_trajectories: int, num_devices: int) -> BCConfig:
    """`config` with `train.batch_size` resolved for `train_trajectories` split over `num_devices`: a null batch size
    becomes `DEFAULT_BATCH_SIZE`, or the largest multiple of `num_devices` the trajectories fill when they are fewer;
    `ConfigError` names the value that works when a set batch size cannot be filled."""
    fitting = train_trajectories // num_devices * num_devices
    if fitting < 1:
        raise ConfigError(
            f"{config.dataset}: {train_trajectories} training trajectories cannot fill a batch over the "
            f"{num_devices} local devices; lower validation.fraction or use a larger dataset"
        )
    requested = config.train.batch_size
    if requested is None:
        resolved = min(DEFAULT_BATCH_SIZE, fitting)
    elif requested > train_trajectories:
        raise ConfigError(
            f"train.batch_size={requested} exceeds the {train_trajectories} training trajectories of "
            f"{config.dataset}; use train.batch_size={fitting} (or leave it null)"
        )
    else:
        resolved = requested
    return dataclasses.replace(config, train=dataclasses.replace(config.train, batch_size=resolved))


def changed_keys(stored: BCConfig, requested: BCConfig) -> list[str]:
    """Dotted keys whose values differ between two configs, except those a resumed run may change."""
    first, second = (
        OmegaConf.to_container(OmegaConf.structured(stored)),
        OmegaConf.to_container(OmegaConf.structured(requested)),
    )
    changed = []
    for key in sorted(set(first) | set(second)):
        if isinstance(first.get(key), dict):
            changed += [
                f"{key}.{name}"
                for name in sorted(set(first[key]) | set(second.get(key, {})))
                if (key, name) not in RESUMABLE_CHANGES and first[key].get(name) != second.get(key, {}).get(name)
            ]
        elif (key,) not in RESUMABLE_CHANGES and first.get(key) != second.get(key):
            changed.append(key)
    return changed
