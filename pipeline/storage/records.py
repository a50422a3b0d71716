"""Commit records, typed: a level batch's `BatchRecord` holds one `LevelRecord` per slot, each with an `Outcome`.

The manifest stores them as JSON (`BatchRecord.to_json`); readers get them back with `BatchRecord.from_json`, which
names the field of a malformed record.
"""

from __future__ import annotations

import dataclasses
import enum
from collections.abc import Mapping

from kforge.pipeline.storage.layout import DatasetError

FILTERED_PREFIX = "filtered:"
"""Outcome prefix of a level dropped by the trivial-level filter, followed by the reason's name."""

PROVENANCE = "provenance"
"""Record key of how a batch was made (wall times, worker); it varies between runs and is not part of the data."""


class Outcome(enum.StrEnum):
    """What became of a level (a string in the JSON record)."""

    KEPT = "kept"  # its trajectory is stored
    UNSOLVED = "unsolved"  # trained, but the expert window was not successful
    FAILED = "failed"  # training or rollout produced non-finite values (contained to that level)
    PADDING = "padding"  # a slot past `split.num_levels` in the last shard
    FILTERED_TOUCHING_AT_START = FILTERED_PREFIX + "touching_at_start"
    FILTERED_NO_ACTUATOR = FILTERED_PREFIX + "no_actuator"
    FILTERED_SOLVED_BY_NOOP = FILTERED_PREFIX + "solved_by_noop"

    @classmethod
    def filtered(cls, reason: str) -> Outcome:
        """The outcome of a level dropped by the filter for `reason` (a filter reason's lower-case name)."""
        return cls(FILTERED_PREFIX + reason)

    @property
    def is_filtered(self) -> bool:
        return self.value.startswith(FILTERED_PREFIX)

    @property
    def reason(self) -> str:
        """The filter reason of a filtered outcome ("no_actuator")."""
        return self.value.removeprefix(FILTERED_PREFIX)

    @property
    def is_trained(self) -> bool:
        """Experts were trained for the level (kept, unsolved or failed)."""
        return self in (Outcome.KEPT, Outcome.UNSOLVED, Outcome.FAILED)

    @property
    def has_window(self) -> bool:
        """An expert window was collected (kept or unsolved), so its episode lengths are recorded."""
        return self in (Outcome.KEPT, Outcome.UNSOLVED)


@dataclasses.dataclass(frozen=True)
class LevelRecord:
    """One slot of a level batch."""

    slot: int
    outcome: Outcome
    level_id: int
    level_seed: int
    expert_success_rate: float | None  # [-] None: no evaluation episode ended (a NaN)
    episode_lengths: tuple[int, ...]  # [env steps] of the completed episodes of the window
    expert_env_steps: int | None = None
    trained_env_steps: int | None = None  # [env steps] the level's training used (None: records made before budgets)
    curve_success_rate: tuple[float | None, ...] | None = None  # [-] per curve point (None: NaN)
    curve_mean_return: tuple[float | None, ...] | None = None

    @property
    def kept(self) -> bool:
        return self.outcome == Outcome.KEPT

    def to_json(self) -> dict:
        data = {
            "slot": self.slot,
            "kept": self.kept,
            "outcome": str(self.outcome),
            "level_id": self.level_id,
            "level_seed": self.level_seed,
            "expert_success_rate": self.expert_success_rate,
            "episode_lengths": list(self.episode_lengths),
        }
        if self.expert_env_steps is not None:
            data["expert_env_steps"] = self.expert_env_steps
        if self.trained_env_steps is not None:
            data["trained_env_steps"] = self.trained_env_steps
        if self.curve_success_rate is not None:
            data["learning_curve"] = {
                "success_rate": list(self.curve_success_rate),
                "mean_return": list(self.curve_mean_return or ()),
            }
        return data

    @classmethod
    def from_json(cls, data: Mapping, where: str) -> LevelRecord:
        try:
            outcome = Outcome(data["outcome"])
            if bool(data["kept"]) != (outcome == Outcome.KEPT):
                raise DatasetError(f"{where}: kept={data['kept']} but outcome {outcome}")
            curve = data.get("learning_curve")
            rate = data["expert_success_rate"]
            return cls(
                slot=int(data["slot"]),
                outcome=outcome,
                level_id=int(data["level_id"]),
                level_seed=int(data["level_seed"]),
                expert_success_rate=None if rate is None else float(rate),
                episode_lengths=tuple(int(length) for length in data["episode_lengths"]),
                expert_env_steps=_optional_int(data.get("expert_env_steps")),
                trained_env_steps=_optional_int(data.get("trained_env_steps")),
                curve_success_rate=None if curve is None else tuple(curve["success_rate"]),
                curve_mean_return=None if curve is None else tuple(curve["mean_return"]),
            )
        except KeyError as error:
            raise DatasetError(f"{where}: level record without {error}") from error
        except (TypeError, ValueError) as error:
            raise DatasetError(f"{where}: malformed level record ({error})") from error


@dataclasses.dataclass(frozen=True)
class ArrayEntry:
    """A stored array's shard object of a level batch: its key (None: nothing stored), digests and size."""

    file: str | None
    sha256: str | None  # of the object's bytes (None: no object)
    data_sha256: str  # of the decoded (levels_per_batch, ...) content
    size: int | None = None  # [bytes] of the object; None: no object, or a record written before sizes were recorded

    def to_json(self) -> dict:
        data = {"file": self.file, "sha256": self.sha256, "data_sha256": self.data_sha256}
        if self.size is not None:
            data["size"] = self.size
        return data

    @classmethod
    def from_json(cls, data: Mapping) -> ArrayEntry:
        size = data.get("size")
        return cls(data["file"], data["sha256"], data["data_sha256"], None if size is None else int(size))


@dataclasses.dataclass(frozen=True)
class BatchRecord:
    """The commit record of a level batch."""

    shard: int
    batch: int
    global_batch: int
    slots: tuple[int, int]  # [start, stop) global slots
    num_kept: int
    levels: tuple[LevelRecord, ...]
    arrays: Mapping[str, ArrayEntry]  # field name -> its shard object
    curve_env_steps: tuple[int, ...] | None = None  # x axis of the levels' learning curves
    budget_mode: str | None = None  # experts.budget_mode the batch was trained with (None: records made before it)
    provenance: Mapping | None = None  # wall times and worker: not part of the data

    def to_json(self) -> dict:
        data = {
            "shard": self.shard,
            "batch": self.batch,
            "global_batch": self.global_batch,
            "slots": list(self.slots),
            "num_kept": self.num_kept,
            "levels": [level.to_json() for level in self.levels],
            "arrays": {name: entry.to_json() for name, entry in self.arrays.items()},
        }
        if self.curve_env_steps is not None:
            data["curve_env_steps"] = list(self.curve_env_steps)
        if self.budget_mode is not None:
            data["budget_mode"] = self.budget_mode
        if self.provenance is not None:
            data[PROVENANCE] = dict(self.provenance)
        return data

    @classmethod
    def from_json(cls, data: Mapping, where: str) -> BatchRecord:
        try:
            steps = data.get("curve_env_steps")
            return cls(
                shard=int(data["shard"]),
                batch=int(data["batch"]),
                global_batch=int(data["global_batch"]),
                slots=(int(data["slots"][0]), int(data["slots"][1])),
                num_kept=int(data["num_kept"]),
                levels=tuple(
                    LevelRecord.from_json(level, f"{where} level {i}") for i, level in enumerate(data["levels"])
                ),
                arrays={name: ArrayEntry.from_json(entry) for name, entry in data["arrays"].items()},
                curve_env_steps=None if steps is None else tuple(int(step) for step in steps),
                budget_mode=None if data.get("budget_mode") is None else str(data["budget_mode"]),
                provenance=data.get(PROVENANCE),
            )
        except KeyError as error:
            raise DatasetError(f"{where}: record without {error}") from error
        except (TypeError, ValueError, IndexError, AttributeError) as error:
            raise DatasetError(f"{where}: malformed record ({error})") from error

    @property
    def kept_slots(self) -> list[int]:
        return [level.slot for level in self.levels if level.kept]

    @property
    def object_sizes(self) -> dict[str, int | None]:
        """Key -> recorded byte size (None where the record predates sizes) of each data object it commits."""
        return {entry.file: entry.size for entry in self.arrays.values() if entry.file is not None}


def _optional_int(value) -> int | None:
    return None if value is None else int(value)
