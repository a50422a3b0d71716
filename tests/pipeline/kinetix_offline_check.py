"""Checks run inside a virtualenv with kinetix-env 3.0.2 (zarr 2.18): Kinetix's own code against a `kforge export`.

Run by tests/pipeline/test_kinetix_offline_compat.py; it needs only Kinetix's dependencies, not this project.

1. zarr 2.18 opens the export; every shard's record fields are `action`, `action_mask`, `done` and `env_state/` plus
   the flattened leaves of Kinetix's own size-s EnvState, in its order, with its shapes and dtypes; the values of
   each row equal our dataset's (EXPECTED, in our field names, mapped here by hand).
2. `TrajectoryDatasetManager` loads one epoch: the EnvState pytree has Kinetix's structure, every leaf (B, T, ...)
   with Kinetix's dtype; each loaded trajectory equals one of ours; the stored action mask equals Kinetix's
   `get_valid_action_mask_np` of the loaded states.
3. Kinetix's pixel renderer draws loaded states: the green and the (static, half-tone) blue disc appear where their
   positions say, the grey arm is drawn; the images are written as PNG.
4. Kinetix's level loader reads the given level files, Kinetix's env rolls each out with no-op actions, and the
   windows are written as a zarr 2.18 shard following Kinetix-Offline's recipe (our importer reads it back).

Prints a JSON report on success; exits non-zero with the failing check's message otherwise.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import zarr
from flax.serialization import to_state_dict
from flax.traverse_util import flatten_dict
from kinetix.data.bc_utils import get_valid_action_mask, get_valid_action_mask_np
from kinetix.data.data_utils import TrajectoryDatasetManager
from kinetix.environment.env import make_kinetix_env
from kinetix.environment.env_state import EnvParams
from kinetix.environment.spaces import ActionType, ObservationType
from kinetix.environment.utils import create_empty_env, static_env_params_from_size
from kinetix.render.renderer_pixels import make_render_pixels
from kinetix.util.saving import load_from_json_file
from PIL import Image

RECORD_FIELDS = ("action", "action_mask", "done")
PIXELS_PER_METRE = 25  # Kinetix pixels_per_unit 100 / downscale 4; image axis 0 is x, axis 1 is y (up)
DISC_PIXELS = (50, 110)  # pixels of a 0.2 m disc: pi (0.2 * 25)^2 = 79, edges either way
CENTRE_TOLERANCE = 1.5  # [px]
GREEN = (0.0, 204.0, 0.0)  # Kinetix role 1, movable
STATIC_BLUE = (0.0, 51.0, 102.0)  # Kinetix role 2 at half tone: a static shape
GREY = (160.0, 160.0, 160.0)  # role 0, movable: the arm
KINETIX_STEPS = 8  # env steps of each window written with Kinetix's own code


def check(condition: bool, message: str) -> None:
    if not condition:
        raise SystemExit(f"check failed: {message}")


def kinetix_leaves(state) -> dict[str, np.ndarray]:
    return {name: np.asarray(value) for name, value in flatten_dict(to_state_dict(state), sep="/").items()}


def expected_kinetix(ours: dict[str, np.ndarray], num_polygons: int) -> dict[str, np.ndarray]:
    """Kinetix leaves (level, T, ...) of our trajectories, from our field names (hand-written mapping)."""
    p = num_polygons
    out = {}
    for name in ("position", "rotation", "velocity", "angular_velocity", "inverse_mass", "inverse_inertia", "active"):
        out[f"polygon/{name}"] = ours[f"bodies/{name}"][:, :, :p]
        out[f"circle/{name}"] = ours[f"bodies/{name}"][:, :, p:]
    out["circle/radius"] = ours["bodies/radius"][:, :, p:]
    vertices = ours["bodies/vertices"][:, :, :p].copy()
    n_vertices = ours["bodies/n_vertices"][0, 0, :p]
    for slot, n in enumerate(n_vertices):
        vertices[:, :, slot, :n] = vertices[:, :, slot, :n][:, :, ::-1]  # ours counter-clockwise, Kinetix clockwise
    out["polygon/vertices"] = vertices
    out["polygon_shape_roles"] = ours["task/roles"][:, :, :p]
    out["circle_shape_roles"] = ours["task/roles"][:, :, p:]
    out["polygon_densities"] = ours["task/densities"][:, :, :p]
    out["circle_densities"] = ours["task/densities"][:, :, p:]
    out["joint/a_index"] = ours["joints/body_a"]
    out["joint/b_index"] = ours["joints/body_b"]
    out["joint/a_relative_pos"] = ours["joints/anchor_a"]
    out["joint/rotation"] = ours["joints/reference_angle"]
    out["joint/motor_on"] = ours["joints/motor_on"]
    out["thruster/object_index"] = ours["thrusters/body"]
    out["thruster/rotation"] = ours["thrusters/angle"]
    out["thruster/power"] = ours["thrusters/power"]
    out["motor_bindings"] = ours["task/motor_bindings"]
    out["thruster_bindings"] = ours["task/thruster_bindings"]
    out["collision_matrix"] = ours["collision_matrix"]
    out["gravity"] = ours["gravity"]
    out["timestep"] = ours["timestep"]
    out["last_distance"] = ours["last_distance"]
    return out


def check_trajectory(kinetix: dict[str, np.ndarray], expected: dict[str, np.ndarray], level: int, where: str) -> None:
    for name, value in expected.items():
        check(np.array_equal(kinetix[name], value[level]), f"{where}: {name} differs from our dataset")


def check_raw_shards(group: Path, template: dict, expected: dict, ours: dict, level_of_id: dict) -> int:
    root = zarr.open_group(str(group), mode="r")
    names = sorted(root.array_keys())
    check(bool(names), "no shards")
    field_names = [*RECORD_FIELDS, *(f"env_state/{name}" for name in template)]
    rows = 0
    for name in names:
        array = root[name]
        check(array.ndim == 3 and array.shape[2] == 1, f"{name}: shape {array.shape}")
        check(list(array.dtype.names) == field_names, f"{name}: record fields {array.dtype.names}")
        for leaf, value in template.items():
            field = array.dtype.fields[f"env_state/{leaf}"][0]
            check(field.shape == value.shape and field.base == value.dtype, f"{name}: {leaf} is {field}")
        records = array[:]
        for row, level_id in enumerate(array.attrs["kforge_export"]["level_id"]):
            level = level_of_id[level_id]
            record = records[row, :, 0]
            leaves = {leaf: record[f"env_state/{leaf}"] for leaf in template}
            check_trajectory(leaves, expected, level, f"{name} row {row}")
            for field in RECORD_FIELDS:
                check(np.array_equal(record[field], ours[field][level]), f"{name} row {row}: {field}")
            rows += 1
    return rows


def check_loader(group: Path, template_state, expected: dict, ours: dict, static) -> tuple[list, int]:
    manager = TrajectoryDatasetManager(str(group), batch_size=4, seed=0)
    treedef = jax.tree.structure(template_state)
    states, count = [], 0
    for _ in range(manager.length):
        batch = manager.load_next_batch()
        check(jax.tree.structure(batch.env_state) == treedef, "loaded EnvState has another pytree structure")
        steps = batch.done.shape[1]
        for leaf, value in zip(jax.tree.leaves(batch.env_state), jax.tree.leaves(template_state), strict=True):
            check(np.shape(leaf) == (4, steps, *np.shape(value)), f"leaf shape {np.shape(leaf)} vs {np.shape(value)}")
            check(np.asarray(leaf).dtype == np.asarray(value).dtype, f"leaf dtype {np.asarray(leaf).dtype}")
        check(batch.action.shape == (4, steps, 6) and batch.action.dtype == np.int32, "action shape/dtype")
        check(bool(np.all(batch.mask)), "mask not all True")
        flat = jax.tree.map(lambda x: np.asarray(x).reshape((-1, *np.shape(x)[2:])), batch.env_state)
        kinetix_mask = get_valid_action_mask_np(flat, static, np.asarray(batch.action).reshape(-1, 6))
        check(np.array_equal(kinetix_mask.reshape(batch.action_mask.shape), batch.action_mask), "action_mask")
        for row in range(4):
            state = jax.tree.map(lambda x, r=row: np.asarray(x[r]), batch.env_state)
            levels = [
                level
                for level in range(len(ours["action"]))
                if np.array_equal(batch.action[row], ours["action"][level])
                and np.array_equal(batch.done[row], ours["done"][level])
            ]
            check(len(levels) >= 1, f"loaded trajectory {count} matches none of ours")
            check_trajectory(kinetix_leaves(state), expected, levels[0], f"loaded trajectory {count}")
            states.append(state)
            count += 1
    return states, count


def colour_pixels(image: np.ndarray, colour) -> np.ndarray:
    return np.argwhere(np.all(np.abs(image - np.asarray(colour)) < 1.0, axis=-1))


def check_render(states: list, static, images: Path) -> list[dict]:
    render = make_render_pixels(EnvParams(), static)
    images.mkdir(parents=True, exist_ok=True)
    report = []
    for index, (trajectory, step) in enumerate([(0, 0), (0, -1), (1, 0)]):
        state = jax.tree.map(lambda x, t=step: x[t], states[trajectory])
        image = np.asarray(render(state))
        Image.fromarray(np.clip(image, 0, 255).astype(np.uint8).transpose(1, 0, 2)[::-1]).save(
            images / f"state_{index}.png"
        )
        stats = {"shape": list(image.shape), "distinct_colours": len(np.unique(image.reshape(-1, 3), axis=0))}
        for role, colour in ((1, GREEN), (2, STATIC_BLUE)):
            pixels = colour_pixels(image, colour)
            check(
                DISC_PIXELS[0] <= len(pixels) <= DISC_PIXELS[1], f"image {index}: {len(pixels)} pixels of role {role}"
            )
            centre = state.circle.position[list(state.circle_shape_roles).index(role)] * PIXELS_PER_METRE
            offset = np.abs(pixels.mean(axis=0) - centre).max()
            check(offset <= CENTRE_TOLERANCE, f"image {index}: role {role} drawn {offset:.1f} px from its position")
            stats[f"role_{role}_pixels"] = len(pixels)
        stats["grey_pixels"] = len(colour_pixels(image, GREY))
        check(stats["grey_pixels"] > 0, f"image {index}: the grey arm is not drawn")
        report.append(stats)
    return report


def write_kinetix_shard(levels: list[str], out: Path, static) -> None:
    """Kinetix-Offline recipe: roll each level out from its start (state before each action, action, done after)."""
    loaded = [load_from_json_file(path) for path in levels]
    start = jax.tree.map(lambda *xs: jnp.stack(xs), *[state for state, _, _ in loaded])
    env_params = loaded[0][2]
    env = make_kinetix_env(ActionType.MULTI_DISCRETE, ObservationType.SYMBOLIC_FLAT, None, env_params, static)
    action = jnp.zeros((len(levels), 6), jnp.int32)

    def one_step(state, key):
        keys = jax.random.split(key, len(levels))
        step = jax.vmap(env.step, in_axes=(0, 0, 0, None, 0))
        _, next_state, _, done, _ = step(keys, state, action, env_params, start)
        return next_state, (state, done)

    _, (states, done) = jax.lax.scan(one_step, start, jax.random.split(jax.random.PRNGKey(0), KINETIX_STEPS))
    columns = {"action": np.broadcast_to(np.asarray(action)[None], (KINETIX_STEPS, len(levels), 6))}
    flat_states = jax.tree.map(lambda x: np.asarray(x).reshape((-1, *np.shape(x)[2:])), states)
    # the jax version: the numpy one indexes out of bounds with the unused bindings of inactive thrusters in some files
    mask = get_valid_action_mask(flat_states, static, jnp.zeros((KINETIX_STEPS * len(levels), 6), jnp.int32))
    columns["action_mask"] = np.asarray(mask).reshape(KINETIX_STEPS, len(levels), 6)
    columns["done"] = np.asarray(done)
    columns |= {f"env_state/{name}": value for name, value in kinetix_leaves(states).items()}
    columns = {name: np.swapaxes(value, 0, 1) for name, value in columns.items()}  # (level, step, ...)
    dtype = np.dtype([(name, value.dtype, value.shape[2:]) for name, value in columns.items()])
    records = np.zeros((len(levels), KINETIX_STEPS, 1), dtype)
    for name, value in columns.items():
        records[name] = value[:, :, None]
    root = zarr.open_group(str(out), mode="w")
    root.create_dataset("shard_00", data=records, chunks=(1, KINETIX_STEPS, 1))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--export", type=Path, required=True, help="the split group written by kforge export")
    parser.add_argument("--expected", type=Path, required=True, help="npz of our trajectories (our field names)")
    parser.add_argument("--images", type=Path, required=True, help="folder for the rendered PNGs")
    parser.add_argument("--write-shard", type=Path, required=True, help="group to write Kinetix's own shard into")
    parser.add_argument("--levels", nargs="+", required=True, help="size-s Kinetix level JSON files")
    args = parser.parse_args()
    static = static_env_params_from_size("s")
    template_state = create_empty_env(static)
    template = kinetix_leaves(template_state)
    data = np.load(args.expected)
    ours = {name: data[name] for name in data.files if name not in ("level_ids", "level_index")}
    level_of_id = dict(zip(data["level_ids"].tolist(), data["level_index"].tolist(), strict=True))
    expected = expected_kinetix(ours, static.num_polygons)
    rows = check_raw_shards(args.export, template, expected, ours, level_of_id)
    check(rows == len(level_of_id), f"{rows} rows in the shards, {len(level_of_id)} kept trajectories")
    states, loaded = check_loader(args.export, template_state, expected, ours, static)
    check(loaded == rows, f"one loader epoch gave {loaded} trajectories, expected {rows}")
    renders = check_render(states, static, args.images)
    write_kinetix_shard(args.levels, args.write_shard, static)
    report = {"fields": len(RECORD_FIELDS) + len(template), "rows": rows, "loaded": loaded, "renders": renders}
    print(json.dumps(report))


if __name__ == "__main__":
    main()
