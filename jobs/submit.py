"""`python -m kforge.jobs.submit CONFIG [key=value ...] [--scale NAME]`: `kforge run` as a Ray job on a running
cluster.

What `ray job submit` does, with the job's command built and checked here: the config and overrides are validated
before anything is sent, the checkout is uploaded as the job's working dir (`runtime_env`), the job's logs stream to
stdout until it ends, and the exit status is the job's: 0 when it succeeded, `kforge run`'s own code when its driver
exited with one (2: bad config, 1: abandoned shards), 1 for any other failure, 130 when interrupted here (the job
keeps running). The cluster is given as the dashboard's address (`--address http://HEAD:8265`, or the
`RAY_API_SERVER_ADDRESS` / `RAY_ADDRESS` environment variables, which Ray lets override the flag).

The job runs in a temporary copy of the working dir, so `output_dir` (given or derived from the split and scale) is
made absolute here, relative paths resolving against the current directory, and must be on storage that every node
of the cluster reaches; config and scale files must lie inside the working dir; `ray.address` is set to `auto` (the
cluster the job runs on).
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import shlex
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from kforge.pipeline.generation import ConfigError, absolute_output_dir, load_config

REPO_ROOT = Path(__file__).resolve().parents[1]
"""The checkout this module belongs to: the default working dir of submitted jobs."""

UPLOAD_EXCLUDES = [".git", ".venv", ".venv-kinetix", "outputs", "wandb", "__pycache__"]
"""Paths under the working dir that are not uploaded with a job (Ray also skips what .gitignore lists)."""

JOB_FAILED_EXIT = 1
"""Exit status when the job failed without a driver exit code (e.g. it was stopped or its runtime env failed)."""
USAGE_EXIT = 2
"""Exit status when nothing was submitted: a bad config or argument, or no job server at the address."""
INTERRUPTED_EXIT = 130
"""Exit status on Ctrl-C while following the job (the job itself keeps running)."""

STATUS_POLL_SECONDS = 1.0
"""Interval of status checks after the log stream ended before the job's status is final."""


@dataclasses.dataclass(frozen=True)
class Submission:
    """What is sent to the cluster for one `kforge run`."""

    entrypoint: str  # shell command run in the job's working dir
    runtime_env: dict  # Ray runtime_env: working_dir, excludes, env_vars
    output_dir: Path | str  # absolute dataset directory the job writes, or an s3:// or gs:// URL as given


def build_submission(
    config: str | Path,
    overrides: Sequence[str] = (),
    scale: str | None = None,
    working_dir: str | Path = REPO_ROOT,
    env_vars: dict[str, str] | None = None,
    max_batches: int | None = None,
) -> Submission:
    """The job for `kforge run CONFIG OVERRIDES --scale SCALE`; `ConfigError` naming the problem if the config is
    unusable or a file it names lies outside `working_dir` (the job sees only what is uploaded from there)."""
    working_dir = Path(working_dir).resolve()
    job = load_config(config, overrides, scale=scale)
    output_dir = absolute_output_dir(job.output_dir)
    command = ["python", "-m", "kforge", "run", "--no-progress", "--json"]
    if scale is not None:
        is_path = scale.endswith((".yaml", ".yml"))  # else a preset name, resolved in the job's configs/scales
        command += ["--scale", _inside(Path(scale), working_dir, "scale") if is_path else scale]
    if max_batches is not None:
        command += ["--max-batches", str(max_batches)]
    command += [_inside(Path(config), working_dir, "config"), *overrides]
    command += [f"output_dir={output_dir}", "ray.address=auto"]
    runtime_env = {"working_dir": str(working_dir), "excludes": UPLOAD_EXCLUDES, "env_vars": dict(env_vars or {})}
    return Submission(entrypoint=shlex.join(command), runtime_env=runtime_env, output_dir=output_dir)


def _inside(path: Path, working_dir: Path, what: str) -> str:
    """`path` relative to the working dir (the job's cwd); `ConfigError` if it lies outside."""
    path = path.resolve()
    if not path.is_relative_to(working_dir):
        raise ConfigError(f"{what} {path} is outside the working dir {working_dir}; a job sees only files from there")
    return path.relative_to(working_dir).as_posix()


def parse_env_vars(pairs: Sequence[str]) -> dict[str, str]:
    """`KEY=VALUE` strings as a dict; `ConfigError` naming a pair without `=`."""
    env_vars = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or not key:
            raise ConfigError(f"--env expects KEY=VALUE, got {pair!r}")
        env_vars[key] = value
    return env_vars


async def _print_logs(client, job_id: str) -> None:
    async for lines in client.tail_job_logs(job_id):
        print(lines, end="", flush=True)


def follow(client, job_id: str) -> int:
    """Stream the job's logs until it ends; its exit status (see the module docstring)."""
    from ray.job_submission import JobStatus

    try:
        asyncio.run(_print_logs(client, job_id))
    except RuntimeError as error:  # the log stream broke off; the status below still tells how the job ended
        print(f"log stream of {job_id} ended early: {error}", file=sys.stderr)
    info = client.get_job_info(job_id)
    while not info.status.is_terminal():
        time.sleep(STATUS_POLL_SECONDS)
        info = client.get_job_info(job_id)
    print(f"job {job_id} {info.status.value}" + (f": {info.message}" if info.message else ""), file=sys.stderr)
    if info.status == JobStatus.SUCCEEDED:
        return 0
    return info.driver_exit_code or JOB_FAILED_EXIT


def main(argv: Sequence[str] | None = None) -> None:
    """Submit `kforge run CONFIG [key=value ...]` to a Ray cluster and follow it; exits with the job's status."""
    parser = argparse.ArgumentParser(prog="python -m kforge.jobs.submit", description=__doc__.split("\n\n")[0])
    parser.add_argument("config", help="job YAML inside the working dir, e.g. configs/splits/1M/s.yaml")
    parser.add_argument("overrides", nargs="*", help="dotlist overrides, e.g. output_dir=/shared/ds ray.num_workers=8")
    parser.add_argument("--scale", help="`kforge run --scale`: a preset name (tiny, local, full) or a YAML path")
    parser.add_argument("--address", help="dashboard address, e.g. http://127.0.0.1:8265 (default: Ray's lookup)")
    parser.add_argument("--working-dir", default=REPO_ROOT, help="directory uploaded as the job's (default: checkout)")
    parser.add_argument("--env", action="append", default=[], metavar="KEY=VALUE", help="job environment (repeat)")
    parser.add_argument("--submission-id", help="job id to use (default: Ray picks one); resubmitting needs a new one")
    parser.add_argument("--max-batches", type=int, help="`kforge run --max-batches`: stop after that many batches")
    parser.add_argument("--no-wait", action="store_true", help="print the job id and return once it is submitted")
    args = parser.parse_intermixed_args(argv)
    try:
        submission = build_submission(
            args.config, args.overrides, args.scale, args.working_dir, parse_env_vars(args.env), args.max_batches
        )
    except ConfigError as error:
        print(f"error: {error}", file=sys.stderr)
        raise SystemExit(USAGE_EXIT) from error

    from ray.job_submission import JobSubmissionClient

    try:
        client = JobSubmissionClient(args.address)
    except ConnectionError as error:
        print(f"error: no Ray job server: {error}", file=sys.stderr)
        raise SystemExit(USAGE_EXIT) from error
    job_id = client.submit_job(
        entrypoint=submission.entrypoint,
        runtime_env=submission.runtime_env,
        submission_id=args.submission_id,
        metadata={"kforge_output_dir": str(submission.output_dir)},
    )
    print(f"submitted {job_id}: {submission.entrypoint}", file=sys.stderr)
    print(f"  stop: ray job stop --address {client.get_address()} {job_id}", file=sys.stderr)
    if args.no_wait:
        print(job_id)
        return
    try:
        status = follow(client, job_id)
    except KeyboardInterrupt:
        print(f"\nstopped following {job_id}; the job keeps running", file=sys.stderr)
        raise SystemExit(INTERRUPTED_EXIT) from None
    raise SystemExit(status)


if __name__ == "__main__":
    main()
