"""The YAML configs that ship with kforge: release splits (`splits/<budget>/<size>.yaml`, named like "1M/s"),
scale presets (`scales/<name>.yaml`), the specialists' PPO settings (`ppo_specialist.yaml`) and the behaviour-cloning
defaults (`bc.yaml`).

Standard library only, so that the command line can list them without importing JAX.
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["BC", "YAML_SUFFIXES", "scale_names", "scale_path", "split_names", "split_path"]

CONFIGS_DIR = Path(__file__).resolve().parent
"""The installed config folder."""

SPLITS_DIR = CONFIGS_DIR / "splits"
"""Release splits: split "1M/s" is SPLITS_DIR/1M/s.yaml."""

SCALES_DIR = CONFIGS_DIR / "scales"
"""Scale presets: `--scale NAME` reads SCALES_DIR/NAME.yaml."""

PPO_SPECIALIST = CONFIGS_DIR / "ppo_specialist.yaml"
"""The specialists' PPO settings, equal to `agents.PPOConfig`'s defaults."""

BC = CONFIGS_DIR / "bc.yaml"
"""Defaults of `kforge bc train`, equal to `pipeline.learning.BCConfig`'s schema defaults."""

YAML_SUFFIXES = (".yaml", ".yml")


def split_names() -> list[str]:
    """Names of the release splits, e.g. ["10M/m", "10M/s", "1M/l", "1M/m", "1M/s"]."""
    return sorted(path.relative_to(SPLITS_DIR).with_suffix("").as_posix() for path in SPLITS_DIR.glob("*/*.yaml"))


def scale_names() -> list[str]:
    """Names of the scale presets, e.g. ["full", "local", "tiny"]."""
    return sorted(path.stem for path in SCALES_DIR.glob("*.yaml"))


def split_path(name: str) -> Path | None:
    """The YAML file of a release split named like "1M/s", or None if there is no such split."""
    path = SPLITS_DIR / f"{name}.yaml"
    return path if name in split_names() else None


def scale_path(name: str) -> Path | None:
    """The YAML file of a scale preset, or None if there is no such preset."""
    return SCALES_DIR / f"{name}.yaml" if name in scale_names() else None
