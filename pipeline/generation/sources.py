"""Where a job's config layers and output come from: release split names, scale presets, datasets and URLs."""

from __future__ import annotations

from pathlib import Path

from kforge import configs
from kforge.pipeline.generation.schema import ConfigError

DATASET_CONFIG_FILE = "config.yaml"
"""The job config a dataset keeps at its root (`pipeline.storage.CONFIG_FILE`)."""

DEFAULT_OUTPUT_ROOT = "outputs"
"""Folder of the default output_dir, `outputs/<split name, '/' as '-'>-<scale>` (e.g. outputs/1M-s-tiny)."""


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
    if is_url(config):
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


def is_url(location: str | Path) -> bool:
    """True for an object-store URL (`pipeline.storage.is_remote`)."""
    if not isinstance(location, str) or "://" not in location:
        return False
    from kforge.pipeline.storage import is_remote  # the storage layer imports JAX: only for URLs

    return is_remote(location)


def absolute_output_dir(output_dir: str) -> Path | str:
    """Where a job writes, as every machine names it: a local path made absolute, an `s3://`, `gs://` URL as given."""
    return output_dir if is_url(output_dir) else Path(output_dir).resolve()


def default_output_dir(split_name: str, scale: str | None) -> str:
    """`outputs/<split name with '/' as '-'>[-<scale name>]`, e.g. outputs/1M-s-tiny."""
    name = split_name.replace("/", "-") + (f"-{Path(scale).stem}" if scale else "")
    return f"{DEFAULT_OUTPUT_ROOT}/{name}"
