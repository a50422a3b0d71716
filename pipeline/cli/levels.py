"""`kforge levels`: sample, preview, import and export levels as Kinetix level JSON files.

- `sample`: levels START..START+N-1 of a (size, seed) pair: the levels a split with that size and seed trains (level
  i's key derives from (seed, i) as in pipeline/generation/level_batch.py), so `--seed 0 --size s` gives split
  1M/s's levels.
- `preview`: a level file, or a sampled level, as a PNG of its start or a GIF of an episode under a simple policy.
- `import`: check a Kinetix level JSON (each problem names its field), report what it holds and what
  normalisation changed, and write it in the form this project writes (`env.level_files.save_level`), which loads
  back exactly.
- `export`: levels of a split config by level id, exactly as a run of that config samples them (same batches);
  config overrides are positional `key=value` arguments, as for `kforge run`. The config may be a dataset's (a
  folder, or an `s3://`, `gs://` URL, read through the dataset store layer); the level files are written to a
  local folder, where level tools (`preview`, `render`, Kinetix's level loader) open them.
"""

from __future__ import annotations

import argparse
import collections
import functools
import json
import re
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path

import jax
import numpy as np
from PIL import Image
from tqdm import tqdm

from engine import DEFAULT_PHYSICS_SCHEME, KINETIX_SIZES, PHYSICS_SCHEMES, physics_scheme
from env import (
    BUNDLED_SIZES,
    GIF_FPS,
    GIF_RESOLUTION,
    EnvParams,
    Level,
    LevelFileError,
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
from pipeline.cli import EXIT_CODES_HELP, add_common_options, fail
from pipeline.generation import ConfigError, EnvSection, KeyPurpose, environment, level_keys, load_config, sample_batch

LEVELS_DIR = Path("outputs") / "levels"
"""Default parent folder of written levels and previews."""

LEVEL_FILE = "level-{:07d}.json"
"""File name of level i (7 digits: the largest release split has 5.98M levels)."""

SAMPLE_CHUNK = 64
"""Levels per sampler call of `sample` (one compiled shape; the last chunk's extra levels are discarded)."""

PREVIEW_SUPERSAMPLE = 2
"""Samples per pixel side of a PNG preview (antialiasing)."""

DEFAULT_GIF_STEPS = 256
"""[env steps] length of a GIF preview: one full episode."""

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
    """Write levels --start .. --start + --num - 1 of (--size, --seed) as Kinetix JSON files."""
    if args.num < 1 or args.start < 0:
        raise SystemExit("error: --num must be >= 1 and --start >= 0")
    out = args.out or LEVELS_DIR / f"{args.size}-seed{args.seed}"
    ids = range(args.start, args.start + args.num)
    levels = sampled_levels(args.size, args.seed, ids, progress=not args.no_progress)
    _write_levels(levels, StaticEnvParams.for_size(args.size), sample_params(), out)


def export_command(args: argparse.Namespace) -> None:
    """Write the given level ids of a split config as Kinetix JSON files, sampled in the job's own level batches."""
    overrides = [item for item in args.items if "=" in item] + (args.override or [])
    try:
        level_ids = [int(item) for item in args.items if "=" not in item]
    except ValueError as error:
        item = error.args[0].split(": ", 1)[-1]
        raise ConfigError(f"{item} is neither a level id nor a key=value override") from None
    if not level_ids:
        raise ConfigError("no level ids given (e.g. kforge levels export 1M/s 0 1 2)")
    job = load_config(args.config, overrides, scale=args.scale)
    outside = [level_id for level_id in level_ids if not 0 <= level_id < job.split.num_levels]
    if outside:
        raise ConfigError(
            f"level ids {outside} are outside split {job.split.name} (split.num_levels = {job.split.num_levels})"
        )
    params, static = environment(job)
    levels = _sampled_levels(
        sorted(set(level_ids)),
        job.work.levels_per_batch,
        functools.partial(sample_batch, job),
        progress=not args.no_progress,
    )
    _write_levels(levels, static, params, args.out or LEVELS_DIR / job.split.name.replace("/", "-"))


# ---------------------------------------------------------------------------------------------------- preview


@functools.partial(jax.jit, static_argnames=("static", "resolution"))
def _start_image(level: Level, static: StaticEnvParams, resolution: int) -> jax.Array:
    image = render_image(reset(level), static, resolution, PREVIEW_SUPERSAMPLE)
    return (image * 255.0 + 0.5).astype(np.uint8)


def preview_command(args: argparse.Namespace) -> None:
    """Render a level file or a sampled level: PNG of the start state, or GIF of an episode (by --out's suffix)."""
    sampled = (args.size, args.seed, args.index)
    if (args.level is None) == all(value is None for value in sampled):
        raise SystemExit("error: give a LEVEL file, or --size, --seed and --index of a sampled level (not both)")
    if args.out is not None and args.out.suffix not in (".png", ".gif"):
        raise SystemExit(f"error: --out must end in .png (start state) or .gif (episode), got {args.out}")
    if args.steps < 1 or args.resolution < 1:
        raise SystemExit("error: --steps and --resolution must be >= 1")
    if args.level is not None:
        loaded = load_level(args.level)
        level, static, params, name = loaded.level, loaded.static, loaded.params, args.level.stem
    else:
        if any(value is None for value in sampled) or args.index < 0:
            raise SystemExit("error: a sampled level needs all of --size, --seed and --index (>= 0)")
        [(_, level)] = sampled_levels(args.size, args.seed, [args.index])
        static, params = StaticEnvParams.for_size(args.size), sample_params()
        name = f"{args.size}-seed{args.seed}-{LEVEL_FILE.format(args.index).removesuffix('.json')}"
    params, static = under_scheme(physics_scheme(args.physics), params, static)
    out = args.out or LEVELS_DIR / f"{name}.png"
    if out.suffix == ".gif":
        states, _ = record_episode(
            level, params, static, Policy(args.policy), jax.random.key(args.policy_seed), args.steps
        )
        path = write_state_gif(jax.device_get(states), static, out, fps=GIF_FPS, resolution=args.resolution)
    else:
        out.parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(np.asarray(_start_image(level, static, args.resolution))).save(out)
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
    """Check a Kinetix level file, report its content, and write it normalised."""
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
    """Print the names of the hand-designed Kinetix levels that ship with kforge, one a line, with a count per size;
    any command that takes a level file also takes such a name (e.g. `kforge render l/h4_cartpole`)."""
    sizes = BUNDLED_SIZES if args.size is None else (args.size,)
    for size in sizes:
        names = list_levels(size)
        print("\n".join(names))
        print(f"{len(names)} levels ({size})")


# ------------------------------------------------------------------------------------------------- arguments


_SAMPLE_NOTE = (
    "Level i comes from the key (seed, i), as in a generation run, so --size s --seed 0 writes the first levels of "
    "split 1M/s (configs/splits/1M/s.yaml). Files hold the training env params (dense_reward_scale 0.2)."
)
_IMPORT_NOTE = (
    "A malformed file is refused with the path of the offending field (e.g. env_state.polygon[4].role). A valid one "
    "is summarised (size, shapes by role, motors, thrusters), with warnings for a task that cannot be solved, and "
    "written as this project writes levels: contact caches empty, collision matrix recomputed from the joints, "
    "numbers at float32, unmodelled parameters at Kinetix's defaults."
)


def _parser(prog: str | None) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=prog, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.epilog = EXIT_CODES_HELP
    commands = parser.add_subparsers(dest="command", required=True, metavar="subcommand")

    listing = commands.add_parser(
        "list", help="name the bundled hand-designed Kinetix levels", description=list_command.__doc__
    )
    listing.add_argument("--size", choices=list(BUNDLED_SIZES), help="only levels of this size")
    listing.set_defaults(run=list_command)

    sample = commands.add_parser(
        "sample", help="sample levels of a size from a seed", description=sample_command.__doc__ + " " + _SAMPLE_NOTE
    )
    sample.add_argument("--size", choices=sorted(KINETIX_SIZES), required=True, help="env size")
    sample.add_argument("--seed", type=int, required=True, help="split seed (configs/splits/*: split.seed)")
    sample.add_argument("--num", type=int, required=True, help="number of levels")
    sample.add_argument("--start", type=int, default=0, help="first level id (default 0)")
    sample.add_argument(
        "--out", type=Path, help="folder for level-<id>.json (default outputs/levels/<size>-seed<seed>)"
    )
    sample.add_argument("--no-progress", action="store_true", help="no progress bar")
    sample.set_defaults(run=sample_command)

    preview = commands.add_parser(
        "preview", help="render a level to PNG (start) or GIF (episode)", description=preview_command.__doc__
    )
    preview.add_argument(
        "level",
        type=Path,
        nargs="?",
        help="level JSON file or bundled name (s/h4_thrust_aim), or --size/--seed/--index",
    )
    preview.add_argument("--size", choices=sorted(KINETIX_SIZES), help="sampled level: env size")
    preview.add_argument("--seed", type=int, help="sampled level: split seed")
    preview.add_argument("--index", type=int, help="sampled level: level id")
    preview.add_argument("--out", type=Path, help="output .png or .gif (default outputs/levels/<name>.png)")
    preview.add_argument("--resolution", type=int, default=GIF_RESOLUTION, help="image side in pixels (default 500)")
    preview.add_argument("--steps", type=int, default=DEFAULT_GIF_STEPS, help="GIF: env steps to play (default 256)")
    preview.add_argument("--policy", choices=[p.value for p in Policy], default=Policy.NOOP.value, help="GIF: policy")
    preview.add_argument("--policy-seed", type=int, default=0, help="GIF: seed of the random policy (default 0)")
    preview.add_argument(
        "--physics",
        choices=sorted(PHYSICS_SCHEMES),
        default=DEFAULT_PHYSICS_SCHEME,
        help=f"GIF: physics scheme, as a job's env.physics (default {DEFAULT_PHYSICS_SCHEME})",
    )
    preview.set_defaults(run=preview_command)

    importer = commands.add_parser(
        "import",
        help="check a Kinetix level JSON and write it normalised",
        description=import_command.__doc__ + " " + _IMPORT_NOTE,
    )
    importer.add_argument("level", type=Path, help="Kinetix level JSON file")
    importer.add_argument("--out", type=Path, help="normalised file (default outputs/levels/imported/<name>)")
    importer.set_defaults(run=import_command)

    export = commands.add_parser(
        "export", help="write levels of a split config by id", description=export_command.__doc__
    )
    export.add_argument(
        "config",
        help="job config, e.g. configs/splits/1M/s.yaml, or a dataset (folder, s3:// or gs:// URL) or its config.yaml",
    )
    export.add_argument(
        "items",
        nargs="+",
        metavar="ID|KEY=VALUE",
        help="level ids in [0, split.num_levels) and config overrides as key=value, in any order (as for kforge run)",
    )
    export.add_argument("--scale", help="scale preset, as for kforge run (sets split.num_levels, the id range)")
    export.add_argument("--override", action="append", metavar="KEY=VALUE", help="deprecated: give KEY=VALUE alone")
    export.add_argument("--out", type=Path, help="folder for level-<id>.json (default outputs/levels/<split>)")
    export.add_argument("--no-progress", action="store_true", help="no progress bar")
    export.set_defaults(run=export_command)
    for subcommand in commands.choices.values():
        add_common_options(subcommand)
    return parser


def main(argv: Sequence[str] | None = None, prog: str | None = None) -> None:
    """`kforge levels <subcommand> ...`; `kforge levels <subcommand> --help` explains each."""
    args = _parser(prog).parse_args(argv)
    try:
        args.run(args)
    except (LevelFileError, ConfigError, OSError) as error:
        if args.debug:
            raise
        raise fail(error) from error
