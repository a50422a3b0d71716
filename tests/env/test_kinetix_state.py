"""Kinetix `EnvState` leaves <-> our `EnvState`: sizes from Kinetix's format, values from Kinetix's own level files."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from kforge.env import StaticEnvParams, initial_state, load_level
from kforge.env.kinetix_state import KinetixStateError, kinetix_leaf_specs, state_from_kinetix, state_to_kinetix

REFERENCE_STATE_BYTES = {"s": 1456, "m": 2442, "l": 8022}
"""Bytes of one full Kinetix EnvState per size (measured with kinetix-env 3.0.2; docs/kinetix.md)."""

NUM_LEAVES = 82

BODY_FIELDS = (
    "position",
    "rotation",
    "velocity",
    "angular_velocity",
    "inverse_mass",
    "inverse_inertia",
    "friction",
    "restitution",
    "collision_mode",
    "active",
)
JOINT_FIELDS = (
    "a_index",
    "b_index",
    "a_relative_pos",
    "b_relative_pos",
    "active",
    "motor_speed",
    "motor_power",
    "motor_on",
    "motor_has_joint_limits",
    "min_rotation",
    "max_rotation",
    "is_fixed_joint",
    "rotation",
)
THRUSTER_FIELDS = ("object_index", "relative_position", "rotation", "power", "active")
"""Fields a Kinetix level file stores with the values a state holds (the file's values, cast to float32)."""

CACHE_TOLERANCE = 1e-4  # [m] global_position caches: the file's float32 cache vs ours from the pose in float64


def _value(raw):
    """A Kinetix JSON array (dict keyed "0", "1", ...) or scalar as a numpy value."""
    if isinstance(raw, dict):
        return np.asarray([_value(raw[str(i)]) for i in range(len(raw))])
    return np.asarray(raw)


def _level_files(levels_dir, size: str):
    return sorted((levels_dir / size).glob("*.json"))


def _stack(trees):
    return jax.tree.map(lambda *xs: jnp.stack(xs), *trees)


@pytest.mark.parametrize("size", ["s", "m", "l"])
def test_leaves_and_bytes_per_state_match_the_reference(size):
    specs = kinetix_leaf_specs(StaticEnvParams.for_size(size))
    assert len(specs) == NUM_LEAVES
    assert sum(int(np.prod(spec.shape)) * spec.dtype.itemsize for spec in specs.values()) == REFERENCE_STATE_BYTES[size]


def test_leaves_reproduce_the_level_file(fixture_file):
    raw = json.loads(fixture_file.read_text())["env_state"]
    loaded = load_level(fixture_file)
    leaves = state_to_kinetix(initial_state(loaded.level), loaded.static)
    for kind in ("polygon", "circle"):
        for slot, record in enumerate(raw[kind]):
            for field in BODY_FIELDS:
                expected = _value(record[field]).astype(leaves[f"{kind}/{field}"].dtype)
                np.testing.assert_array_equal(leaves[f"{kind}/{field}"][slot], expected, err_msg=f"{kind}[{slot}]")
            assert leaves[f"{kind}_shape_roles"][slot] == record["role"]
            assert leaves[f"{kind}_densities"][slot] == np.float32(record["density"])
        for slot, record in enumerate(raw["polygon"]):
            n = record["n_vertices"]
            file_vertices = _value(record["vertices"])[:n].astype(np.float32)  # clockwise, as Kinetix stores them
            np.testing.assert_array_equal(leaves["polygon/vertices"][slot, :n], file_vertices)
    np.testing.assert_array_equal(leaves["circle/radius"], [np.float32(c["radius"]) for c in raw["circle"]])
    for kind, fields, binding in (
        ("joint", JOINT_FIELDS, "motor_binding"),
        ("thruster", THRUSTER_FIELDS, "thruster_binding"),
    ):
        for slot, record in enumerate(raw[kind]):
            for field in fields:
                expected = _value(record[field]).astype(leaves[f"{kind}/{field}"].dtype)
                np.testing.assert_array_equal(leaves[f"{kind}/{field}"][slot], expected, err_msg=f"{kind}[{slot}]")
            assert leaves[f"{kind.replace('joint', 'motor')}_bindings"][slot] == record[binding]
            if record["active"]:
                np.testing.assert_allclose(
                    leaves[f"{kind}/global_position"][slot], _value(record["global_position"]), atol=CACHE_TOLERANCE
                )
    np.testing.assert_array_equal(leaves["collision_matrix"], _value(raw["collision_matrix"]))
    np.testing.assert_array_equal(leaves["gravity"], _value(raw["gravity"]).astype(np.float32))
    assert leaves["timestep"] == 0 and leaves["last_distance"] == -1.0
    assert not any(leaves[name].any() for name in leaves if name.startswith("acc_"))


@pytest.mark.parametrize("size", ["s", "m"])
def test_batched_round_trip_of_level_files_is_exact(size, levels_dir):
    loaded = [load_level(path) for path in _level_files(levels_dir, size)]
    static = loaded[0].static
    states = _stack([initial_state(entry.level) for entry in loaded])
    leaves = state_to_kinetix(states, static)
    back, back_static = state_from_kinetix(leaves)
    assert back_static == static
    for (path, got), want in zip(jax.tree_util.tree_flatten_with_path(back)[0], jax.tree.leaves(states), strict=True):
        np.testing.assert_array_equal(np.asarray(got), np.asarray(want), err_msg=jax.tree_util.keystr(path))
    for index, entry in enumerate(loaded):  # the batched mapping is the per-level one, row by row
        single = state_to_kinetix(initial_state(entry.level), static)
        for name, value in single.items():
            np.testing.assert_array_equal(leaves[name][index], value, err_msg=name)


def test_import_drops_warm_start_caches_only(levels_dir):
    loaded = load_level(_level_files(levels_dir, "m")[0])
    state = initial_state(loaded.level)
    sim = state.sim
    warm = state.replace(
        sim=sim.replace(
            contacts=sim.contacts.replace(
                normal_impulse=sim.contacts.normal_impulse + 1.5, feature=jnp.zeros_like(sim.contacts.feature)
            ),
            joints=sim.joints.replace(linear_impulse=sim.joints.linear_impulse + 0.5),
        ),
        timestep=jnp.asarray(17, jnp.int32),
        last_distance=jnp.asarray(2.25, jnp.float32),
    )
    back, _ = state_from_kinetix(state_to_kinetix(warm, loaded.static))
    expected = state.replace(timestep=warm.timestep, last_distance=warm.last_distance)
    for got, want in zip(jax.tree.leaves(back), jax.tree.leaves(expected), strict=True):
        np.testing.assert_array_equal(np.asarray(got), np.asarray(want))


def test_missing_or_misshapen_leaves_are_named(levels_dir):
    loaded = load_level(_level_files(levels_dir, "s")[0])
    leaves = state_to_kinetix(initial_state(loaded.level), loaded.static)
    with pytest.raises(KinetixStateError, match="leaf thruster/power is missing"):
        state_from_kinetix({name: value for name, value in leaves.items() if name != "thruster/power"})
    with pytest.raises(KinetixStateError, match=r"leaf joint/rotation: shape \(2,\), expected \(1,\)"):
        state_from_kinetix(leaves | {"joint/rotation": np.zeros(2, np.float32)})
    with pytest.raises(KinetixStateError, match="leaf gravity: dtype int32"):
        state_from_kinetix(leaves | {"gravity": np.zeros(2, np.int32)})
    with pytest.raises(KinetixStateError, match="3 polygon slots"):
        state_from_kinetix(leaves | {"polygon/active": np.zeros(3, bool)})
