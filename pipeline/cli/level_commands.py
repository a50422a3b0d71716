"""What `kforge levels` runs once its arguments are parsed (pipeline/cli/levels.py, which imports this module only
then): sampling, previews, import checks and split exports of Kinetix level JSON files."""

from __future__ import annotations

import argparse
import collections
import functools
import json
import re
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

import jax
import numpy as np
from PIL import Image
from tqdm import tqdm

from kforge.engine import KINETIX_SIZES, physics_scheme
from kforge.env import (
    BUNDLED_SIZES,
    GIF_RESOLUTION,
    EnvParams,
    Level,
    Policy,
    Role,
    StaticEnvParams,
    level_to_dict,
    list_levels,
    load_level,
    record_episode,
    render_image,
    reset,
    sample_levels,
    save_level,
    under_scheme,
    write_state_gif,
)
from kforge.pipeline.generation import EnvSection, KeyPurpose, level_keys, resolve, sample_batch

LEVELS_DIR = Path("outputs") / "levels"
"""Default parent folder of written levels and previews."""

LEVEL_FILE = "level-{:07d}.json"
"""File name of level i (7 digits: the largest release split has 5.98M levels)."""

SAMPLE_CHUNK = 64
"""Levels per sampler call of `sample` (one compiled shape; the last chunk's extra levels are discarded)."""

PREVIEW_SUPERSAMPLE = 2
"""Samples per pixel side of a PNG preview (antialiasing)."""

MAX_LISTED_CHANGES = 12
"""Groups of changed fields `import` lists before summarising the rest."""


def _sampled_levels(
    ids: Iterable[int], batch_size: int, sample: Callable[[np.ndarray], Level], progress: bool
) -> Iterator[tuple[int, Level]]:
    """(id, level) for each id, sampled in aligned batches `[k B, (k + 1) B)` by `sample(indices)`."""
    ids = list(ids)
    by_batch = collections.defaultdict(list)
    for level_id in ids:
        by_batch[level_id // batch_size].append(level_id)
    with tqdm(total=len(ids), unit="level", desc="levels", disable=not progress) as bar:
        for batch, members in sorted(by_batch.items()):
            levels = jax.device_get(sample(np.arange(batch * batch_size, (batch + 1) * batch_size)))
            for level_id in members:
                yield level_id, jax.tree.map(lambda x, i=level_id - batch * batch_size: x[i], levels)
                bar.update()


def sampled_levels(size: str, seed: int, ids: Iterable[int], progress: bool = False) -> Iterator[tuple[int, Level]]:
    """(id, level) of a split with this size and seed: level i from the key (seed, i)."""
    static = StaticEnvParams.for_size(size)
    return _sampled_levels(
        ids, SAMPLE_CHUNK, lambda indices: sample_levels(level_keys(seed, indices, KeyPurpose.SAMPLE), static), progress
    )


def sample_params() -> EnvParams:
    """Env params written into sampled level files: the job schema's training defaults."""
    return EnvParams(dense_reward_scale=EnvSection().dense_reward_scale)


def _write_levels(levels: Iterator[tuple[int, Level]], static: StaticEnvParams, params: EnvParams, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    for level_id, level in levels:
        save_level(level, static, params, out / LEVEL_FILE.format(level_id))
    print(out)


def sample_command(args: argparse.Namespace) -> None:
    """`levels sample`: sample the levels and write one file per level into --out."""
    out = args.out or LEVELS_DIR / f"{args.size}-seed{args.seed}"
    ids = range(args.start, args.start + args.num)
    levels = sampled_levels(args.size, args.seed, ids, progress=not args.no_progress)
    _write_levels(levels, StaticEnvParams.for_size(args.size), sample_params(), out)


def export_command(args: argparse.Namespace) -> None:
    """`levels export`: the job's config, its ids checked against split.num_levels, sampled batch by batch."""
    job, level_ids = resolve(args.job), args.level_ids
    levels = _sampled_levels(
        sorted(set(level_ids)),
        job.work.levels_per_batch,
        functools.partial(sample_batch, job),
        progress=not args.no_progress,
    )
    _write_levels(levels, job.static, job.env_params, args.out or LEVELS_DIR / job.split.name.replace("/", "-"))


# ---------------------------------------------------------------------------------------------------- preview


@functools.partial(jax.jit, static_argnames=("static", "resolution"))
def _start_image(level: Level, static: StaticEnvParams, resolution: int) -> jax.Array:
    image = render_image(reset(level), static, resolution, PREVIEW_SUPERSAMPLE)
    return (image * 255.0 + 0.5).astype(np.uint8)


def preview_command(args: argparse.Namespace) -> None:
    """`levels preview`: load or sample the level, then write the PNG or play and write the GIF."""
    if args.level is not None:
        loaded = load_level(args.level)
        level, static, params, name = loaded.level, loaded.static, loaded.params, args.level.stem
    else:
        [(_, level)] = sampled_levels(args.size, args.seed, [args.index])
        static, params = StaticEnvParams.for_size(args.size), sample_params()
        name = f"{args.size}-seed{args.seed}-{LEVEL_FILE.format(args.index).removesuffix('.json')}"
    params, static = under_scheme(physics_scheme(args.physics), params, static)
    out = args.out or LEVELS_DIR / f"{name}.png"
    resolution = args.resolution or GIF_RESOLUTION
    if out.suffix == ".gif":
        states, _ = record_episode(
            level, params, static, Policy(args.policy), jax.random.key(args.policy_seed), args.steps
        )
        path = write_state_gif(jax.device_get(states), static, out, resolution=resolution)
    else:
        out.parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(np.asarray(_start_image(level, static, resolution))).save(out)
        path = out
    print(path)


# ----------------------------------------------------------------------------------------------------- import


def size_name(static: StaticEnvParams) -> str:
    """ "s", "m" or "l" if the slot counts are a Kinetix size, else the counts."""
    sim = static.sim
    counts = (sim.num_polygons, sim.num_circles, sim.num_joints, sim.num_thrusters)
    names = [name for name, sizes in KINETIX_SIZES.items() if sizes == counts]
    return names[0] if names else f"custom (polygons, circles, joints, thrusters) = {counts}"


def level_summary(level: Level, static: StaticEnvParams) -> tuple[list[str], list[str]]:
    """(lines describing the level, warnings about a task that cannot be solved or played)."""
    bodies, joints, thrusters = level.sim.bodies, level.sim.joints, level.sim.thrusters
    active = np.asarray(bodies.active)
    roles = np.asarray(level.task.roles)[active]
    fixed = np.asarray(bodies.inverse_mass)[active] == 0
    motors = np.asarray(joints.active) & np.asarray(joints.motor_on) & ~np.asarray(joints.is_fixed)
    role_counts = ", ".join(f"{np.sum(roles == role)} {role.name.lower()}" for role in Role)
    lines = [
        f"size: {size_name(static)}",
        f"active shapes: {int(active.sum())}, the {static.sim.num_reserved_static} boundaries included; roles: "
        f"{role_counts}; {int(fixed.sum()) - static.sim.num_reserved_static} fixed in place besides the boundaries",
        f"joints: {int(np.asarray(joints.active).sum())} active, {int(motors.sum())} with a motor on",
        f"thrusters: {int(np.asarray(thrusters.active).sum())} active",
    ]
    warnings = []
    for role in (Role.GREEN, Role.BLUE):
        if not np.any(roles == role):
            warnings.append(f"role: no active {role.name.lower()} shape, so no episode can succeed")
    if not motors.any() and not np.asarray(thrusters.active).any():
        warnings.append("joint.motor_on / thruster.active: no motor and no thruster, so no action does anything")
    return lines, warnings


def _leaves(value, path: str) -> Iterator[tuple[str, object]]:
    """(path, leaf) pairs of a JSON document; array entries (lists, or dicts keyed "0", "1", ...) as [i]."""
    if isinstance(value, dict):
        for key, item in value.items():
            yield from _leaves(item, f"{path}[{key}]" if key.isdigit() else f"{path}.{key}" if path else key)
    elif isinstance(value, list):
        for index, item in enumerate(value):
            yield from _leaves(item, f"{path}[{index}]")
    else:
        yield path, value


def _same_value(a, b) -> bool:
    """Equal as the file stores them: numbers compared at float32 (the precision levels are written at)."""
    numbers = (bool, int, float)
    if isinstance(a, numbers) and isinstance(b, numbers) and not isinstance(a, bool) and not isinstance(b, bool):
        return np.float32(a) == np.float32(b)
    return a == b


def normalisation_changes(raw: dict, normalised: dict) -> list[str]:
    """What writing the level changed, grouped by field with slot indices dropped: "<field>: N values changed"."""
    before, after = dict(_leaves(raw, "")), dict(_leaves(normalised, ""))
    changes = collections.Counter()
    for path in before.keys() | after.keys():
        if path not in after:
            kind = "dropped (not a field of the format)"
        elif path not in before:
            kind = "added (default value)"
        elif not _same_value(before[path], after[path]):
            kind = "changed"
        else:
            continue
        changes[(re.sub(r"\[\d+\]", "[]", path), kind)] += 1
    return [f"{field}: {count} values {kind}" for (field, kind), count in sorted(changes.items())]


def import_command(args: argparse.Namespace) -> None:
    """`levels import`: load the file (refusing a malformed one), print its summary and changes, write it."""
    loaded = load_level(args.level)
    normalised = level_to_dict(*loaded)
    lines, warnings = level_summary(loaded.level, loaded.static)
    changes = normalisation_changes(json.loads(args.level.read_text()), normalised)
    out = args.out or LEVELS_DIR / "imported" / args.level.name
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(normalised))
    print(f"{args.level}: valid Kinetix level")
    print("\n".join(f"  {line}" for line in lines))
    print("\n".join(f"  warning: {warning}" for warning in warnings) or "  no warnings")
    if changes:
        print(f"  normalised ({len(changes)} fields; the loader ignores or recomputes these):")
        print("\n".join(f"    {change}" for change in changes[:MAX_LISTED_CHANGES]))
        if len(changes) > MAX_LISTED_CHANGES:
            print(f"    ... and {len(changes) - MAX_LISTED_CHANGES} more fields")
    else:
        print("  already normalised")
    print(out)


def list_command(args: argparse.Namespace) -> None:
    """`levels list`: the bundled level names of each size (or of --size), then their count."""
    sizes = BUNDLED_SIZES if args.size is None else (args.size,)
    for size in sizes:
        names = list_levels(size)
        print("\n".join(names))
        print(f"{len(names)} levels ({size})")
