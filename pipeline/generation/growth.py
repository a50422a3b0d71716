"""Resuming on an existing dataset: the job must define the same data; a larger `split.num_levels` grows it.

Level i is the same level whatever the split's level count (its keys derive from (seed, i)), so raising the count
appends levels: the dataset's arrays get the new shards' slots and every existing commit stays valid, except the
level batches holding padding slots that become levels, whose commits are withdrawn so the run regenerates them.
The grown dataset equals one generated at the larger count from the start. Lowering the count is refused.
"""

from __future__ import annotations

from kforge.pipeline.generation.definition import GROWABLE_KEY, definition_fingerprint
from kforge.pipeline.storage import DatasetSpec, grow_dataset, open_dataset


class ResumeRefused(ValueError):
    """The output directory holds a dataset made with a config that would change the data."""


FINGERPRINT = "data_fingerprint"
DEFINITION = "data_config"
"""Keys of the data fingerprint and the data definition among a dataset's attributes."""


def reconcile_dataset(root: str, spec: DatasetSpec) -> list[tuple[int, int]]:
    """Check that the dataset at `root` holds the data `spec` (the job's) defines, and grow it to `spec` if the job
    has more levels; returns the (shard, batch) commits withdrawn by growing. `ResumeRefused` naming the keys that
    differ, or both level counts if the job has fewer levels."""
    stored = open_dataset(root).spec
    old, new = stored.attributes.get(DEFINITION, {}), spec.attributes[DEFINITION]
    if stored.attributes.get(FINGERPRINT) != definition_fingerprint(new):
        changed = [key for key in changed_keys(old, new) if not key.startswith(".".join(GROWABLE_KEY) + " ")]
        raise ResumeRefused(
            f"{root} holds a dataset generated with a different config; these keys would change the data: "
            f"{', '.join(changed) or '(unknown: older dataset)'}. Use another output_dir or the original values."
        )
    section, key = GROWABLE_KEY
    old_levels, new_levels = old[section][key], new[section][key]
    if new_levels < old_levels:
        raise ResumeRefused(
            f"{root} holds {old_levels} levels; split.num_levels={new_levels} would shrink it, which is refused "
            f"(a dataset only grows). Use split.num_levels={old_levels} or more, or another output_dir."
        )
    if stored.to_json() == spec.to_json():
        return []
    return grow_dataset(root, spec, (old_levels, new_levels))


def changed_keys(old: dict, new: dict, prefix: str = "") -> list[str]:
    """Dotted keys whose values differ between two nested dicts, each as "key (old -> new)"."""
    keys = []
    for key in sorted(set(old) | set(new)):
        a, b = old.get(key), new.get(key)
        if isinstance(a, dict) and isinstance(b, dict):
            keys += changed_keys(a, b, f"{prefix}{key}.")
        elif a != b:
            keys.append(f"{prefix}{key} ({a!r} -> {b!r})")
    return keys
