"""The `kforge` command line: one subcommand per entry point, each forwarding its own arguments."""

from __future__ import annotations

import argparse
from collections.abc import Callable, Sequence

import engine.demo
import env.play
import pipeline.export
import pipeline.levels_cli
import pipeline.run
import pipeline.stats
import pipeline.verify

COMMANDS: dict[str, tuple[str, Callable[..., None]]] = {
    "demo": ("simulate a small engine scene and write it as a GIF", engine.demo.main),
    "run": ("generate (or resume) a dataset from a job config", pipeline.run.main),
    "verify": ("check every shard of a dataset against its manifest", pipeline.verify.main),
    "render": ("play a Kinetix level file with a simple policy and write a GIF", env.play.main),
    "export": ("write a dataset as Kinetix-Offline zarr v2 shards (--format kinetix)", pipeline.export.main),
    "stats": ("write a dataset card: counts, bytes, timings, config and plots", pipeline.stats.main),
    "levels": ("sample, preview, import and export Kinetix level files", pipeline.levels_cli.main),
}
"""Subcommand name -> (help line, `main(argv, prog)` that parses the remaining arguments)."""


def main(argv: Sequence[str] | None = None) -> None:
    """Run `kforge <command> [arguments]`; `kforge <command> --help` shows the command's own options."""
    parser = argparse.ArgumentParser(prog="kforge", description=__doc__)
    subcommands = parser.add_subparsers(dest="command", required=True, metavar="command")
    for name, (help_line, _) in COMMANDS.items():
        subcommands.add_parser(name, help=help_line, add_help=False)
    args, rest = parser.parse_known_args(argv)
    _, run = COMMANDS[args.command]
    run(rest, prog=f"{parser.prog} {args.command}")
