"""Which trajectories a BC run learns from: the dataset's kept levels, split into training and held-out validation
levels by a seeded permutation (a level's trajectories are all on one side)."""

from __future__ import annotations

import math

import numpy as np

from kforge.pipeline.storage import iter_records, open_dataset, require_intact


def kept_levels(dataset: str) -> dict[int, list[int]]:
    """Level id -> the global slots of its committed, kept trajectories; `DatasetDamaged` if a committed level
    batch's data files are missing or differ from their recorded sha256 (a learner reads nothing unchecked)."""
    require_intact(dataset)
    levels: dict[int, list[int]] = {}
    for record in iter_records(open_dataset(dataset).store):
        for level in record.levels:
            if level.kept:
                levels.setdefault(level.level_id, []).append(level.slot)
    return levels


def validation_split(level_ids: list[int], fraction: float, seed: int) -> tuple[list[int], list[int]]:
    """(training, validation) level ids: ceil(fraction * n) validation levels (at least one when fraction > 0 and
    there are two levels or more), drawn by a permutation seeded with `seed`; both lists sorted."""
    ids = sorted(level_ids)
    count = 0 if fraction <= 0 or len(ids) < 2 else min(len(ids) - 1, max(1, math.ceil(fraction * len(ids))))
    order = np.random.default_rng(seed).permutation(len(ids))
    validation = sorted(ids[i] for i in order[:count])
    held_out = set(validation)
    return [level for level in ids if level not in held_out], validation
