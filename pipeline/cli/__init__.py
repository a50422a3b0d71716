"""The `kforge` command line: one subcommand per entry point, each parsing its own arguments.

A subcommand's module is imported only when it runs, so `kforge --help` and a subcommand's `--help` answer without
importing JAX or Ray.
"""

from __future__ import annotations

import argparse
import importlib
from collections.abc import Sequence

COMMANDS: dict[str, tuple[str, str]] = {
    "run": ("generate (or resume) a dataset from a release split or a job config", "pipeline.cli.run"),
    "verify": ("check every shard of a dataset against its commit records", "pipeline.cli.verify"),
    "stats": ("write a dataset card: counts, bytes, timings, config and plots", "pipeline.cli.stats"),
    "export": ("write a dataset as Kinetix-Offline zarr v2 shards (--format kinetix)", "pipeline.cli.export"),
    "levels": ("list, sample, preview, import and export Kinetix level files", "pipeline.cli.levels"),
    "render": ("play a Kinetix level with a simple policy and write a GIF", "env.play"),
    "demo": ("simulate a small engine scene and write it as a GIF", "engine.demo"),
}
"""Subcommand name -> (help line, module whose `main(argv, prog)` parses the remaining arguments)."""


def main(argv: Sequence[str] | None = None) -> None:
    """Run `kforge <command> [arguments]`; `kforge <command> --help` shows the command's own options."""
    parser = argparse.ArgumentParser(prog="kforge", description=__doc__.splitlines()[0])
    subcommands = parser.add_subparsers(dest="command", required=True, metavar="command")
    for name, (help_line, _) in COMMANDS.items():
        subcommands.add_parser(name, help=help_line, add_help=False)
    args, rest = parser.parse_known_args(argv)
    _, module = COMMANDS[args.command]
    importlib.import_module(module).main(rest, prog=f"{parser.prog} {args.command}")
