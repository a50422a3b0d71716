"""The stored field list derived from the EnvState pytree: names, shapes, per-step split, layout checks."""

from __future__ import annotations

import pytest

from kforge.env import ActionType, StaticEnvParams
from kforge.pipeline.storage.layout import (
    DYNAMIC_STATE_FIELDS,
    DatasetError,
    FieldSpec,
    Layout,
    check_layout,
    make_layout,
)

pytestmark = pytest.mark.smoke

SIZE_S = StaticEnvParams.for_size("s")  # 5 polygons + 2 circles = 7 bodies, 1 joint, 1 thruster


def test_state_fields_cover_every_leaf_with_hand_checked_shapes():
    layout = make_layout(SIZE_S, ActionType.MULTI_DISCRETE)
    fields = {spec.name: spec for spec in layout.state_fields}
    # 13 body + 17 joint + 5 thruster + 3 contact leaves, collision matrix, gravity, 5 task leaves, 2 counters
    assert len(fields) == 13 + 17 + 5 + 3 + 2 + 5 + 2
    assert fields["env_state/sim/bodies/position"] == FieldSpec(
        "env_state/sim/bodies/position", (7, 2), "float32", True
    )
    assert fields["env_state/sim/bodies/vertices"] == FieldSpec(
        "env_state/sim/bodies/vertices", (7, 4, 2), "float32", False
    )
    assert fields["env_state/sim/collision_matrix"].shape == (7, 7)
    assert fields["env_state/timestep"] == FieldSpec("env_state/timestep", (), "int32", True)
    assert layout.field("action") == FieldSpec("action", (6,), "int32", True)
    assert layout.field("action_mask") == FieldSpec("action_mask", (6,), "bool", False)


def test_exactly_the_declared_dynamic_leaves_are_per_step():
    layout = make_layout(SIZE_S, ActionType.MULTI_DISCRETE)
    per_step = {spec.name.removeprefix("env_state/") for spec in layout.state_fields if spec.per_step}
    assert per_step == set(DYNAMIC_STATE_FIELDS)
    assert not layout.field("env_state/task/roles").per_step
    assert not layout.field("env_state/sim/joints/motor_speed").per_step


def test_solver_caches_are_the_per_step_impulses_and_contact_features():
    layout = make_layout(SIZE_S, ActionType.MULTI_DISCRETE)
    caches = {spec.name.removeprefix("env_state/sim/") for spec in layout.fields if spec.is_solver_cache}
    assert caches == {
        "contacts/normal_impulse",
        "contacts/tangent_impulse",
        "contacts/feature",
        "joints/linear_impulse",
        "joints/angular_impulse",
        "joints/motor_impulse",
        "joints/limit_impulse",
    }
    assert not layout.field("env_state/sim/joints/anchor_a").is_solver_cache  # per-level joint geometry


def test_contact_cache_size_follows_the_static_size():
    # size m: 6 polygons + 3 circles; K candidate pairs grows, so the per-step contact fields do too
    small = make_layout(SIZE_S, ActionType.MULTI_DISCRETE).field("env_state/sim/contacts/feature").shape
    medium = make_layout(StaticEnvParams.for_size("m"), ActionType.MULTI_DISCRETE).field(
        "env_state/sim/contacts/feature"
    )
    assert medium.shape[1] == small[1] == 2 and medium.shape[0] > small[0]


def test_layout_json_round_trip_and_fill_values():
    layout = make_layout(SIZE_S, ActionType.CONTINUOUS, num_steps=16)
    assert Layout.from_json(layout.to_json()) == layout
    assert layout.field("action").dtype == "float32"
    assert layout.field("meta/episode_lengths").shape == (16,)
    assert layout.field("meta/level_seed").fill_value == -1
    assert layout.field("done").fill_value is False


def test_check_layout_names_the_unknown_and_missing_fields():
    layout = make_layout(SIZE_S, ActionType.MULTI_DISCRETE)
    data = layout.to_json()
    renamed = [dict(spec) for spec in data["fields"]]
    for spec in renamed:
        if spec["name"] == "env_state/sim/bodies/radius":
            spec["name"] = "env_state/sim/bodies/old_radius"
    stored = Layout.from_json(data | {"fields": renamed})
    with pytest.raises(DatasetError, match="old_radius is stored.*bodies/radius is missing"):
        check_layout(stored, "somewhere")
    check_layout(layout, "somewhere")  # its own layout passes
