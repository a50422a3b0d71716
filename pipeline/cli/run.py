"""`kforge run SPLIT|CONFIG [key=value ...]`: generate a split's dataset; re-running on the same directory resumes
it, and a larger `split.num_levels` grows it."""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from collections.abc import Sequence

from kforge import configs
from kforge.pipeline.cli import EXIT_DATA, EXIT_INTERRUPTED, add_common_options, fail, load_config_or_exit


def main(argv: Sequence[str] | None = None, prog: str | None = None) -> None:
    """Run CONFIG (a release split such as 1M/s, or a job YAML) at a --scale with `key=value` overrides; resumes in
    output_dir (Ctrl-C or SIGTERM stops it, keeping every committed level batch), and grows it when
    split.num_levels is raised. Ends with a short summary (--json: the machine-readable one)."""
    parser = argparse.ArgumentParser(prog=prog, description=main.__doc__)
    parser.add_argument(
        "config",
        help=f"release split ({', '.join(configs.split_names())}), a job YAML file, or a dataset to continue "
        "(a folder, s3:// or gs:// URL holding config.yaml)",
    )
    parser.add_argument("overrides", nargs="*", help="dotlist overrides, e.g. split.num_levels=32 ray.num_workers=2")
    parser.add_argument(
        "--scale", help=f"scale preset applied over CONFIG: {', '.join(configs.scale_names())}, or a YAML path"
    )
    parser.add_argument(
        "--print-config", action="store_true", help="print the resolved config (each key's type and meaning) and exit"
    )
    parser.add_argument("--max-batches", type=int, help="commit at most this many level batches, then stop")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--json", action="store_true", help="end with the summary as JSON (for scripts)")
    args = add_common_options(parser).parse_intermixed_args(argv)  # overrides may follow the options
    if args.max_batches is not None and args.max_batches < 1:
        parser.error(f"--max-batches must be >= 1, got {args.max_batches}")

    from kforge.pipeline.generation import load_config, to_yaml

    job = load_config_or_exit(lambda: load_config(args.config, args.overrides, scale=args.scale), args.debug)
    if args.print_config:
        print(to_yaml(job), end="")
        return

    from kforge.pipeline.generation import JobInterrupted, ResumeRefused, closing_summary, run_job
    from kforge.pipeline.storage import DatasetError

    try:
        summary = run_job(
            job,
            max_batches=args.max_batches,
            show_progress=not args.no_progress,
            verbose=args.verbose,
            report=lambda line: print(line, file=sys.stderr),
        )
    except JobInterrupted as interrupted:
        resume = shlex.join(["kforge", "run", *(argv if argv is not None else sys.argv[1:])])
        print(
            f"{interrupted} ({interrupted.committed_in_run} in this run); resume with: {resume}",
            file=sys.stderr,
        )
        raise SystemExit(EXIT_INTERRUPTED) from None
    except (ResumeRefused, DatasetError) as error:
        if args.debug:
            raise
        raise fail(error) from error
    if args.json:
        print(json.dumps(summary, indent=1))
    else:
        print(closing_summary(summary, job.output_dir))
    if summary["abandoned_shards"] or summary["committed_batches"] < summary["total_batches"]:
        raise SystemExit(EXIT_DATA)
