"""Kinetix level files: every fixture loads with its size and content, geometry lands where the JSON says, saving
reproduces the files, round trips are exact (s, m and l), and malformed files fail naming the field."""

from __future__ import annotations

import copy
import json
import math

import jax
import numpy as np
import pytest

from kforge.engine import SceneBuilder, StaticSimParams
from kforge.engine.geometry import polygon_mass_properties, rotate_host
from kforge.env import EnvParams, Level, Role, StaticEnvParams, bundled_level_path, list_levels
from kforge.env.level_files import LevelFileError, level_to_dict, load_level, save_level
from kforge.env.state import Task

# Kinetix's values of the env_params our engine does not model (Kinetix `EnvParams` defaults).
KINETIX_DEFAULT_ENV_PARAMS = {
    "slop": 0.01,
    "baumgarte_coefficient_joints_v": 2.0,
    "baumgarte_coefficient_joints_p": 0.7,
    "baumgarte_coefficient_fjoint_av": 2.0,
    "baumgarte_coefficient_rjoint_limit_av": 5.0,
    "baumgarte_coefficient_collision": 0.2,
    "joint_stiffness": 0.6,
    "motor_decay_coefficient": 0.1,
    "motor_joint_limit": 0.1,
    "pixels_per_unit": 100,
    "num_shape_roles": 4,
    "max_timesteps": 256,
}
FLOAT_TOLERANCE = 1e-6


def _vector(entry) -> list[float]:
    return [entry[str(i)] for i in range(len(entry))]


def _shapes(raw) -> list[dict]:
    """Polygon records then circle records: the global shape order."""
    return raw["env_state"]["polygon"] + raw["env_state"]["circle"]


def _assert_levels_equal(a: Level, b: Level):
    paths_a, leaves_a = zip(*jax.tree_util.tree_leaves_with_path(a), strict=True)
    leaves_b = jax.tree.leaves(b)
    assert len(leaves_a) == len(leaves_b)
    for path, x, y in zip(paths_a, leaves_a, leaves_b, strict=True):
        x, y = np.asarray(x), np.asarray(y)
        assert x.dtype == y.dtype and x.shape == y.shape, jax.tree_util.keystr(path)
        np.testing.assert_array_equal(x, y, err_msg=jax.tree_util.keystr(path))


# ------------------------------------------------------------------------------------------ fixtures load


def test_fixture_loads_with_its_size_and_content(fixture_file):
    raw = json.loads(fixture_file.read_text())
    loaded = load_level(fixture_file)
    size = fixture_file.parent.name
    assert loaded.static == StaticEnvParams.for_size(size)

    shapes = _shapes(raw)
    level = loaded.level
    np.testing.assert_array_equal(level.task.roles, [shape["role"] for shape in shapes])
    np.testing.assert_array_equal(level.sim.bodies.active, [shape["active"] for shape in shapes])
    for role in (Role.GREEN, Role.BLUE, Role.RED):
        expected = sum(shape["active"] and shape["role"] == role for shape in shapes)
        assert int(np.sum(np.asarray(level.sim.bodies.active) & (np.asarray(level.task.roles) == role))) == expected

    joints, thrusters = raw["env_state"]["joint"], raw["env_state"]["thruster"]
    np.testing.assert_array_equal(level.sim.joints.active, [j["active"] for j in joints])
    np.testing.assert_array_equal(level.sim.joints.body_a, [j["a_index"] for j in joints])
    np.testing.assert_array_equal(level.sim.joints.body_b, [j["b_index"] for j in joints])
    np.testing.assert_array_equal(level.sim.joints.is_fixed, [j["is_fixed_joint"] for j in joints])
    np.testing.assert_array_equal(level.task.motor_bindings, [j["motor_binding"] for j in joints])
    np.testing.assert_array_equal(level.sim.thrusters.active, [t["active"] for t in thrusters])
    np.testing.assert_array_equal(level.sim.thrusters.body, [t["object_index"] for t in thrusters])
    np.testing.assert_array_equal(level.task.thruster_bindings, [t["thruster_binding"] for t in thrusters])
    assert not np.any(level.task.motor_auto)

    assert loaded.params.dense_reward_scale == raw["env_params"]["dense_reward_scale"]
    assert loaded.params.sim.dt == raw["env_params"]["dt"]
    assert loaded.params.sim.base_motor_speed == raw["env_params"]["base_motor_speed"]
    np.testing.assert_array_equal(level.sim.gravity, np.float32(_vector(raw["env_state"]["gravity"])))
    # Kinetix's loader starts from empty contact caches.
    assert np.all(np.asarray(level.sim.contacts.feature) == -1)
    assert not np.any(level.sim.contacts.normal_impulse)


def test_fixture_collision_matrix_equals_the_stored_one(fixture_file):
    """Recomputed from the joints, it matches what Kinetix stored in every fixture."""
    raw = json.loads(fixture_file.read_text())
    stored = raw["env_state"]["collision_matrix"]
    expected = np.array([_vector(stored[str(i)]) for i in range(len(stored))])
    np.testing.assert_array_equal(load_level(fixture_file).level.sim.collision_matrix, expected)


def test_fixture_mass_properties_match_density_and_geometry(fixture_file):
    """The file's inverse masses are used as given; they equal the exact values for rectangles and discs, except
    that disc inverse inertias are twice ours: Jax2D's I = m r^2 / 4 instead of m r^2 / 2."""
    raw = json.loads(fixture_file.read_text())
    level = load_level(fixture_file).level
    bodies = level.sim.bodies
    for index, shape in enumerate(_shapes(raw)):
        if not shape["active"] or shape["inverse_mass"] == 0:
            continue
        assert float(bodies.inverse_mass[index]) == np.float32(shape["inverse_mass"])
        assert float(bodies.inverse_inertia[index]) == np.float32(shape["inverse_inertia"])
        density = shape["density"]
        if index < len(raw["env_state"]["polygon"]):
            corners = np.array([_vector(shape["vertices"][str(k)]) for k in range(4)])
            width, height = np.linalg.norm(corners[1] - corners[0]), np.linalg.norm(corners[2] - corners[1])
            # Every fixture polygon is a box: perpendicular sides.
            assert abs(np.dot(corners[1] - corners[0], corners[2] - corners[1])) < 1e-6
            mass = density * width * height
            inertia = mass * (width**2 + height**2) / 12
            assert shape["inverse_mass"] == pytest.approx(1 / mass, rel=1e-5)
            assert shape["inverse_inertia"] == pytest.approx(1 / inertia, rel=1e-5)
            # Our counter-clockwise vertices give the same (positive) area.
            engine_mass, _, engine_inertia = polygon_mass_properties(bodies.vertices[index], 4, density)
            assert float(engine_mass) == pytest.approx(mass, rel=1e-5)
            assert float(engine_inertia) == pytest.approx(inertia, rel=1e-5)
        else:
            radius = shape["radius"]
            mass = density * math.pi * radius**2
            assert shape["inverse_mass"] == pytest.approx(1 / mass, rel=1e-5)
            assert shape["inverse_inertia"] == pytest.approx(2 / (0.5 * mass * radius**2), rel=1e-5)


# Joints whose anchors do not coincide in the file: (level, joint) -> distance [m] between the two world anchors.
# m/arm_up's lower arm was rotated in the editor after it was pinned, so its joint starts 3 cm apart; one of
# l/gears' joints starts 2 cm apart in the file.
SEPARATED_JOINTS = {("m/arm_up", 1): 0.0302, ("l/gears", 4): 0.0200}


def test_fixture_joint_anchors_coincide_in_world(fixture_file):
    """Anchors map to the same world point from both bodies: checks the anchor and rotation mapping."""
    name = f"{fixture_file.parent.name}/{fixture_file.stem}"
    level = load_level(fixture_file).level
    bodies, joints = jax.tree.map(np.asarray, (level.sim.bodies, level.sim.joints))
    for j in np.flatnonzero(joints.active):
        a, b = joints.body_a[j], joints.body_b[j]
        world_a = bodies.position[a] + rotate_host(bodies.rotation[a], joints.anchor_a[j])
        world_b = bodies.position[b] + rotate_host(bodies.rotation[b], joints.anchor_b[j])
        gap = float(np.linalg.norm(world_a - world_b))
        assert gap == pytest.approx(SEPARATED_JOINTS.get((name, int(j)), 0.0), abs=1e-4), (name, j)


def _world_corners(level: Level, body: int) -> np.ndarray:
    bodies = jax.tree.map(np.asarray, level.sim.bodies)
    n = bodies.n_vertices[body]
    return bodies.position[body] + rotate_host(bodies.rotation[body], bodies.vertices[body, :n])


def _signed_area(points: np.ndarray) -> float:
    following = np.roll(points, -1, axis=0)
    return 0.5 * float(np.sum(points[:, 0] * following[:, 1] - points[:, 1] * following[:, 0]))


def test_h4_thrust_aim_green_box_corners(levels_dir):
    # Green box (polygon 4): position (4.4875, 4.435), rotation 0, Kinetix vertices (+-0.3225, +-0.195) clockwise
    # from top-right. World corners: x = 4.4875 +- 0.3225 = 4.81 / 4.165, y = 4.435 +- 0.195 = 4.63 / 4.24.
    level = load_level(levels_dir / "s" / "h4_thrust_aim.json").level
    assert int(level.task.roles[4]) == Role.GREEN
    corners = _world_corners(level, 4)
    assert _signed_area(corners) > 0  # counter-clockwise in our engine
    expected_ccw = [(4.165, 4.63), (4.165, 4.24), (4.81, 4.24), (4.81, 4.63)]  # Kinetix order reversed
    np.testing.assert_allclose(corners, expected_ccw, atol=1e-5)


def test_arm_left_rotated_green_arm_corners(levels_dir):
    # Green arm (polygon 5): position (2.8675, 1.1475), rotation pi/4, Kinetix vertices (+-0.1025, +-0.6525).
    # Corner (0.1025, 0.6525) -> (2.8675 + (0.1025 - 0.6525) / sqrt 2, 1.1475 + (0.1025 + 0.6525) / sqrt 2)
    # = (2.47859, 1.68137); likewise for the others, listed in our (reversed, counter-clockwise) order.
    level = load_level(levels_dir / "m" / "arm_left.json").level
    assert int(level.task.roles[5]) == Role.GREEN
    corners = _world_corners(level, 5)
    expected_ccw = [(2.33363, 1.53641), (3.25641, 0.61363), (3.40136, 0.75859), (2.47859, 1.68137)]
    np.testing.assert_allclose(corners, expected_ccw, atol=1e-4)
    assert _signed_area(corners) > 0


# ------------------------------------------------------------------------------------------ saving


def _flatten(tree, prefix="") -> dict[str, object]:
    if isinstance(tree, dict):
        return {k: v for key, value in tree.items() for k, v in _flatten(value, f"{prefix}/{key}").items()}
    if isinstance(tree, list):
        return {k: v for i, value in enumerate(tree) for k, v in _flatten(value, f"{prefix}/{i}").items()}
    return {prefix: tree}


def _unmodelled_default(path: str):
    """Kinetix's value of a field our engine does not model, or None if the field is modelled."""
    parts = [p for p in path.split("/") if p and not p.isdigit()]
    if parts[0] == "env_params" and parts[1] in KINETIX_DEFAULT_ENV_PARAMS:
        return KINETIX_DEFAULT_ENV_PARAMS[parts[1]]
    if parts[0] == "static_env_params" and parts[1] == "downscale":
        return 4
    if parts[0] != "env_state":
        return None
    kind, field = parts[1], parts[2] if len(parts) > 2 else None
    if kind.startswith("acc_"):
        return False if field == "active" else 0.0
    unmodelled = {
        ("circle", "vertices"): 0.0,
        ("circle", "n_vertices"): 0,
        ("polygon", "radius"): 0.0,
        ("polygon", "highlighted"): False,
        ("circle", "highlighted"): False,
        ("joint", "acc_impulse"): 0.0,
        ("joint", "acc_r_impulse"): 0.0,
    }
    return unmodelled.get((kind, field))


def _stale_cache(raw: dict, path: str) -> bool:
    """A `global_position` cache of an inactive joint or thruster slot: Kinetix leaves whatever was there (some l
    files hold 256 or 0), and we write the anchor's world position, so its value carries nothing to compare."""
    parts = path.strip("/").split("/")
    if parts[0] != "env_state" or parts[1] not in ("joint", "thruster") or parts[3] != "global_position":
        return False
    return not raw["env_state"][parts[1]][int(parts[2])]["active"]


def test_saved_fixture_reproduces_the_file(fixture_file):
    raw = json.loads(fixture_file.read_text())
    saved = level_to_dict(*load_level(fixture_file))
    original, written = _flatten(raw), _flatten(saved)
    assert written.keys() == original.keys()
    for path, value in written.items():
        if _stale_cache(raw, path):
            continue
        default = _unmodelled_default(path)
        expected = original[path] if default is None else default
        assert type(value) is type(expected) or {type(value), type(expected)} == {int, float}, path
        if isinstance(expected, float):
            assert value == pytest.approx(expected, abs=FLOAT_TOLERANCE), path
        else:
            assert value == expected, path


def test_save_load_round_trip_of_fixture_is_exact(fixture_file, tmp_path):
    loaded = load_level(fixture_file)
    save_level(*loaded, tmp_path / "level.json")
    again = load_level(tmp_path / "level.json")
    _assert_levels_equal(again.level, loaded.level)
    assert again.static == loaded.static
    assert again.params == loaded.params


def _built_level(size: str) -> tuple[Level, StaticEnvParams]:
    """A scene using every feature: triangle, rotated box, disc, revolute joint with limits and motor, fixed joint,
    thruster, roles, non-zero velocities, several bindings."""
    static = StaticEnvParams.for_size(size)
    builder = SceneBuilder(static.sim)
    box = builder.add_box((1.0, 1.0), (0.6, 0.3), rotation=0.3, velocity=(0.5, -0.25), density=2.0)
    triangle = builder.add_polygon((2.0, 1.5), [(0.0, 0.0), (0.4, 0.0), (0.1, 0.3)], rotation=-0.7, friction=0.5)
    wheel = builder.add_circle((1.3, 1.2), 0.2, angular_velocity=1.5, restitution=0.25)
    ball = builder.add_circle((3.5, 2.0), 0.3, static=True)
    builder.add_revolute_joint(box, wheel, (1.3, 1.1), motor_speed=-1.5, motor_power=2.0, motor_on=True, limits=(-1, 2))
    builder.add_fixed_joint(box, triangle, (1.5, 1.2))
    builder.add_thruster(triangle, (2.1, 1.55), angle=2.0, power=0.7)
    sim = builder.build()
    n, j, t = static.num_bodies, static.sim.num_joints, static.sim.num_thrusters
    roles = np.zeros(n, np.int32)
    roles[[box, wheel, ball, 1]] = [Role.GREEN, Role.RED, Role.BLUE, Role.RED]
    task = Task(
        roles=jax.numpy.asarray(roles),
        densities=jax.numpy.asarray(builder.densities, jax.numpy.float32),
        motor_bindings=jax.numpy.asarray(np.arange(j) % 4, jax.numpy.int32),
        thruster_bindings=jax.numpy.asarray(np.arange(t)[::-1] % 2, jax.numpy.int32),
        motor_auto=jax.numpy.zeros(j, bool),
    )
    return Level(sim=sim, task=task), static


@pytest.mark.parametrize("size", ["m", "l"])
def test_built_level_round_trip_is_exact(size, tmp_path):
    level, static = _built_level(size)
    params = EnvParams(dense_reward_scale=0.2)
    save_level(level, static, params, tmp_path / "level.json")
    loaded = load_level(tmp_path / "level.json")
    assert loaded.static == static
    assert loaded.params == params
    _assert_levels_equal(loaded.level, level)
    raw = json.loads((tmp_path / "level.json").read_text())
    assert raw["static_env_params"]["num_polygons"] == static.sim.num_polygons
    # Kinetix stores the triangle clockwise: its first three vertices have a negative signed area.
    triangle = raw["env_state"]["polygon"][5]
    assert triangle["n_vertices"] == 3
    assert _signed_area(np.array([_vector(triangle["vertices"][str(k)]) for k in range(3)])) < 0


def test_saving_motor_auto_is_refused():
    level, static = _built_level("m")
    level = level.replace(task=level.task.replace(motor_auto=jax.numpy.array([False, True])))
    with pytest.raises(ValueError, match="motor_auto"):
        level_to_dict(level, static, EnvParams())


def _expand_m_to_l(raw: dict) -> dict:
    """The m level in an l-size file: inactive padding slots appended and global shape indices >= 6 shifted by 6,
    as Kinetix's `expand_env_state` does."""
    raw = copy.deepcopy(raw)
    state = raw["env_state"]
    large = StaticSimParams.for_size("l")
    old_polygons = StaticSimParams.for_size("m").num_polygons
    polygons, circles, joints, thrusters = large.num_polygons, large.num_circles, large.num_joints, large.num_thrusters
    shift = polygons - old_polygons

    def padded(records, count):
        blank = copy.deepcopy(records[-1])
        blank["active"] = False
        return records + [copy.deepcopy(blank) for _ in range(count - len(records))]

    state["polygon"] = padded(state["polygon"], polygons)
    state["circle"] = padded(state["circle"], circles)
    state["joint"] = padded(state["joint"], joints)
    state["thruster"] = padded(state["thruster"], thrusters)
    for record in state["joint"]:
        for key in ("a_index", "b_index"):
            record[key] += shift if record[key] >= old_polygons else 0
    for record in state["thruster"]:
        record["object_index"] += shift if record["object_index"] >= old_polygons else 0
    n = polygons + circles
    state["collision_matrix"] = {str(i): {str(k): i != k for k in range(n)} for i in range(n)}
    manifold = state["acc_rr_manifolds"][0]
    state["acc_rr_manifolds"] = [manifold] * (2 * (polygons * (polygons - 1) // 2 - 6))
    state["acc_cr_manifolds"] = [manifold] * (polygons * circles)
    state["acc_cc_manifolds"] = [manifold] * (circles * (circles - 1) // 2)
    raw["static_env_params"].update(num_polygons=polygons, num_circles=circles, num_joints=joints)
    return raw


def test_m_level_expanded_to_size_l_loads(levels_dir):
    # m/h2_car_right: green box (polygon 4) carries two motor wheels, circles 1 and 0 (global 7 and 6 in m).
    raw = json.loads((levels_dir / "m" / "h2_car_right.json").read_text())
    loaded_m = load_level(raw)
    loaded_l = load_level(_expand_m_to_l(raw))
    assert loaded_l.static == StaticEnvParams.for_size("l")
    joints_m, joints_l = loaded_m.level.sim.joints, loaded_l.level.sim.joints
    np.testing.assert_array_equal(joints_m.body_a[:2], [4, 4])
    np.testing.assert_array_equal(joints_m.body_b[:2], [7, 6])
    np.testing.assert_array_equal(joints_l.body_b[:2], [13, 12])  # circles now start at global index 12
    bodies_m, bodies_l = loaded_m.level.sim.bodies, loaded_l.level.sim.bodies
    np.testing.assert_array_equal(bodies_l.position[12:15], bodies_m.position[6:9])
    np.testing.assert_array_equal(bodies_l.position[:6], bodies_m.position[:6])
    np.testing.assert_array_equal(loaded_l.level.task.roles[12:15], loaded_m.level.task.roles[6:9])
    assert not np.any(bodies_l.active[6:12]) and not np.any(joints_l.active[2:])
    # Wheels and body are one jointed group: they must not collide with each other, but do with the rest.
    matrix = np.asarray(loaded_l.level.sim.collision_matrix)
    assert not matrix[4, 12] and not matrix[12, 13] and matrix[12, 0] and matrix[4, 14]


# ------------------------------------------------------------------------------------------ malformed files


def _h4(levels_dir) -> dict:
    return json.loads((levels_dir / "s" / "h4_thrust_aim.json").read_text())


def _set(path: str, value):
    """Mutation replacing the value at a '/'-separated path (list indices as numbers)."""

    def mutate(raw):
        *parents, last = path.split("/")
        node = raw
        for part in parents:
            node = node[int(part)] if isinstance(node, list) else node[part]
        if value is DELETE:
            del node[int(last) if isinstance(node, list) else last]
        else:
            node[int(last) if isinstance(node, list) else last] = value

    return mutate


DELETE = object()
CW_CONCAVE = {
    "0": {"0": -0.1, "1": -0.05},
    "1": {"0": 0.32, "1": -0.2},
    "2": {"0": -0.32, "1": -0.2},
    "3": {"0": -0.32, "1": 0.2},
}
CCW_BOX = {
    "0": {"0": -0.3, "1": 0.2},
    "1": {"0": -0.3, "1": -0.2},
    "2": {"0": 0.3, "1": -0.2},
    "3": {"0": 0.3, "1": 0.2},
}

MALFORMED = {
    "three vertices": (
        _set("env_state/polygon/4/vertices/3", DELETE),
        "env_state.polygon[4].vertices: expected 4 points, got 3",
    ),
    "missing field": (_set("env_state/polygon/4/inverse_mass", DELETE), "env_state.polygon[4].inverse_mass: missing"),
    "missing section": (_set("env_params", DELETE), "env_params: missing"),
    "bool as number": (_set("env_state/polygon/4/rotation", True), "env_state.polygon[4].rotation: expected a number"),
    "number as bool": (_set("env_state/circle/1/active", 1), "env_state.circle[1].active: expected true/false"),
    "string coordinate": (
        _set("env_state/polygon/4/position/0", "4.5"),
        "env_state.polygon[4].position[0]: expected a number",
    ),
    "nan": (_set("env_state/circle/0/position/1", float("nan")), "env_state.circle[0].position[1]: expected a finite"),
    "fractional index": (
        _set("env_state/thruster/0/object_index", 4.5),
        "env_state.thruster[0].object_index: expected an integer",
    ),
    "slot count": (_set("env_state/circle/1", DELETE), "env_state.circle: expected 2 slots"),
    "array keys": (
        _set("env_state/polygon/4/vertices", {**CCW_BOX, "7": CCW_BOX["3"]}),
        "env_state.polygon[4].vertices: array keys",
    ),
    "non-convex": (_set("env_state/polygon/4/vertices", CW_CONCAVE), "env_state.polygon[4].vertices: polygon is not"),
    "counter-clockwise": (
        _set("env_state/polygon/4/vertices", CCW_BOX),
        "env_state.polygon[4].vertices: vertices must",
    ),
    "triangle with n_vertices 2": (_set("env_state/polygon/4/n_vertices", 2), "env_state.polygon[4].n_vertices"),
    "role": (_set("env_state/polygon/4/role", 4), "env_state.polygon[4].role: must be in 0..3, got 4"),
    "collision mode": (_set("env_state/circle/0/collision_mode", 3), "env_state.circle[0].collision_mode"),
    "negative inverse mass": (_set("env_state/circle/0/inverse_mass", -1.0), "env_state.circle[0].inverse_mass"),
    "restitution": (_set("env_state/circle/0/restitution", 1.5), "env_state.circle[0].restitution"),
    "zero radius": (_set("env_state/circle/0/radius", 0.0), "env_state.circle[0].radius"),
    "movable boundary": (_set("env_state/polygon/0/inverse_mass", 1.0), "env_state.polygon[0].inverse_mass"),
    "joint index": (_set("env_state/joint/0/a_index", 7), "env_state.joint[0].a_index: shape index 7 out of range"),
    "thruster index": (_set("env_state/thruster/0/object_index", -1), "env_state.thruster[0].object_index"),
    "thruster binding": (_set("env_state/thruster/0/thruster_binding", 2), "env_state.thruster[0].thruster_binding"),
    "thruster on inactive shape": (
        _set("env_state/polygon/4/active", False),
        "env_state.thruster[0].object_index: active thruster on inactive shape 4",
    ),
    "collision matrix size": (_set("env_state/collision_matrix/6", DELETE), "env_state.collision_matrix: expected 7"),
    "manifold count": (_set("env_state/acc_cr_manifolds/9", DELETE), "env_state.acc_cr_manifolds: expected 10"),
    "gravity": (_set("env_state/gravity/1", None), "env_state.gravity[1]: expected a number"),
    "boundary count": (
        _set("static_env_params/num_static_fixated_polys", 3),
        "static_env_params.num_static_fixated_polys: expected 4",
    ),
    "too few polygons": (_set("static_env_params/num_polygons", 3), "static_env_params.num_polygons"),
    "frame skip": (_set("static_env_params/frame_skip", 0), "static_env_params.frame_skip: must be >= 1"),
    "dt": (_set("env_params/dt", 0.0), "env_params.dt: must be > 0"),
}


@pytest.mark.parametrize("case", MALFORMED)
def test_malformed_level_names_the_field(case, levels_dir):
    mutate, message = MALFORMED[case]
    raw = _h4(levels_dir)
    mutate(raw)
    with pytest.raises(LevelFileError) as error:
        load_level(raw)
    assert message in str(error.value)
    assert isinstance(error.value, ValueError)


def test_joint_on_inactive_shape_is_refused(levels_dir):
    raw = json.loads((levels_dir / "m" / "h2_car_right.json").read_text())
    raw["env_state"]["circle"][0]["active"] = False
    with pytest.raises(
        LevelFileError, match=r"env_state\.joint\[1\]\.b_index: active joint attached to inactive shape 6"
    ):
        load_level(raw)


def test_error_from_a_file_names_the_file(tmp_path, levels_dir):
    raw = _h4(levels_dir)
    raw["env_state"]["polygon"][4]["role"] = 9
    path = tmp_path / "broken.json"
    path.write_text(json.dumps(raw))
    with pytest.raises(LevelFileError, match=r"broken\.json: env_state\.polygon\[4\]\.role"):
        load_level(path)
    path.write_text("{not json")
    with pytest.raises(LevelFileError, match=r"broken\.json: not valid JSON"):
        load_level(path)


def test_document_must_be_an_object():
    with pytest.raises(LevelFileError, match="document: expected an object"):
        load_level([1, 2])


def test_bundled_levels_load_by_name_with_their_size():
    assert [len(list_levels(size)) for size in ("s", "m", "l")] == [10, 24, 40]
    cartpole = load_level("l/h4_cartpole")
    assert cartpole.static == load_level(bundled_level_path("l/h4_cartpole")).static
    assert (cartpole.static.sim.num_polygons, cartpole.static.sim.num_joints) == (12, 6)
    assert load_level("s/h4_thrust_aim.json").static.sim.num_polygons == 5


def test_an_unknown_level_name_is_refused_with_close_names():
    expected = r"^l/h4_cartpol: no such level file or bundled level \(did you mean l/h4_c"
    with pytest.raises(LevelFileError, match=expected):
        load_level("l/h4_cartpol")
    with pytest.raises(LevelFileError, match="kforge levels list names the bundled ones"):
        load_level("q/nothing-like-it")


def test_an_existing_file_wins_over_a_bundled_name(tmp_path, monkeypatch):
    raw = json.loads(bundled_level_path("s/h0_weak_thrust").read_text())
    raw["env_state"]["gravity"] = {"0": 0.0, "1": -5.0}
    (tmp_path / "s").mkdir()
    (tmp_path / "s" / "h4_thrust_aim").write_text(json.dumps(raw))
    monkeypatch.chdir(tmp_path)
    assert float(load_level("s/h4_thrust_aim").level.sim.gravity[1]) == -5.0
