"""Chaos rounds: a small generation job hit by one fault per round, resumed to the end, and compared with an
uninterrupted run of the same config. Reports rounds survived, committed level batches lost, trajectories
duplicated, and rounds whose bytes differ from the uninterrupted run (targets: all survived, 0, 0, 0).

    python benchmarks/chaos.py --rounds 50 [--stores local,s3] [--seed 0] [--out chaos.json]

Each round takes the next (fault, store) pair in turn; the moment of the fault (after how many commits) is drawn
from a generator seeded with --seed. Faults:

- driver-sigkill: every process of the job's session is SIGKILLed (the job and its embedded Ray), then resumed;
- driver-sigterm: SIGTERM to the job's driver (a scheduler's stop: exit 130 expected), then resumed;
- worker-kill: on Ray with two workers, the first worker dies between writing a level batch and committing it (the
  worker's fault drill, `KFORGE_WORKER_FAULT`); the job replaces it and finishes by itself;
- lease-expiry: the job is stopped (SIGSTOP) past its lease's stale limit, a second job takes the lease over and
  finishes the dataset, then the first is continued: it must end with `LeaseLost` (exit 1) and change nothing.

Stores: `local` (a temporary folder) and `s3` (moto's S3 server started on 127.0.0.1 by this script). The job is the
test suite's tiny job over 16 levels without the trivial-level filter (8 level batches, 4 kept trajectories); its
programs are compiled once into a compilation cache shared by the rounds. "Bytes differ" compares every commit
record, provenance left out: the records hold the sha256 of every stored object and of its decoded content, so equal
records mean equal data. Not covered here: a killed coordinator and a lost node (tests/pipeline/test_lost_actors.py,
tests/pipeline/test_multinode.py).
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import importlib.util
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path

import numpy as np

REPOSITORY = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPOSITORY))  # the project's `pipeline`, not benchmarks/pipeline.py

from kforge.pipeline.generation import load_config, to_yaml  # noqa: E402
from kforge.pipeline.storage import PROVENANCE, all_committed, iter_records, open_store, verify_dataset  # noqa: E402


def _tiny_job() -> list[str]:
    """The test suite's tiny job (tests/pipeline/conftest.py `TINY_JOB`) over 16 levels without the trivial-level
    filter, so that it keeps trajectories (levels 9-12 at split seed 0): 8 level batches in 4 shards."""
    spec = importlib.util.spec_from_file_location("chaos_test_helpers", REPOSITORY / "tests/pipeline/conftest.py")
    helpers = sys.modules[spec.name] = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(helpers)
    overrides = [item for item in helpers.TINY_JOB if not item.startswith(("split.num_levels=", "compile_cache."))]
    return [*overrides, "split.num_levels=16", "filter.enabled=false"]


TINY_JOB = _tiny_job()
TOTAL_BATCHES = 8
LEASE = ["lease.stale_after_s=2", "lease.heartbeat_s=0.25"]
"""A lease that a stopped or killed job loses 2 s after its last heartbeat."""
STALE_WAIT_S = 3.0  # [s] how long a stopped or killed job's lease is left to go stale
JOB_TIMEOUT_S = 900.0
POLL_S = 0.05
FAULTS = ("driver-sigkill", "driver-sigterm", "worker-kill", "lease-expiry")
EXIT_INTERRUPTED, EXIT_DATA = 130, 1
S3_ENV = {
    "AWS_ACCESS_KEY_ID": "testing",
    "AWS_SECRET_ACCESS_KEY": "not-a-real-secret",
    "AWS_REGION": "us-east-1",
    "AWS_EC2_METADATA_DISABLED": "true",
}
BUCKET = "kforge-chaos"


def committed(location: str) -> int:
    """Committed level batches of the dataset at `location` (0 before it exists)."""
    with contextlib.suppress(Exception):  # the dataset may not exist yet
        if open_store(location).exists("data/zarr.json"):
            return sum(len(batches) for batches in all_committed(location).values())
    return 0


def records(location: str) -> dict[tuple[int, int], str]:
    """(shard, batch) -> its commit record as JSON, provenance left out."""
    return {
        (record.shard, record.batch): json.dumps(
            {key: value for key, value in record.to_json().items() if key != PROVENANCE}, sort_keys=True
        )
        for record in iter_records(location)
    }


class Job:
    """`python -m kforge run CONFIG` in a session of its own."""

    def __init__(self, config_file: Path, env: dict):
        self.process = subprocess.Popen(
            [sys.executable, "-m", "kforge", "run", str(config_file), "--no-progress"],
            start_new_session=True,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            env=env,
        )

    def wait_for(self, condition) -> bool:
        """Wait until `condition()` holds (True) or the job ends (False)."""
        deadline = time.monotonic() + JOB_TIMEOUT_S
        while self.process.poll() is None and time.monotonic() < deadline:
            if condition():
                return True
            time.sleep(POLL_S)
        return False

    def signal_session(self, signum: int) -> None:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.process.pid, signum)

    def finish(self) -> tuple[int, str]:
        """(exit code, last output line) once it ends."""
        output = self.process.communicate(timeout=JOB_TIMEOUT_S)[0].decode(errors="replace").strip()
        return self.process.returncode, (output.splitlines() or [""])[-1]

    def kill(self) -> None:
        self.signal_session(signal.SIGKILL)
        self.process.wait()


def run_round(fault: str, location: str, work: Path, env: dict, cache: Path, rng) -> dict:
    """Apply one fault to a fresh job at `location`, resume it to the end; what happened."""
    workers = 2 if fault == "worker-kill" else 0
    overrides = [
        f"output_dir={location}",
        *TINY_JOB,
        *LEASE,
        f"compile_cache.dir={cache}",
        f"ray.num_workers={workers}",
    ]
    config_file = work / f"job-{uuid.uuid4().hex[:8]}.yaml"
    config_file.write_text(to_yaml(load_config(None, overrides)))
    after = int(rng.integers(1, TOTAL_BATCHES))  # commits before the fault: 1 to all but one
    notes = []
    round_env = dict(env)
    marker = work / f"fault-{uuid.uuid4().hex[:8]}"
    if fault == "worker-kill":  # the first worker dies after staging its first level batch
        round_env["KFORGE_WORKER_FAULT"] = f"1:{marker}"
        after = None
    job = Job(config_file, round_env)
    try:
        if fault == "worker-kill":
            code, last = job.finish()
            if code != 0 or not marker.exists():
                notes.append(f"worker killed: fault fired {marker.exists()}, job exit {code} ({last})")
        elif not job.wait_for(lambda: committed(location) >= after):
            notes.append("ended before the fault")
        elif fault == "driver-sigkill":
            job.kill()
            time.sleep(STALE_WAIT_S)  # its lease goes stale: a resume sooner is refused (`LeaseHeld`), as designed
        elif fault == "driver-sigterm":
            job.signal_session(signal.SIGTERM)
            code, last = job.finish()
            if code != EXIT_INTERRUPTED:
                notes.append(f"SIGTERM: exit {code} ({last})")
        elif fault == "lease-expiry":
            job.signal_session(signal.SIGSTOP)
            time.sleep(STALE_WAIT_S)
            taker = Job(config_file, env)
            code, last = taker.finish()
            if code != 0:
                notes.append(f"taking job: exit {code} ({last})")
            job.signal_session(signal.SIGCONT)
            code, last = job.finish()
            if code != EXIT_DATA or "lease" not in last:  # fenced: `LeaseLost` at its next step
                notes.append(f"stopped job after the take-over: exit {code} ({last})")
    finally:
        if job.process.poll() is None:
            job.kill()
    resumed = Job(config_file, env)
    code, last = resumed.finish()
    if code != 0:
        notes.append(f"resume: exit {code} ({last})")
    return {"fault": fault, "after_commits": after, "notes": notes}


@contextlib.contextmanager
def s3_server():
    """moto's S3 server on 127.0.0.1 with one bucket: the environment its jobs need."""
    import boto3
    from moto.server import ThreadedMotoServer

    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    endpoint = f"http://{host}:{port}"
    client = boto3.client(
        "s3",
        endpoint_url=endpoint,
        region_name=S3_ENV["AWS_REGION"],
        aws_access_key_id=S3_ENV["AWS_ACCESS_KEY_ID"],
        aws_secret_access_key=S3_ENV["AWS_SECRET_ACCESS_KEY"],
    )
    client.create_bucket(Bucket=BUCKET)
    try:
        yield {**S3_ENV, "AWS_ENDPOINT_URL": endpoint}
    finally:
        server.stop()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=50)
    parser.add_argument("--stores", default="local,s3", help="comma-separated: local, s3")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=None, help="write the rounds and the totals as JSON")
    args = parser.parse_args()
    stores = args.stores.split(",")
    if set(stores) - {"local", "s3"}:
        parser.error(f"--stores: unknown store in {args.stores!r} (local, s3)")
    rng = np.random.default_rng(args.seed)
    base_env = {**os.environ, "RAY_AUTH_MODE": "disabled", "RAY_USAGE_STATS_ENABLED": "0"}
    with tempfile.TemporaryDirectory(prefix="kforge-chaos-") as temp, contextlib.ExitStack() as stack:
        work = Path(temp)
        cache = work / "jax-cache"
        s3_env = stack.enter_context(s3_server()) if "s3" in stores else {}
        env_of = {"local": base_env, "s3": {**base_env, **s3_env}}

        def location(store: str, name: str) -> str:
            return f"s3://{BUCKET}/{name}" if store == "s3" else str(work / name)

        references = {}
        for store in stores:
            reference = location(store, "reference")
            os.environ.update(env_of[store])  # this process reads the datasets too
            config = load_config(None, [f"output_dir={reference}", *TINY_JOB, f"compile_cache.dir={cache}"])
            config_file = work / f"reference-{store}.yaml"
            config_file.write_text(to_yaml(config))
            job = Job(config_file, env_of[store])
            code, last = job.finish()
            if code != 0:
                raise SystemExit(f"the uninterrupted {store} run failed: {last}")
            references[store] = records(reference)
        rounds = []
        pairs = [(fault, store) for fault in FAULTS for store in stores]
        for index in range(args.rounds):
            fault, store = pairs[index % len(pairs)]
            target = location(store, f"round-{index:03d}")
            os.environ.update(env_of[store])
            started = time.perf_counter()
            outcome = run_round(fault, target, work, env_of[store], cache, rng)
            found, reference = records(target), references[store]
            kept = collections.Counter(
                (level["level_id"]) for text in found.values() for level in json.loads(text)["levels"] if level["kept"]
            )
            outcome |= {
                "store": store,
                "seconds": round(time.perf_counter() - started, 1),
                "lost": len(set(reference) - set(found)),
                "duplicated": sum(count - 1 for count in kept.values()),
                "bytes_differ": any(found.get(key) != value for key, value in reference.items()),
            }
            outcome["verifies"] = all(report.ok for report in verify_dataset(target))
            outcome["survived"] = not outcome["notes"] and outcome["verifies"] and not outcome["lost"]
            rounds.append(outcome)
            print(json.dumps(outcome), flush=True)
    totals = {
        "rounds": len(rounds),
        "survived": sum(r["survived"] for r in rounds),
        "lost": sum(r["lost"] for r in rounds),
        "duplicated": sum(r["duplicated"] for r in rounds),
        "rounds_whose_bytes_differ": sum(r["bytes_differ"] for r in rounds),
    }
    print(json.dumps(totals))
    if args.out is not None:
        args.out.write_text(json.dumps({"rounds": rounds, "totals": totals}, indent=1))


if __name__ == "__main__":
    main()
