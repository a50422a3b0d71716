"""`kforge export --format kinetix` and the import back: Kinetix-Offline layout, dtypes, values, shuffle, errors.

Expectations are written out from Kinetix's format (docs/kinetix.md: sizes, offline dataset format) and from the
conftest rollout in our own field names, not computed by the exporter's mapping.
"""

from __future__ import annotations

import json
import shutil

import jax
import numpy as np
import pytest
from pipeline_test_helpers import NUM_STEPS

import kforge.pipeline.kinetix.export as kinetix_export
from kforge.env import initial_state
from kforge.pipeline.cli import main as kforge
from kforge.pipeline.kinetix.export import export_kinetix
from kforge.pipeline.kinetix.importer import load_kinetix_levels
from kforge.pipeline.kinetix.zarr_v2 import RecordArray
from kforge.pipeline.storage.layout import DatasetError

P, C, J, T = 5, 2, 1, 1  # size s slots (docs/kinetix.md, sizes)
NRR, NCR, NCC = 4, 10, 1  # contact-pair slots of size s: P(P-1)/2 - 6, C P, C(C-1)/2
F4, I4, B1 = "<f4", "<i4", "|b1"
KEPT_LEVEL_IDS = [0, 1, 10, 11, 20, 21, 30, 31]  # level batch g keeps levels 10 g and 10 g + 1
PER_SHARD = 3  # 8 trajectories -> shards of 3, 3 and 2
SPLIT = "train"


def _body(n: int) -> dict:
    vec, one = (n, 2), (n,)
    return {
        "position": (F4, vec),
        "rotation": (F4, one),
        "velocity": (F4, vec),
        "angular_velocity": (F4, one),
        "inverse_mass": (F4, one),
        "inverse_inertia": (F4, one),
        "friction": (F4, one),
        "restitution": (F4, one),
        "collision_mode": (I4, one),
        "active": (B1, one),
        "n_vertices": (I4, one),
        "vertices": (F4, (n, 4, 2)),
        "radius": (F4, one),
    }


def _manifold(pairs: tuple[int, ...]) -> dict:
    return {
        "normal": (F4, pairs + (2,)),
        "penetration": (F4, pairs),
        "collision_point": (F4, pairs + (2,)),
        "active": (B1, pairs),
        "acc_impulse_normal": (F4, pairs),
        "acc_impulse_tangent": (F4, pairs),
        "restitution_velocity_target": (F4, pairs),
    }


EXPECTED_STATE = {
    **{f"polygon/{k}": v for k, v in _body(P).items()},
    **{f"circle/{k}": v for k, v in _body(C).items()},
    **{
        f"joint/{k}": (kind, (J,) + shape)
        for k, (kind, shape) in {
            "a_index": (I4, ()),
            "b_index": (I4, ()),
            "a_relative_pos": (F4, (2,)),
            "b_relative_pos": (F4, (2,)),
            "global_position": (F4, (2,)),
            "active": (B1, ()),
            "acc_impulse": (F4, (2,)),
            "acc_r_impulse": (F4, ()),
            "motor_speed": (F4, ()),
            "motor_power": (F4, ()),
            "motor_on": (B1, ()),
            "motor_has_joint_limits": (B1, ()),
            "min_rotation": (F4, ()),
            "max_rotation": (F4, ()),
            "is_fixed_joint": (B1, ()),
            "rotation": (F4, ()),
        }.items()
    },
    "thruster/object_index": (I4, (T,)),
    "thruster/relative_position": (F4, (T, 2)),
    "thruster/rotation": (F4, (T,)),
    "thruster/power": (F4, (T,)),
    "thruster/global_position": (F4, (T, 2)),
    "thruster/active": (B1, (T,)),
    "collision_matrix": (B1, (P + C, P + C)),
    **{f"acc_rr_manifolds/{k}": v for k, v in _manifold((NRR, 2)).items()},
    **{f"acc_cr_manifolds/{k}": v for k, v in _manifold((NCR,)).items()},
    **{f"acc_cc_manifolds/{k}": v for k, v in _manifold((NCC,)).items()},
    "gravity": (F4, (2,)),
    "thruster_bindings": (I4, (T,)),
    "motor_bindings": (I4, (J,)),
    "motor_auto": (B1, (J,)),
    "polygon_shape_roles": (I4, (P,)),
    "circle_shape_roles": (I4, (C,)),
    "polygon_highlighted": (B1, (P,)),
    "circle_highlighted": (B1, (C,)),
    "polygon_densities": (F4, (P,)),
    "circle_densities": (F4, (C,)),
    "timestep": (I4, ()),
    "last_distance": (F4, ()),
}
"""Kinetix's 82 EnvState leaves at size s: name -> (dtype, shape) (docs/kinetix.md, offline dataset format)."""

EXPECTED_RECORD = {"action": (I4, (6,)), "action_mask": (B1, (6,)), "done": (B1, ())} | {
    f"env_state/{name}": spec for name, spec in EXPECTED_STATE.items()
}
RECORD_BYTES_S = 1487  # record itemsize for size s, 85 fields (docs/kinetix.md)


@pytest.fixture(scope="module")
def exported(dataset_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("kinetix")
    summary = export_kinetix(dataset_dir, out, seed=0, trajectories_per_shard=PER_SHARD, show_progress=False)
    return summary


def shard_rows(group):
    """(shard name, records (N, T, 1), level ids) of every shard, in name order."""
    names = sorted(p.name for p in group.iterdir() if (p / ".zarray").is_file())
    arrays = [RecordArray.open(group / name) for name in names]
    return [(name, a.read(), a.attributes["kforge_export"]["level_id"]) for name, a in zip(names, arrays, strict=True)]


def test_layout_is_one_zarr_v2_group_of_record_shards(exported):
    group = exported.group
    assert group.name == SPLIT
    assert json.loads((group / ".zgroup").read_text()) == {"zarr_format": 2}
    assert exported.shard_sizes == {"shard-000000": 3, "shard-000001": 3, "shard-000002": 2}
    assert exported.num_trajectories == len(KEPT_LEVEL_IDS) and exported.record_bytes == RECORD_BYTES_S
    for name, size in exported.shard_sizes.items():
        meta = json.loads((group / name / ".zarray").read_text())
        assert meta["zarr_format"] == 2 and meta["shape"] == [size, NUM_STEPS, 1]
        assert meta["chunks"][1:] == [NUM_STEPS, 1] and meta["compressor"]["id"] == "zstd"
    attributes = json.loads((group / ".zattrs").read_text())["kforge_export"]
    assert attributes["split"] == SPLIT and attributes["seed"] == 0 and attributes["num_trajectories"] == 8
    assert not [p.name for p in group.parent.iterdir() if p.name != SPLIT]  # no staging folder left


def test_record_fields_dtypes_and_shapes_are_kinetix_s(exported):
    array = RecordArray.open(exported.group / "shard-000000")
    fields = {
        name: (array.dtype.fields[name][0].base.str, array.dtype.fields[name][0].shape) for name in array.dtype.names
    }
    assert fields == EXPECTED_RECORD
    assert len(fields) == 85 and array.dtype.itemsize == RECORD_BYTES_S


def _rotate(angle, vector):
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([c * vector[..., 0] - s * vector[..., 1], s * vector[..., 0] + c * vector[..., 1]], -1)


def _expected_leaves(states, level: int) -> dict[str, np.ndarray]:
    """Kinetix leaves of rollout trajectory `level` (T, ...), written out from our field names."""
    s = jax.tree.map(lambda x: np.asarray(x[level]), states)
    b, j, t, task = s.sim.bodies, s.sim.joints, s.sim.thrusters, s.task
    expected = {}
    for name in ("position", "rotation", "velocity", "angular_velocity", "inverse_mass", "inverse_inertia"):
        expected[f"polygon/{name}"], expected[f"circle/{name}"] = getattr(b, name)[:, :P], getattr(b, name)[:, P:]
    for name in ("friction", "restitution", "collision_mode", "active"):
        expected[f"polygon/{name}"], expected[f"circle/{name}"] = getattr(b, name)[:, :P], getattr(b, name)[:, P:]
    clockwise = b.vertices[:, :P].copy()
    for slot in range(P):
        n = int(b.n_vertices[0, slot])
        clockwise[:, slot, :n] = b.vertices[:, slot, :n][:, ::-1]
    expected |= {
        "polygon/n_vertices": b.n_vertices[:, :P],
        "polygon/vertices": clockwise,
        "polygon/radius": np.zeros((NUM_STEPS, P)),
        "circle/n_vertices": np.zeros((NUM_STEPS, C)),
        "circle/vertices": np.zeros((NUM_STEPS, C, 4, 2)),
        "circle/radius": b.radius[:, P:],
        "joint/a_index": j.body_a,
        "joint/b_index": j.body_b,
        "joint/a_relative_pos": j.anchor_a,
        "joint/b_relative_pos": j.anchor_b,
        "joint/active": j.active,
        "joint/motor_speed": j.motor_speed,
        "joint/motor_power": j.motor_power,
        "joint/motor_on": j.motor_on,
        "joint/motor_has_joint_limits": j.has_limits,
        "joint/min_rotation": j.lower_angle,
        "joint/max_rotation": j.upper_angle,
        "joint/is_fixed_joint": j.is_fixed,
        "joint/rotation": j.reference_angle,
        "joint/acc_impulse": np.zeros((NUM_STEPS, J, 2)),
        "joint/acc_r_impulse": np.zeros((NUM_STEPS, J)),
        "thruster/object_index": t.body,
        "thruster/relative_position": t.anchor,
        "thruster/rotation": t.angle,
        "thruster/power": t.power,
        "thruster/active": t.active,
        "collision_matrix": s.sim.collision_matrix,
        "gravity": s.sim.gravity,
        "thruster_bindings": task.thruster_bindings,
        "motor_bindings": task.motor_bindings,
        "motor_auto": task.motor_auto,
        "polygon_shape_roles": task.roles[:, :P],
        "circle_shape_roles": task.roles[:, P:],
        "polygon_highlighted": np.zeros((NUM_STEPS, P)),
        "circle_highlighted": np.zeros((NUM_STEPS, C)),
        "polygon_densities": task.densities[:, :P],
        "circle_densities": task.densities[:, P:],
        "timestep": s.timestep,
        "last_distance": s.last_distance,
    }
    for name in EXPECTED_STATE:
        if name.startswith("acc_"):
            expected[name] = np.zeros((NUM_STEPS, *EXPECTED_STATE[name][1]))
    return expected


def test_values_equal_the_rollout(exported, rolled_out):
    states, action, done, _ = rolled_out
    seen = []
    for _, records, level_ids in shard_rows(exported.group):
        for row, level_id in enumerate(level_ids):
            seen.append(level_id)
            level = level_id % 10  # slot 3 g + i of the dataset holds rollout level i
            record = records[row, :, 0]
            np.testing.assert_array_equal(record["action"], action[level])
            np.testing.assert_array_equal(record["done"], done[level])
            # the levels' only motor and thruster are bound to slots 0 and 4
            np.testing.assert_array_equal(record["action_mask"], np.tile([1, 0, 0, 0, 1, 0], (NUM_STEPS, 1)))
            expected = _expected_leaves(states, level)
            caches = {"joint/global_position", "thruster/global_position"}  # checked below, at a tolerance
            assert set(expected) == set(EXPECTED_STATE) - caches
            for name, value in expected.items():
                np.testing.assert_array_equal(record[f"env_state/{name}"], value, err_msg=name)
            bodies = jax.tree.map(lambda x, i=level: np.asarray(x[i]), states.sim.bodies)
            for kind, index, anchor in (
                ("joint", "a_index", "a_relative_pos"),
                ("thruster", "object_index", "relative_position"),
            ):
                body = record[f"env_state/{kind}/{index}"]
                world = np.take_along_axis(bodies.position, body[..., None], 1) + _rotate(
                    np.take_along_axis(bodies.rotation, body, 1), record[f"env_state/{kind}/{anchor}"]
                )
                np.testing.assert_allclose(record[f"env_state/{kind}/global_position"], world, atol=1e-5)
    assert sorted(seen) == KEPT_LEVEL_IDS


def test_polygons_are_clockwise_as_in_kinetix(exported):
    records = shard_rows(exported.group)[0][1][:, :, 0]
    vertices = records["env_state/polygon/vertices"]
    following = np.roll(vertices, -1, axis=-2)
    doubled_area = np.sum(vertices[..., 0] * following[..., 1] - vertices[..., 1] * following[..., 0], axis=-1)
    active = records["env_state/polygon/active"] & (records["env_state/polygon/n_vertices"] == 4)
    assert active.any() and np.all(doubled_area[active] < 0)


def test_shuffle_is_seeded_and_spreads_levels_over_shards(exported, dataset_dir, tmp_path, monkeypatch):
    order = [level_id for _, _, ids in shard_rows(exported.group) for level_id in ids]
    assert sorted(order) == KEPT_LEVEL_IDS and order != KEPT_LEVEL_IDS
    again = export_kinetix(
        dataset_dir, tmp_path / "again", seed=0, trajectories_per_shard=PER_SHARD, show_progress=False
    )
    for path in exported.group.rglob("*"):
        if path.is_file():
            assert path.read_bytes() == (again.group / path.relative_to(exported.group)).read_bytes(), path
    monkeypatch.setattr(kinetix_export, "TRAJECTORIES_PER_CHUNK", 2)
    other = export_kinetix(
        dataset_dir, tmp_path / "other", seed=1, trajectories_per_shard=PER_SHARD, show_progress=False
    )
    other_rows = shard_rows(other.group)
    other_order = [level_id for _, _, ids in other_rows for level_id in ids]
    assert sorted(other_order) == KEPT_LEVEL_IDS and other_order != order
    assert len(list((other.group / "shard-000000").glob("*.0.0"))) == 2  # 3 rows in chunks of 2
    by_id = {
        level_id: records[row] for _, records, ids in shard_rows(exported.group) for row, level_id in enumerate(ids)
    }
    for _, records, ids in other_rows:
        for row, level_id in enumerate(ids):
            assert records[row].tobytes() == by_id[level_id].tobytes()


def _assert_trees_equal(got, want):
    for (path, a), b in zip(jax.tree_util.tree_flatten_with_path(got)[0], jax.tree.leaves(want), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=jax.tree_util.keystr(path))


def test_import_gives_back_each_levels_start_state(exported, levels):
    imported = load_kinetix_levels(exported.group)
    assert imported.static.sim.num_polygons == P and imported.static.sim.num_circles == C
    got_levels, got_states = jax.tree.map(np.asarray, (imported.levels, imported.initial_states))
    order = [level_id for _, _, ids in shard_rows(exported.group) for level_id in ids]
    for row, level_id in enumerate(order):
        level = jax.tree.map(lambda x, i=level_id % 10: np.asarray(x[i]), levels)
        _assert_trees_equal(jax.tree.map(lambda x, r=row: x[r], got_levels), level)
        _assert_trees_equal(jax.tree.map(lambda x, r=row: x[r], got_states), initial_state(level))
    one_shard = load_kinetix_levels(exported.group / "shard-000002")
    np.testing.assert_array_equal(
        one_shard.initial_states.sim.bodies.position, imported.initial_states.sim.bodies.position[6:]
    )


def test_missing_or_corrupt_dataset_is_named(dataset_dir, tmp_path):
    with pytest.raises(DatasetError, match="not a dataset"):
        export_kinetix(tmp_path / "nothing", tmp_path / "out", show_progress=False)
    copy = tmp_path / "copy"
    shutil.copytree(dataset_dir, copy)
    record = next((copy / "manifest").rglob("batch-*.json"))
    record.write_text("{ not json")
    with pytest.raises(DatasetError, match="unreadable record"):
        export_kinetix(copy, tmp_path / "out", show_progress=False)
    assert not (tmp_path / "out").exists()


def test_a_corrupt_chunk_fails_without_leaving_a_partial_export(dataset_dir, tmp_path):
    copy = tmp_path / "copy"
    shutil.copytree(dataset_dir, copy)
    chunk = next(
        p for p in (copy / "data" / "env_state" / "sim" / "bodies" / "position" / "c").rglob("*") if p.is_file()
    )
    data = bytearray(chunk.read_bytes())
    data[100] ^= 0xFF
    chunk.write_bytes(bytes(data))
    with pytest.raises(DatasetError, match="bodies/position.* sha256 mismatch"):
        export_kinetix(copy, tmp_path / "out", show_progress=False)
    assert not (tmp_path / "out").exists()  # refused before anything is written


def test_existing_non_empty_output_is_refused(exported, dataset_dir):
    before = sorted(p.name for p in exported.group.iterdir())
    with pytest.raises(DatasetError, match="already exists and is not empty"):
        export_kinetix(dataset_dir, exported.group.parent, show_progress=False)
    assert sorted(p.name for p in exported.group.iterdir()) == before


def test_cli_exports_with_progress_and_reports_errors(dataset_dir, tmp_path, capsys):
    (tmp_path / "out" / SPLIT).mkdir(parents=True)  # an empty split folder may be reused
    kforge(["export", "--format", "kinetix", str(dataset_dir), str(tmp_path / "out")])
    captured = capsys.readouterr()
    assert f"wrote 8 trajectories in 1 shard to {tmp_path / 'out' / SPLIT}" in captured.out and "8/8" in captured.err
    assert "pip install kinetix-env==3.0.2" in captured.out and "load_kinetix_levels" in captured.out
    kforge(["export", "--format", "kinetix", str(dataset_dir), str(tmp_path / "json"), "--json", "--no-progress"])
    assert json.loads(capsys.readouterr().out)["trajectories"] == 8
    assert load_kinetix_levels(tmp_path / "out" / SPLIT).static.sim.num_polygons == P
    with pytest.raises(SystemExit) as exit_info:
        kforge(["export", "--format", "kinetix", str(dataset_dir), str(tmp_path / "out"), "--no-progress"])
    assert exit_info.value.code == 2
    assert "not empty" in capsys.readouterr().err


def test_import_names_a_missing_state_field(exported, tmp_path):
    shard = RecordArray.open(exported.group / "shard-000002")
    records = shard.read()
    kept = [name for name in records.dtype.names if name != "env_state/joint/rotation"]
    trimmed = np.empty(records.shape, np.dtype([(name, records.dtype.fields[name][0]) for name in kept]))
    for name in kept:
        trimmed[name] = records[name]
    target = RecordArray.create(tmp_path / "shard", records.shape, 16, trimmed.dtype, shard.compressor)
    target.write_chunk(0, trimmed)
    with pytest.raises(DatasetError, match="joint/rotation is missing"):
        load_kinetix_levels(tmp_path / "shard")
    with pytest.raises(DatasetError, match="neither a Kinetix-Offline split"):
        load_kinetix_levels(tmp_path)
