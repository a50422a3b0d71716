"""Checkpoints of a BC run: the parameters, optimiser state and step count, as msgpack files in <run>/checkpoints.

A checkpoint is written to a temporary file and renamed, so a run killed while writing leaves the previous ones
intact; only the `keep` most recent are kept.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import TypeVar

from flax import serialization

CHECKPOINT_DIR = "checkpoints"
"""Folder of a run's checkpoints."""

_NAME = re.compile(r"^step-(\d{9})\.msgpack$")

State = TypeVar("State")


def checkpoint_path(run_dir: str | os.PathLike, step: int) -> Path:
    return Path(run_dir) / CHECKPOINT_DIR / f"step-{step:09d}.msgpack"


def checkpoint_steps(run_dir: str | os.PathLike) -> list[int]:
    """Steps of the run's checkpoints, oldest first."""
    folder = Path(run_dir) / CHECKPOINT_DIR
    if not folder.is_dir():
        return []
    return sorted(int(match.group(1)) for name in os.listdir(folder) if (match := _NAME.match(name)))


def save_checkpoint(run_dir: str | os.PathLike, step: int, state, keep: int) -> Path:
    """Write `state` (a pytree) as the checkpoint of `step`, then drop all but the `keep` most recent."""
    path = checkpoint_path(run_dir, step)
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_suffix(".partial")
    partial.write_bytes(serialization.to_bytes(state))
    os.replace(partial, path)
    for old in checkpoint_steps(run_dir)[:-keep]:
        checkpoint_path(run_dir, old).unlink(missing_ok=True)
    return path


def restore_checkpoint(run_dir: str | os.PathLike, step: int, template: State) -> State:
    """The checkpoint of `step`, with the structure of `template`."""
    path = checkpoint_path(run_dir, step)
    try:
        return serialization.from_bytes(template, path.read_bytes())
    except (ValueError, KeyError, TypeError) as error:
        raise ValueError(f"{path}: not a checkpoint of this run's model ({error})") from error
