"""`kforge run SPLIT|CONFIG [key=value ...]`: generate a split's dataset; re-running on the same directory resumes."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence

import configs


def main(argv: Sequence[str] | None = None, prog: str | None = None) -> None:
    """Run CONFIG (a release split such as 1M/s, or a job YAML) at a --scale with `key=value` overrides; resumes in
    output_dir."""
    parser = argparse.ArgumentParser(prog=prog, description=main.__doc__)
    parser.add_argument("config", help=f"release split ({', '.join(configs.split_names())}) or a job YAML file")
    parser.add_argument("overrides", nargs="*", help="dotlist overrides, e.g. split.num_levels=32 ray.num_workers=2")
    parser.add_argument(
        "--scale", help=f"scale preset applied over CONFIG: {', '.join(configs.scale_names())}, or a YAML path"
    )
    parser.add_argument(
        "--print-config", action="store_true", help="print the resolved config (each key's type and meaning) and exit"
    )
    parser.add_argument("--max-batches", type=int, help="stop after this many level batches (resume later)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    args = parser.parse_intermixed_args(argv)  # overrides may follow the options

    from pipeline.generation import ConfigError, ResumeRefused, load_config, run_job, to_yaml
    from pipeline.storage import DatasetError

    try:
        job = load_config(args.config, args.overrides, scale=args.scale)
        if args.print_config:
            print(to_yaml(job), end="")
            return
        summary = run_job(job, max_batches=args.max_batches, show_progress=not args.no_progress)
    except (ConfigError, ResumeRefused, DatasetError) as error:
        print(f"error: {error}", file=sys.stderr)
        raise SystemExit(2) from error
    print(json.dumps(summary, indent=1))
    if summary["abandoned_shards"]:
        raise SystemExit(1)
