"""What a stored trajectory holds: one named field per `EnvState` leaf (per step or once per trajectory) plus actions.

The field list is derived from the `EnvState` pytree of a `StaticEnvParams` size, so it follows the state's
definition; only the set of leaves that evolve within an episode (`DYNAMIC_STATE_FIELDS`) is declared here. Every
other leaf is static per level and stored once per trajectory; the writer checks that it really is constant.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Mapping

import jax
import numpy as np

from kforge.engine import Batching, StaticSimParams, empty_state
from kforge.env import (
    NUM_ACTION_SLOTS,
    ActionType,
    EnvState,
    Level,
    StaticEnvParams,
    empty_task,
    initial_state,
    noop_action,
)

STATE_PREFIX = "env_state"
"""Stored name prefix of the state leaves: `env_state/sim/bodies/position` (Kinetix's convention)."""

DYNAMIC_STATE_FIELDS = (
    "sim/bodies/position",
    "sim/bodies/rotation",
    "sim/bodies/velocity",
    "sim/bodies/angular_velocity",
    "sim/joints/linear_impulse",
    "sim/joints/angular_impulse",
    "sim/joints/motor_impulse",
    "sim/joints/limit_impulse",
    "sim/contacts/normal_impulse",
    "sim/contacts/tangent_impulse",
    "sim/contacts/feature",
    "timestep",
    "last_distance",
)
"""`EnvState` leaves that change within an episode (stored per step); all other leaves are per level."""

ACTION = "action"
ACTION_MASK = "action_mask"
DONE = "done"
SUCCESS = "success"
VALID = "meta/valid"
LEVEL_ID = "meta/level_id"
LEVEL_SEED = "meta/level_seed"
EXPERT_SUCCESS_RATE = "meta/expert_success_rate"
NUM_EPISODES = "meta/num_episodes"
EPISODE_LENGTHS = "meta/episode_lengths"

SOLVER_CACHE_PREFIXES = (f"{STATE_PREFIX}/sim/contacts/", f"{STATE_PREFIX}/sim/joints/")
"""Name prefixes of the state leaves whose per-step fields are solver caches (`FieldSpec.is_solver_cache`)."""

INT_FILL = -1
"""Fill value of integer arrays: an unwritten slot reads as -1 (never a valid level id, seed or length)."""


class DatasetError(ValueError):
    """A dataset on disk is missing, corrupt, or does not match what the code or the caller expects."""


@dataclasses.dataclass(frozen=True)
class FieldSpec:
    """One stored array: per-trajectory shape (after the trajectory axis, and the time axis when `per_step`)."""

    name: str
    shape: tuple[int, ...]
    dtype: str
    per_step: bool

    def full_shape(self, num_steps: int) -> tuple[int, ...]:
        """Shape of one trajectory's value: (num_steps, *shape) per step, else `shape`."""
        return ((num_steps,) if self.per_step else ()) + self.shape

    @property
    def fill_value(self):
        """Value an unwritten slot reads as: NaN for floats, INT_FILL for integers, False for bools."""
        kind = np.dtype(self.dtype).kind
        if kind == "f":
            return float("nan")
        if kind in "iu":
            return INT_FILL
        return False

    @property
    def is_solver_cache(self) -> bool:
        """A per-step field of the solver's warm-start caches (accumulated contact and joint impulses, contact
        feature ids): no observation reads it, but a bit-exact restart of the simulation needs it."""
        return self.per_step and self.name.startswith(SOLVER_CACHE_PREFIXES)

    def to_json(self) -> dict:
        return {"name": self.name, "shape": list(self.shape), "dtype": self.dtype, "per_step": self.per_step}

    @classmethod
    def from_json(cls, data: Mapping) -> FieldSpec:
        return cls(str(data["name"]), tuple(int(n) for n in data["shape"]), str(data["dtype"]), bool(data["per_step"]))


@dataclasses.dataclass(frozen=True)
class Layout:
    """Every stored field of a dataset, with the sizes it was derived from; hashable and JSON round-trippable."""

    static: StaticEnvParams
    action_type: ActionType
    num_steps: int
    fields: tuple[FieldSpec, ...]

    def field(self, name: str) -> FieldSpec:
        for spec in self.fields:
            if spec.name == name:
                return spec
        raise KeyError(f"no stored field named {name!r}")

    @property
    def state_fields(self) -> tuple[FieldSpec, ...]:
        return tuple(spec for spec in self.fields if spec.name.startswith(STATE_PREFIX + "/"))

    def to_json(self) -> dict:
        return {
            "static_env_params": static_to_json(self.static),
            "action_type": self.action_type.value,
            "num_steps": self.num_steps,
            "fields": [spec.to_json() for spec in self.fields],
        }

    @classmethod
    def from_json(cls, data: Mapping) -> Layout:
        return cls(
            static=static_from_json(data["static_env_params"]),
            action_type=ActionType(data["action_type"]),
            num_steps=int(data["num_steps"]),
            fields=tuple(FieldSpec.from_json(spec) for spec in data["fields"]),
        )


def static_to_json(static: StaticEnvParams) -> dict:
    return dataclasses.asdict(static)


def static_from_json(data: Mapping) -> StaticEnvParams:
    fields = dict(data)
    sim = dict(fields.pop("sim"))
    if "batching" in sim:  # a nested dataclass in the JSON (`static_to_json`)
        sim["batching"] = Batching(**sim["batching"])
    return StaticEnvParams(sim=StaticSimParams(**sim), **fields)


def _state_template(static: StaticEnvParams) -> EnvState:
    sim = static.sim
    level = Level(sim=empty_state(sim), task=empty_task(sim.num_bodies, sim.num_joints, sim.num_thrusters))
    return jax.eval_shape(initial_state, level)


def _path_name(path) -> str:
    parts = []
    for key in path:
        if not isinstance(key, jax.tree_util.GetAttrKey):
            raise TypeError(f"EnvState leaf path {path!r} is not made of dataclass attributes")
        parts.append(key.name)
    return "/".join(parts)


def state_leaf_names(static: StaticEnvParams) -> tuple[str, ...]:
    """Flattened `EnvState` leaf names in pytree order, e.g. 'sim/bodies/position' (without the prefix)."""
    leaves, _ = jax.tree_util.tree_flatten_with_path(_state_template(static))
    return tuple(_path_name(path) for path, _ in leaves)


def make_layout(static: StaticEnvParams, action_type: ActionType, num_steps: int | None = None) -> Layout:
    """The stored fields of trajectories of `num_steps` steps (default: the episode length) at `static`'s size."""
    num_steps = static.max_timesteps if num_steps is None else num_steps
    if num_steps < 1:
        raise ValueError(f"num_steps must be >= 1, got {num_steps}")
    leaves, _ = jax.tree_util.tree_flatten_with_path(_state_template(static))
    names = [_path_name(path) for path, _ in leaves]
    unknown = sorted(set(DYNAMIC_STATE_FIELDS) - set(names))
    if unknown:
        raise DatasetError(f"DYNAMIC_STATE_FIELDS names leaves that EnvState does not have: {unknown}")
    state_fields = tuple(
        FieldSpec(f"{STATE_PREFIX}/{name}", tuple(leaf.shape), str(leaf.dtype), name in DYNAMIC_STATE_FIELDS)
        for name, (_, leaf) in zip(names, leaves, strict=True)
    )
    action = noop_action(action_type)
    fields = (
        FieldSpec(ACTION, tuple(action.shape), str(action.dtype), True),
        FieldSpec(ACTION_MASK, (NUM_ACTION_SLOTS,), "bool", False),
        FieldSpec(DONE, (), "bool", True),
        FieldSpec(SUCCESS, (), "bool", True),
        *state_fields,
        FieldSpec(VALID, (), "bool", False),
        FieldSpec(LEVEL_ID, (), "int64", False),
        FieldSpec(LEVEL_SEED, (), "int64", False),
        FieldSpec(EXPERT_SUCCESS_RATE, (), "float32", False),
        FieldSpec(NUM_EPISODES, (), "int32", False),
        FieldSpec(EPISODE_LENGTHS, (num_steps,), "int32", False),
    )
    return Layout(static=static, action_type=action_type, num_steps=num_steps, fields=fields)


def check_layout(stored: Layout, where: str) -> None:
    """Raise `DatasetError` naming each difference between a stored layout and the one this code derives."""
    expected = make_layout(stored.static, stored.action_type, stored.num_steps)
    if stored == expected:
        return
    have = {spec.name: spec for spec in stored.fields}
    want = {spec.name: spec for spec in expected.fields}
    problems = [
        f"field {name} is stored but this code's EnvState has no such leaf"
        for name in sorted(have.keys() - want.keys())
    ]
    problems += [f"field {name} is missing from the stored layout" for name in sorted(want.keys() - have.keys())]
    problems += [
        f"field {name} stored as {have[name]} but this code expects {want[name]}"
        for name in sorted(have.keys() & want.keys())
        if have[name] != want[name]
    ]
    if not problems:
        problems = ["field order differs from this code's EnvState"]
    raise DatasetError(f"{where}: stored layout does not match this code: " + "; ".join(problems))


def flatten_state(state: EnvState) -> dict[str, np.ndarray]:
    """Stored name -> host array of every `EnvState` leaf (any leading batch/time axes kept)."""
    leaves, _ = jax.tree_util.tree_flatten_with_path(state)
    return {f"{STATE_PREFIX}/{_path_name(path)}": np.asarray(leaf) for path, leaf in leaves}


def unflatten_state(layout: Layout, arrays: Mapping[str, object]) -> EnvState:
    """The `EnvState` whose leaves are `arrays[stored name]` (inverse of `flatten_state`)."""
    leaves = [arrays[spec.name] for spec in layout.state_fields]
    return jax.tree_util.tree_unflatten(_state_treedef(layout.static), leaves)


@functools.cache
def _state_treedef(static: StaticEnvParams):
    return jax.tree_util.tree_structure(_state_template(static))
