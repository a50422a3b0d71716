"""Kinetix level files (JSON, as written by Kinetix's `export_env_state_to_json` and Kinetix.js): load and save.

A file has three top-level keys: `env_state` (lists of per-slot records for `polygon`, `circle`, `joint` and
`thruster`, plus `collision_matrix`, the three contact-manifold lists and `gravity`), `env_params` and
`static_env_params`. Arrays inside records are dicts keyed "0", "1", ... (nested for 2-D arrays). The level's size is
read from `static_env_params` (any slot counts with the four Kinetix boundary polygons, so s, m and l alike).

Loading follows Kinetix's loader: the collision matrix is recomputed from the joints, contact caches start empty and
episodes last 256 steps. Every malformed or inconsistent input raises `LevelFileError` naming the field path.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from kforge.engine import CONVEXITY_TOLERANCE, MIN_POLYGON_AREA, cross2
from kforge.env.bundled_levels import bundled_level_path, close_level_names
from kforge.env.kinetix_convert import (
    ENV_PARAM_ORDER,
    KINETIX_UNMODELLED_ENV_PARAMS,
    KINETIX_UNMODELLED_STATIC,
    MAX_VERTICES,
    NUM_BOUNDARY_POLYGONS,
    SIM_PARAM_FIELDS,
    STATIC_ORDER,
    KinetixLevel,
    level_from_kinetix,
    level_to_kinetix,
    params_from_kinetix,
    static_from_kinetix,
)
from kforge.env.params import NUM_MOTOR_BINDINGS, NUM_THRUSTER_BINDINGS, EnvParams, StaticEnvParams
from kforge.env.state import NUM_ROLES, Level

NUM_COLLISION_MODES = 3
"""Collision modes 0, 1 and 2."""

BODY_SCHEMA: dict[str, tuple[str, tuple[int, ...]]] = {
    "position": ("float", (2,)),
    "rotation": ("float", ()),
    "velocity": ("float", (2,)),
    "angular_velocity": ("float", ()),
    "inverse_mass": ("float", ()),
    "inverse_inertia": ("float", ()),
    "friction": ("float", ()),
    "restitution": ("float", ()),
    "collision_mode": ("int", ()),
    "active": ("bool", ()),
    "n_vertices": ("int", ()),
    "vertices": ("float", (MAX_VERTICES, 2)),
    "radius": ("float", ()),
    "role": ("int", ()),
    "density": ("float", ()),
    "highlighted": ("bool", ()),
}
"""Polygon and circle record fields: Jax2D `RigidBody` plus Kinetix's role, density and editor highlight."""

JOINT_SCHEMA: dict[str, tuple[str, tuple[int, ...]]] = {
    "a_index": ("int", ()),
    "b_index": ("int", ()),
    "a_relative_pos": ("float", (2,)),
    "b_relative_pos": ("float", (2,)),
    "global_position": ("float", (2,)),
    "active": ("bool", ()),
    "acc_impulse": ("float", (2,)),
    "acc_r_impulse": ("float", ()),
    "motor_speed": ("float", ()),
    "motor_power": ("float", ()),
    "motor_on": ("bool", ()),
    "motor_has_joint_limits": ("bool", ()),
    "min_rotation": ("float", ()),
    "max_rotation": ("float", ()),
    "is_fixed_joint": ("bool", ()),
    "rotation": ("float", ()),
    "motor_binding": ("int", ()),
}
"""Joint record fields: Jax2D `Joint` plus Kinetix's motor binding."""

THRUSTER_SCHEMA: dict[str, tuple[str, tuple[int, ...]]] = {
    "object_index": ("int", ()),
    "relative_position": ("float", (2,)),
    "rotation": ("float", ()),
    "power": ("float", ()),
    "global_position": ("float", (2,)),
    "active": ("bool", ()),
    "thruster_binding": ("int", ()),
}
"""Thruster record fields: Jax2D `Thruster` plus Kinetix's thruster binding."""

OPTIONAL_FIELDS = frozenset({"highlighted"})
"""Record fields that may be missing (Kinetix's loader tolerates it); they default to zero/False."""

MANIFOLD_FIELDS: dict[str, tuple[str, tuple[int, ...]]] = {
    "normal": ("float", (2,)),
    "penetration": ("float", ()),
    "collision_point": ("float", (2,)),
    "active": ("bool", ()),
    "acc_impulse_normal": ("float", ()),
    "acc_impulse_tangent": ("float", ()),
    "restitution_velocity_target": ("float", ()),
}
"""Contact manifold record fields (Jax2D `CollisionManifold`); written empty, ignored on load."""

COUNT_FIELDS = ("num_polygons", "num_circles", "num_joints", "num_thrusters")


class LevelFileError(ValueError):
    """A Kinetix level file (or dict) is malformed or inconsistent; the message names the offending field."""


class LoadedLevel(NamedTuple):
    """A level read from a Kinetix file, with the static and traced parameters it was designed for."""

    level: Level
    static: StaticEnvParams
    params: EnvParams


# ----------------------------------------------------------------------------------------------- decoding


def _fail(path: str, message: str):
    raise LevelFileError(f"{path}: {message}")


def _field(record: Any, key: str, path: str) -> Any:
    if not isinstance(record, Mapping):
        _fail(path or "document", f"expected an object, got {type(record).__name__}")
    if key not in record:
        _fail(f"{path}.{key}" if path else key, "missing")
    return record[key]


def _items(value: Any, count: int, path: str, noun: str) -> list:
    """Entries of a Kinetix array: a dict keyed "0".."count-1" (or a list), checked for length."""
    if isinstance(value, Mapping):
        expected_keys = {str(i) for i in range(len(value))}
        if set(value) != expected_keys:
            _fail(path, f"array keys must be '0'..'{len(value) - 1}', got {sorted(value)}")
        entries = [value[str(i)] for i in range(len(value))]
    elif isinstance(value, list):
        entries = value
    else:
        _fail(path, f"expected an array (dict keyed '0', '1', ...), got {type(value).__name__}")
    if len(entries) != count:
        _fail(path, f"expected {count} {noun}, got {len(entries)}")
    return entries


def _scalar(value: Any, kind: str, path: str):
    if kind == "bool":
        if not isinstance(value, bool):
            _fail(path, f"expected true/false, got {value!r}")
        return value
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        _fail(path, f"expected a number, got {value!r}")
    if not math.isfinite(value):
        _fail(path, f"expected a finite number, got {value!r}")
    if kind == "int":
        if not float(value).is_integer():
            _fail(path, f"expected an integer, got {value!r}")
        return int(value)
    return float(value)


def _decode(value: Any, kind: str, shape: tuple[int, ...], path: str):
    if not shape:
        return _scalar(value, kind, path)
    noun = "points" if len(shape) == 2 else "entries"
    return [_decode(v, kind, shape[1:], f"{path}[{i}]") for i, v in enumerate(_items(value, shape[0], path, noun))]


def _decode_records(records: Any, schema: dict, count: int, path: str, count_name: str) -> dict[str, np.ndarray]:
    """Per-field numpy arrays (slots on axis 0) of a list of slot records."""
    slots = _items(records, count, path, f"slots (static_env_params.{count_name})")
    columns: dict[str, list] = {name: [] for name in schema}
    for i, record in enumerate(slots):
        slot_path = f"{path}[{i}]"
        for name, (kind, shape) in schema.items():
            if name in OPTIONAL_FIELDS and isinstance(record, Mapping) and name not in record:
                value = np.zeros(shape, bool if kind == "bool" else float).tolist()
            else:
                value = _decode(_field(record, name, slot_path), kind, shape, f"{slot_path}.{name}")
            columns[name].append(value)
    dtypes = {"float": np.float64, "int": np.int64, "bool": bool}
    return {
        name: np.asarray(columns[name], dtypes[kind]).reshape((count, *shape)) for name, (kind, shape) in schema.items()
    }


def _check(condition: bool, path: str, message: str):
    if not condition:
        _fail(path, message)


def _decode_static(raw: Any) -> dict[str, int]:
    path = "static_env_params"
    counts = {name: _scalar(_field(raw, name, path), "int", f"{path}.{name}") for name in COUNT_FIELDS}
    for name in COUNT_FIELDS:
        _check(counts[name] >= 0, f"{path}.{name}", f"must be >= 0, got {counts[name]}")
    fixated = _scalar(_field(raw, "num_static_fixated_polys", path), "int", f"{path}.num_static_fixated_polys")
    _check(
        fixated == NUM_BOUNDARY_POLYGONS,
        f"{path}.num_static_fixated_polys",
        f"expected {NUM_BOUNDARY_POLYGONS} (floor, walls and ceiling in polygon slots 0-3), got {fixated}",
    )
    _check(
        counts["num_polygons"] >= NUM_BOUNDARY_POLYGONS,
        f"{path}.num_polygons",
        f"expected at least {NUM_BOUNDARY_POLYGONS} (the boundary polygons), got {counts['num_polygons']}",
    )
    max_vertices = _scalar(_field(raw, "max_polygon_vertices", path), "int", f"{path}.max_polygon_vertices")
    _check(max_vertices == MAX_VERTICES, f"{path}.max_polygon_vertices", f"expected {MAX_VERTICES}, got {max_vertices}")
    frame_skip = _scalar(_field(raw, "frame_skip", path), "int", f"{path}.frame_skip")
    _check(frame_skip >= 1, f"{path}.frame_skip", f"must be >= 1, got {frame_skip}")
    return {**counts, "frame_skip": frame_skip}


def _decode_env_params(raw: Any) -> dict[str, float]:
    path = "env_params"
    values = {
        name: _scalar(_field(raw, name, path), "float", f"{path}.{name}")
        for name in (*SIM_PARAM_FIELDS, "dense_reward_scale")
    }
    for name in ("dt", "clip_position", "clip_velocity", "clip_angular_velocity"):
        _check(values[name] > 0, f"{path}.{name}", f"must be > 0, got {values[name]}")
    for name in ("base_motor_speed", "base_motor_power", "base_thruster_power", "base_friction", "dense_reward_scale"):
        _check(values[name] >= 0, f"{path}.{name}", f"must be >= 0, got {values[name]}")
    return values


def _check_polygon_shape(vertices: np.ndarray, path: str):
    """Kinetix polygons: strictly convex, clockwise, not degenerate."""
    following = np.roll(vertices, -1, axis=0)
    doubled_area = float(np.sum(cross2(vertices, following)))
    _check(
        abs(doubled_area) >= 2 * MIN_POLYGON_AREA, path, f"degenerate polygon (area {abs(doubled_area) / 2:.3g} m^2)"
    )
    _check(doubled_area < 0, path, "vertices must be in clockwise order (Kinetix/Jax2D convention)")
    edges = following - vertices
    turns = cross2(edges, np.roll(edges, -1, axis=0))
    _check(bool(np.all(turns < -CONVEXITY_TOLERANCE)), path, "polygon is not strictly convex")


def _check_bodies(body: dict[str, np.ndarray], kind: str, first_index: int):
    for i in range(len(body["active"])):
        path = f"env_state.{kind}[{i}]"
        for name in ("inverse_mass", "inverse_inertia", "friction", "density"):
            _check(body[name][i] >= 0, f"{path}.{name}", f"must be >= 0, got {body[name][i]}")
        _check(
            0 <= body["restitution"][i] <= 1, f"{path}.restitution", f"must be in [0, 1], got {body['restitution'][i]}"
        )
        mode = body["collision_mode"][i]
        _check(0 <= mode < NUM_COLLISION_MODES, f"{path}.collision_mode", f"must be 0, 1 or 2, got {mode}")
        role = body["role"][i]
        _check(0 <= role < NUM_ROLES, f"{path}.role", f"must be in 0..{NUM_ROLES - 1}, got {role}")
        n = body["n_vertices"][i]
        _check(0 <= n <= MAX_VERTICES, f"{path}.n_vertices", f"must be in 0..{MAX_VERTICES}, got {n}")
        if not body["active"][i]:
            continue
        if kind == "polygon":
            _check(n >= 3, f"{path}.n_vertices", f"an active polygon needs 3 or 4 vertices, got {n}")
            _check_polygon_shape(body["vertices"][i, :n], f"{path}.vertices")
            if first_index + i < NUM_BOUNDARY_POLYGONS:
                _check(
                    body["inverse_mass"][i] == 0,
                    f"{path}.inverse_mass",
                    f"polygon slots 0-{NUM_BOUNDARY_POLYGONS - 1} are static boundaries, got {body['inverse_mass'][i]}",
                )
        else:
            _check(
                body["radius"][i] > 0,
                f"{path}.radius",
                f"an active circle needs a positive radius, got {body['radius'][i]}",
            )


def _check_index(value: int, limit: int, path: str, what: str):
    _check(0 <= value < limit, path, f"{what} {value} out of range [0, {limit})")


def _check_actuators(joint: dict[str, np.ndarray], thruster: dict[str, np.ndarray], active: np.ndarray):
    num_bodies = len(active)
    for i in range(len(joint["active"])):
        path = f"env_state.joint[{i}]"
        for end in ("a_index", "b_index"):
            _check_index(joint[end][i], num_bodies, f"{path}.{end}", "shape index")
        if not joint["active"][i]:
            continue
        _check_index(joint["motor_binding"][i], NUM_MOTOR_BINDINGS, f"{path}.motor_binding", "binding")
        a, b = joint["a_index"][i], joint["b_index"][i]
        _check(a != b, f"{path}.b_index", f"a joint needs two different shapes, got {a} twice")
        for end, index in (("a_index", a), ("b_index", b)):
            _check(bool(active[index]), f"{path}.{end}", f"active joint attached to inactive shape {index}")
        _check(joint["motor_power"][i] >= 0, f"{path}.motor_power", f"must be >= 0, got {joint['motor_power'][i]}")
        if joint["motor_has_joint_limits"][i]:
            low, high = joint["min_rotation"][i], joint["max_rotation"][i]
            _check(low <= high, f"{path}.min_rotation", f"exceeds max_rotation ({low} > {high})")
    for i in range(len(thruster["active"])):
        path = f"env_state.thruster[{i}]"
        index = thruster["object_index"][i]
        _check_index(index, num_bodies, f"{path}.object_index", "shape index")
        if thruster["active"][i]:
            binding = thruster["thruster_binding"][i]
            _check_index(binding, NUM_THRUSTER_BINDINGS, f"{path}.thruster_binding", "binding")
            _check(bool(active[index]), f"{path}.object_index", f"active thruster on inactive shape {index}")
            _check(thruster["power"][i] >= 0, f"{path}.power", f"must be >= 0, got {thruster['power'][i]}")


def manifold_counts(num_polygons: int, num_circles: int) -> dict[str, int]:
    """Records per manifold list: two per polygon pair (pairs of boundary polygons excluded), one otherwise."""
    boundary_pairs = NUM_BOUNDARY_POLYGONS * (NUM_BOUNDARY_POLYGONS - 1) // 2
    polygon_pairs = num_polygons * (num_polygons - 1) // 2 - boundary_pairs
    return {
        "acc_rr_manifolds": 2 * polygon_pairs,
        "acc_cr_manifolds": num_polygons * num_circles,
        "acc_cc_manifolds": num_circles * (num_circles - 1) // 2,
    }


def decode_level(raw: Any) -> KinetixLevel:
    """Validate a parsed Kinetix level JSON document and decode it into numpy arrays."""
    static = _decode_static(_field(raw, "static_env_params", ""))
    env_params = _decode_env_params(_field(raw, "env_params", ""))
    state = _field(raw, "env_state", "")
    p, c = static["num_polygons"], static["num_circles"]
    polygon = _decode_records(
        _field(state, "polygon", "env_state"), BODY_SCHEMA, p, "env_state.polygon", "num_polygons"
    )
    circle = _decode_records(_field(state, "circle", "env_state"), BODY_SCHEMA, c, "env_state.circle", "num_circles")
    joint = _decode_records(
        _field(state, "joint", "env_state"), JOINT_SCHEMA, static["num_joints"], "env_state.joint", "num_joints"
    )
    thruster = _decode_records(
        _field(state, "thruster", "env_state"),
        THRUSTER_SCHEMA,
        static["num_thrusters"],
        "env_state.thruster",
        "num_thrusters",
    )
    num_bodies = p + c
    matrix = _decode(
        _field(state, "collision_matrix", "env_state"), "bool", (num_bodies, num_bodies), "env_state.collision_matrix"
    )
    for name, count in manifold_counts(p, c).items():
        _items(_field(state, name, "env_state"), count, f"env_state.{name}", "records")
    gravity = _decode(_field(state, "gravity", "env_state"), "float", (2,), "env_state.gravity")
    _check_bodies(polygon, "polygon", 0)
    _check_bodies(circle, "circle", p)
    _check_actuators(joint, thruster, np.concatenate([polygon["active"], circle["active"]]))
    return KinetixLevel(
        polygon=polygon,
        circle=circle,
        joint=joint,
        thruster=thruster,
        collision_matrix=np.asarray(matrix, bool),
        gravity=np.asarray(gravity),
        env_params=env_params,
        static_env_params=static,
    )


def load_level(source: str | os.PathLike | Mapping) -> LoadedLevel:
    """Read a Kinetix level from a JSON file path, a bundled level's name ("l/h4_cartpole", see `list_levels`; an
    existing file of that name wins) or an already parsed dict; `LevelFileError` if it is invalid or not found."""
    is_file = isinstance(source, (str, os.PathLike))
    if is_file and not Path(source).is_file():
        bundled = bundled_level_path(str(source))
        if bundled is None:
            close = close_level_names(str(source))
            hint = f" (did you mean {', '.join(close)}?)" if close else " (kforge levels list names the bundled ones)"
            raise LevelFileError(f"{source}: no such level file or bundled level{hint}")
        source = bundled
    if is_file:
        try:
            raw = json.loads(Path(source).read_text())
        except json.JSONDecodeError as error:
            raise LevelFileError(f"{source}: not valid JSON ({error})") from None
    else:
        raw = source
    try:
        kinetix = decode_level(raw)
    except LevelFileError as error:
        if not is_file:
            raise
        raise LevelFileError(f"{source}: {error}") from None
    static = static_from_kinetix(kinetix)
    return LoadedLevel(level_from_kinetix(kinetix, static), static, params_from_kinetix(kinetix))


# ----------------------------------------------------------------------------------------------- encoding


def _encode(value: np.ndarray, kind: str):
    """Kinetix's JSON form of an array: nested dicts keyed "0", "1", ...; scalars as JSON numbers or booleans."""
    value = np.asarray(value)
    if value.ndim:
        return {str(i): _encode(v, kind) for i, v in enumerate(value)}
    if kind == "bool":
        return bool(value)
    if kind == "int":
        return int(value)
    return float(np.float32(value))


def _encode_records(columns: dict[str, np.ndarray], schema: dict) -> list[dict]:
    count = len(next(iter(columns.values())))
    return [{name: _encode(columns[name][i], kind) for name, (kind, _) in schema.items()} for i in range(count)]


def _empty_manifolds(count: int) -> list[dict]:
    record = {name: _encode(np.zeros(shape), kind) for name, (kind, shape) in MANIFOLD_FIELDS.items()}
    return [dict(record) for _ in range(count)]


def level_to_dict(level: Level, static: StaticEnvParams, params: EnvParams) -> dict:
    """The Kinetix JSON document (as a dict) of a level, readable by Kinetix's loader and Kinetix.js.

    Raises ValueError for a level with auto motors: the format cannot store `motor_auto`.
    """
    if np.any(np.asarray(level.task.motor_auto)):
        raise ValueError("Task.motor_auto is set, but Kinetix level files cannot store motor_auto (it loads as False)")
    kinetix = level_to_kinetix(level, static, params)
    counts = kinetix.static_env_params
    env_state = {
        "polygon": _encode_records(kinetix.polygon, BODY_SCHEMA),
        "circle": _encode_records(kinetix.circle, BODY_SCHEMA),
        "joint": _encode_records(kinetix.joint, JOINT_SCHEMA),
        "thruster": _encode_records(kinetix.thruster, THRUSTER_SCHEMA),
        "collision_matrix": _encode(kinetix.collision_matrix, "bool"),
    }
    for name, count in manifold_counts(counts["num_polygons"], counts["num_circles"]).items():
        env_state[name] = _empty_manifolds(count)
    env_state["gravity"] = _encode(kinetix.gravity, "float")
    env_params = {**KINETIX_UNMODELLED_ENV_PARAMS, **kinetix.env_params}
    static_params = {**KINETIX_UNMODELLED_STATIC, **counts}
    return {
        "env_state": env_state,
        "env_params": {name: env_params[name] for name in ENV_PARAM_ORDER},
        "static_env_params": {name: static_params[name] for name in STATIC_ORDER},
    }


def save_level(level: Level, static: StaticEnvParams, params: EnvParams, path: str | os.PathLike) -> None:
    """Write a level as a Kinetix JSON file."""
    Path(path).write_text(json.dumps(level_to_dict(level, static, params)))
