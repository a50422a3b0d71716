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
from collections.abc import Sequence
from pathlib import Path

from kforge.pipeline.cli import (
    ENV_SIZES,
    EXIT_CODES_HELP,
    EXIT_USAGE,
    PHYSICS_SCHEME_NAMES,
    PLAY_PHYSICS_SCHEME,
    POLICY_NAMES,
    InputError,
    add_common_options,
    exit_code,
    fail,
)

DEFAULT_GIF_STEPS = 256
"""[env steps] length of a GIF preview: one full episode."""

PREVIEW_SUFFIXES = (".png", ".gif")
"""What `preview --out` may end in: a PNG of the start state, or a GIF of an episode."""

_LIST_DESCRIPTION = (
    "Print the names of the hand-designed Kinetix levels that ship with kforge, one a line, with a count per size; "
    "any command that takes a level file also takes such a name (e.g. `kforge render l/h4_cartpole`)."
)
_SAMPLE_DESCRIPTION = (
    "Write levels --start .. --start + --num - 1 of (--size, --seed) as Kinetix JSON files. Level i comes from the "
    "key (seed, i), as in a generation run, so --size s --seed 0 writes the first levels of split 1M/s "
    "(configs/splits/1M/s.yaml). Files hold the training env params (dense_reward_scale 0.2)."
)
_PREVIEW_DESCRIPTION = (
    "Render a level file or a sampled level: PNG of the start state, or GIF of an episode (by --out's suffix)."
)
_IMPORT_DESCRIPTION = (
    "Check a Kinetix level file, report its content, and write it normalised. A malformed file is refused with the "
    "path of the offending field (e.g. env_state.polygon[4].role). A valid one is summarised (size, shapes by role, "
    "motors, thrusters), with warnings for a task that cannot be solved, and written as this project writes levels: "
    "contact caches empty, collision matrix recomputed from the joints, numbers at float32, unmodelled parameters at "
    "Kinetix's defaults."
)
_EXPORT_DESCRIPTION = (
    "Write the given level ids of a split config as Kinetix JSON files, sampled in the job's own level batches."
)


def _parser(prog: str | None) -> tuple[argparse.ArgumentParser, dict[str, argparse.ArgumentParser]]:
    """The `levels` parser and its subcommands' parsers by name."""
    parser = argparse.ArgumentParser(
        prog=prog, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.epilog = EXIT_CODES_HELP
    commands = parser.add_subparsers(dest="command", required=True, metavar="subcommand")

    listing = commands.add_parser(
        "list", help="name the bundled hand-designed Kinetix levels", description=_LIST_DESCRIPTION
    )
    listing.add_argument("--size", choices=ENV_SIZES, help="only levels of this size")

    _add_sample(commands)
    _add_preview(commands)
    importer = commands.add_parser(
        "import", help="check a Kinetix level JSON and write it normalised", description=_IMPORT_DESCRIPTION
    )
    importer.add_argument("level", type=Path, help="Kinetix level JSON file")
    importer.add_argument("--out", type=Path, help="normalised file (default outputs/levels/imported/<name>)")

    _add_export(commands)
    for subcommand in commands.choices.values():
        add_common_options(subcommand)
    return parser, commands.choices


def _add_sample(commands) -> None:
    """The `sample` subcommand's parser."""
    sample = commands.add_parser("sample", help="sample levels of a size from a seed", description=_SAMPLE_DESCRIPTION)
    sample.add_argument("--size", choices=ENV_SIZES, required=True, help="env size")
    sample.add_argument("--seed", type=int, required=True, help="split seed (configs/splits/*: split.seed)")
    sample.add_argument("--num", type=int, required=True, help="number of levels")
    sample.add_argument("--start", type=int, default=0, help="first level id (default 0)")
    sample.add_argument(
        "--out", type=Path, help="folder for level-<id>.json (default outputs/levels/<size>-seed<seed>)"
    )
    sample.add_argument("--no-progress", action="store_true", help="no progress bar")


def _add_preview(commands) -> None:
    """The `preview` subcommand's parser."""
    preview = commands.add_parser(
        "preview", help="render a level to PNG (start) or GIF (episode)", description=_PREVIEW_DESCRIPTION
    )
    preview.add_argument(
        "level",
        type=Path,
        nargs="?",
        help="level JSON file or bundled name (s/h4_thrust_aim), or --size/--seed/--index",
    )
    preview.add_argument("--size", choices=ENV_SIZES, help="sampled level: env size")
    preview.add_argument("--seed", type=int, help="sampled level: split seed")
    preview.add_argument("--index", type=int, help="sampled level: level id")
    preview.add_argument("--out", type=Path, help="output .png or .gif (default outputs/levels/<name>.png)")
    preview.add_argument("--resolution", type=int, help="image side in pixels (default 500)")
    preview.add_argument("--steps", type=int, default=DEFAULT_GIF_STEPS, help="GIF: env steps to play (default 256)")
    preview.add_argument("--policy", choices=POLICY_NAMES, default=POLICY_NAMES[0], help="GIF: policy")
    preview.add_argument("--policy-seed", type=int, default=0, help="GIF: seed of the random policy (default 0)")
    preview.add_argument(
        "--physics",
        choices=PHYSICS_SCHEME_NAMES,
        default=PLAY_PHYSICS_SCHEME,
        help=f"GIF: physics scheme, as a job's env.physics (default {PLAY_PHYSICS_SCHEME}: Kinetix's play)",
    )


def _add_export(commands) -> None:
    """The `export` subcommand's parser."""
    export = commands.add_parser("export", help="write levels of a split config by id", description=_EXPORT_DESCRIPTION)
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


def _check(args: argparse.Namespace, chosen: argparse.ArgumentParser) -> None:
    """Refuse, before anything heavy is imported, what the arguments alone show to be wrong (exit 2), and load
    `export`'s job config (`ConfigError`); `chosen` is the subcommand's parser."""
    if args.command == "sample" and (args.num < 1 or args.start < 0):
        chosen.error(f"--num must be >= 1 and --start >= 0, got --num {args.num} --start {args.start}")
    if args.command == "preview":
        sampled = (args.size, args.seed, args.index)
        if (args.level is None) == all(value is None for value in sampled):
            chosen.error("give a LEVEL file, or --size, --seed and --index of a sampled level (not both)")
        if args.level is None and (any(value is None for value in sampled) or args.index < 0):
            chosen.error("a sampled level needs all of --size, --seed and --index (>= 0)")
        if args.out is not None and args.out.suffix not in PREVIEW_SUFFIXES:
            chosen.error(f"--out must end in .png (start state) or .gif (episode), got {args.out}")
        if args.steps < 1 or (args.resolution is not None and args.resolution < 1):
            chosen.error("--steps and --resolution must be >= 1")
    if args.command == "import" and not args.level.is_file():
        raise fail(InputError(f"{args.level}: no such level file"))
    if args.command == "export":
        args.overrides = [item for item in args.items if "=" in item] + (args.override or [])
        numbers = [item for item in args.items if "=" not in item]
        for item in numbers:
            if not item.lstrip("-").isdigit():
                raise fail(InputError(f"{item!r} is neither a level id nor a key=value override"))
        if not numbers:
            raise fail(InputError("no level ids given (e.g. kforge levels export 1M/s 0 1 2)"))
        args.level_ids = [int(item) for item in numbers]
        from kforge.pipeline.generation import ConfigError, load_config

        args.job = load_config(args.config, args.overrides, scale=args.scale)
        split = args.job.split
        outside = [level_id for level_id in args.level_ids if not 0 <= level_id < split.num_levels]
        if outside:
            raise ConfigError(
                f"level ids {outside} are outside split {split.name} (split.num_levels = {split.num_levels})"
            )


def main(argv: Sequence[str] | None = None, prog: str | None = None) -> None:
    """`kforge levels <subcommand> ...`; `kforge levels <subcommand> --help` explains each."""
    parser, subcommands = _parser(prog)
    args = parser.parse_args(argv)
    try:
        _check(args, subcommands[args.command])
        from kforge.pipeline.cli import level_commands

        getattr(level_commands, f"{args.command}_command")(args)
    except Exception as error:  # the caller's mistakes (a level file, a config) end here in one line; others go up
        if args.debug or exit_code(error) != EXIT_USAGE:
            raise
        raise fail(error) from error
