"""The `kforge` command line: one subcommand per entry point, each parsing its own arguments.

A subcommand's module is imported only when it runs, so `kforge --help` and a subcommand's `--help` answer without
importing JAX or Ray. Every subcommand ends with one of the exit codes below, reports errors in one line (the
traceback only with `--debug`), and takes config overrides as positional `key=value` arguments.

Public surface: `main` (the `kforge` script, `python -m kforge`). The subcommand modules share the exit codes,
`EXIT_CODES_HELP`, `add_common_options`, `InputError`, `require_dataset`, `load_config_or_exit` and `fail` from here.
"""

from __future__ import annotations

import _thread
import argparse
import atexit
import gc
import importlib
import os
import signal
import sys
import threading
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import NoReturn, TypeVar

__all__ = ["main"]

Config = TypeVar("Config")

EXIT_OK = 0
"""Success."""
EXIT_DATA = 1
"""The data has a problem (verification failed, unreadable dataset), or the job is incomplete."""
EXIT_USAGE = 2
"""A usage, config or input-file error (argparse's own code for bad arguments)."""
EXIT_INTERRUPTED = 130
"""Interrupted by SIGINT (Ctrl-C) or SIGTERM (128 + SIGINT, as shells report it)."""

INTERRUPT_AGAIN_AFTER_SECONDS = 0.01
"""[s] Delay before a Ctrl-C that came inside a garbage-collector callback is delivered again (`_interrupt`)."""

EXIT_CODES_HELP = (
    "exit codes: 0 success; 1 the data has a problem or the job is incomplete; 2 usage, config or input-file "
    "error; 130 interrupted (SIGINT/SIGTERM). --debug shows the traceback of an error, --verbose shows "
    "third-party logs (Ray, wandb) on the terminal."
)
"""The epilog of every subcommand's --help."""

DEBUG_OPTION = "--debug"
HELP_OPTIONS = {"-h", "--help"}
VERBOSE_OPTION = "--verbose"

COMMANDS: dict[str, tuple[str, str]] = {
    "run": ("generate (or resume, or grow) a dataset from a release split or a job config", "kforge.pipeline.cli.run"),
    "verify": ("check every shard of a dataset against its commit records (--repair)", "kforge.pipeline.cli.verify"),
    "stats": ("write a dataset card: counts, bytes, timings, config and plots", "kforge.pipeline.cli.stats"),
    "export": ("write a dataset as Kinetix-Offline zarr v2 shards (--format kinetix)", "kforge.pipeline.cli.export"),
    "levels": ("list, sample, preview, import and export Kinetix level files", "kforge.pipeline.cli.levels"),
    "bc": ("train a behaviour-cloning policy on a dataset (train), resumable", "kforge.pipeline.cli.bc"),
    "evaluate": (
        "success rates of a BC policy beside no-op and random on seen, unseen and hand levels",
        "kforge.pipeline.cli.evaluate",
    ),
    "render": ("play a Kinetix level with a simple policy and write a GIF", "kforge.pipeline.cli.render"),
    "demo": ("simulate a small engine scene and write it as a GIF", "kforge.pipeline.cli.demo"),
}
"""Subcommand name -> (help line, module whose `main(argv, prog)` parses the remaining arguments)."""

OWN_PARSERS = ("kforge.pipeline.cli.",)
"""Subcommand modules whose parsers take --debug and --verbose themselves (`add_common_options`); the others
never see these two options."""

USAGE_ERRORS = ("InputError", "ConfigError", "ResumeRefused", "LevelFileError", "ExportTargetExists", "OSError")
"""Exception classes (by name, so that this module imports nothing heavy) that are the caller's mistake: exit 2."""
DATA_ERRORS = ("DatasetError",)
"""Exception classes that report a problem of the data: exit 1."""


ENV_SIZES = ("s", "m", "l")
"""Kinetix's env sizes (engine.KINETIX_SIZES, env.BUNDLED_SIZES), named here so that parsing imports nothing heavy."""
PHYSICS_SCHEME_NAMES = ("kforge", "kinetix")
"""The engine's physics schemes (engine.PHYSICS_SCHEMES), the values of --physics."""
PLAY_PHYSICS_SCHEME = "kinetix"
"""The scheme `render` and `levels preview` play under unless --physics names another: Kinetix's play, as the data
and its evaluation (the engine's API default, kforge, stays a choice)."""
POLICY_NAMES = ("noop", "uniform_random")
"""The simple policies a level can be played with (env.Policy's values), the first the default."""

DATASET_METADATA = "data/zarr.json"
"""The file every local dataset holds (pipeline.storage's GROUP_METADATA, named here so that checking a path imports
nothing heavy)."""
URL_MARK = "://"
"""What a dataset location on object storage (s3://, gs://) holds; those are checked when opened."""


class InputError(ValueError):
    """An argument names something that is not there or not of the kind asked for: exit 2."""


def require_dataset(location: str) -> str:
    """`location`; a location that holds no dataset ends the command with a one-line `InputError` (exit 2): a local
    path before anything heavy is imported, a URL once its store answers (an unreadable store is left to the
    command)."""
    if URL_MARK in location:
        from kforge.pipeline.storage import open_store

        if not open_store(location).exists(DATASET_METADATA):
            raise fail(InputError(f"{location}: not a dataset (no {DATASET_METADATA})"))
        return location
    path = Path(location)
    if not path.exists():
        raise fail(InputError(f"{location}: no such dataset directory"))
    if not (path / DATASET_METADATA).is_file():
        raise fail(InputError(f"{location}: not a dataset (no {DATASET_METADATA})"))
    return location


def load_config_or_exit(load: Callable[[], Config], debug: bool) -> Config:
    """`load()`'s config; its `ConfigError` ends the command in one line with exit 2 (raised as is with --debug).
    Loading and checking a config imports nothing heavy, so these errors come before JAX is imported."""
    from kforge.pipeline.generation import ConfigError

    try:
        return load()
    except ConfigError as error:
        if debug:
            raise
        raise fail(error) from error


def add_common_options(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add --debug and --verbose, and the exit codes as the help's epilog."""
    parser.epilog = EXIT_CODES_HELP
    parser.add_argument(DEBUG_OPTION, action="store_true", help="show the traceback of an error")
    parser.add_argument(VERBOSE_OPTION, action="store_true", help="show third-party logs (Ray, wandb) on the terminal")
    return parser


def exit_code(error: BaseException) -> int:
    """The exit code of an error that ended a subcommand: the first of its classes, most specific first, that
    `USAGE_ERRORS` or `DATA_ERRORS` names; 1 for anything else."""
    if isinstance(error, KeyboardInterrupt):
        return EXIT_INTERRUPTED
    for cls in type(error).__mro__:
        if cls.__name__ in USAGE_ERRORS:
            return EXIT_USAGE
        if cls.__name__ in DATA_ERRORS:
            return EXIT_DATA
    return EXIT_DATA


def fail(error: BaseException, code: int | None = None) -> SystemExit:
    """Print `error` as one line on stderr and return the SystemExit to raise (`raise fail(error) from error`)."""
    text = str(error).strip()
    message = text.splitlines()[0] if text else type(error).__name__
    known = {cls.__name__ for cls in type(error).__mro__} & set(USAGE_ERRORS + DATA_ERRORS)
    if not known:
        message = f"{type(error).__name__}: {message} (run with {DEBUG_OPTION} for the traceback)"
    print(f"error: {message}", file=sys.stderr)
    return SystemExit(exit_code(error) if code is None else code)


def _interrupt(signum, frame) -> None:
    """SIGINT and SIGTERM handler of the kforge process: KeyboardInterrupt where the main flow runs; inside a
    garbage-collector callback (JAX has one), where Python would print and drop it, the signal is delivered again
    shortly after."""
    callbacks = {getattr(callback, "__code__", None) for callback in gc.callbacks}
    while frame is not None:
        if frame.f_code in callbacks:
            again = threading.Timer(INTERRUPT_AGAIN_AFTER_SECONDS, _thread.interrupt_main)
            again.daemon = True
            again.start()
            return
        frame = frame.f_back
    raise KeyboardInterrupt


def _interrupted(error: BaseException | None) -> bool:
    """Whether `error` is a Ctrl-C, or was raised while handling one (numpy, for one, turns a Ctrl-C during its
    import into an ImportError)."""
    while error is not None:
        if isinstance(error, KeyboardInterrupt):
            return True
        error = error.__cause__ or error.__context__
    return False


def _end_interrupted_process() -> NoReturn:
    """End the kforge process with EXIT_INTERRUPTED after its exit handlers ran. (An interpreter whose Ctrl-C
    passed through code run by a C extension kills itself with SIGINT at exit, whatever the exit code asked for.)"""
    atexit._run_exitfuncs()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(EXIT_INTERRUPTED)


def main(argv: Sequence[str] | None = None) -> None:
    """Run `kforge <command> [arguments]`; `kforge <command> --help` shows the command's own options. Without
    `argv` (the `kforge` program itself) an interrupted command always ends the process with EXIT_INTERRUPTED."""
    own_process = argv is None
    if own_process and signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        signal.signal(signal.SIGINT, _interrupt)
    if own_process and signal.getsignal(signal.SIGTERM) is signal.SIG_DFL:
        signal.signal(signal.SIGTERM, _interrupt)  # from the start: a SIGTERM while JAX imports ends as Ctrl-C does
    try:
        try:
            _run(argv)
        except KeyboardInterrupt:  # before a subcommand runs (while arguments are parsed)
            print("interrupted", file=sys.stderr)
            raise SystemExit(EXIT_INTERRUPTED) from None
    except SystemExit as stop:
        if own_process and stop.code == EXIT_INTERRUPTED:
            _end_interrupted_process()
        raise


def _run(argv: Sequence[str] | None) -> None:
    """Parse the subcommand, run it, and turn what ends it into an exit code and a one-line error."""
    parser = argparse.ArgumentParser(prog="kforge", description=__doc__.splitlines()[0], epilog=EXIT_CODES_HELP)
    subcommands = parser.add_subparsers(dest="command", required=True, metavar="command")
    for name, (help_line, _) in COMMANDS.items():
        subcommands.add_parser(name, help=help_line, add_help=False)
    args, rest = parser.parse_known_args(argv)
    _, module = COMMANDS[args.command]
    debug = DEBUG_OPTION in rest
    if not module.startswith(OWN_PARSERS):
        rest = [arg for arg in rest if arg not in (DEBUG_OPTION, VERBOSE_OPTION)]
    try:
        importlib.import_module(module).main(rest, prog=f"{parser.prog} {args.command}")
    except SystemExit as stop:
        if stop.code in (0, None) and not module.startswith(OWN_PARSERS) and HELP_OPTIONS & set(rest):
            print(f"\n{EXIT_CODES_HELP}")  # the same epilog as the subcommands with parsers of their own
        raise
    except GeneratorExit:
        raise
    except BaseException as error:
        if debug:
            raise
        if _interrupted(error):
            print("interrupted", file=sys.stderr)
            raise SystemExit(EXIT_INTERRUPTED) from None
        raise fail(error) from None
