"""Chaos rounds: a small generation job that keeps trajectories, hit by one random fault per round, resumed to the
end, and compared with an uninterrupted run of the same config. Reports rounds survived, committed level batches
lost, trajectories duplicated, and rounds whose bytes differ from the uninterrupted run (targets: all survived, 0,
0, 0).

    python -m benchmarks.chaos --rounds 50 [--stores local,s3] [--seed 0] [--work DIR] --out FILE.json

Each round draws, from a generator seeded with (--seed, round), what to hit, how, when and on which store:

- what: the job's `driver` (its whole session for SIGKILL: the job and its embedded Ray), a `worker` actor's
  process or the `coordinator` actor's process (the job on embedded Ray with two workers), or a `node`: the second
  node of a two-node Ray cluster started with `ray start` on 127.0.0.1 (its `ray start`, raylet, object store and
  workers), with the job submitted to the cluster by address, one worker per node;
- how: `sigkill`, `sigterm`, or `stop`: SIGSTOP for longer than the job's lease stale limit, then SIGCONT (for the
  driver, a second job takes the lease over and finishes the dataset meanwhile, and the stopped job must end with
  `LeaseLost` once continued: lease expiry);
- when: after 0 to all-but-one committed level batches (0: while the job compiles its programs), and for the driver
  once it holds the dataset's lease.

Then the job is run again to the end (a resume; it reports a complete dataset when the job finished by itself).
Stores: `local` (a folder below --work) and `s3` (moto's S3 server started on 127.0.0.1 by this script). The job is
the test suite's job that keeps trajectories (tests/pipeline/conftest.py `KEEPING_JOB`); its programs are compiled
once into a compilation cache shared by the rounds. "Bytes differ" compares every commit record, provenance left
out: the records hold the sha256 of every stored object and of its decoded content, so equal records mean equal
data. The JSON report is rewritten after every round; run the same command again to continue an interrupted series
(rounds already in --out are kept, the uninterrupted runs' records too; each round records the commit it ran at).
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import importlib.util
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path

import numpy as np

from benchmarks.machine import describe_machine, provenance
from kforge.pipeline.generation import load_config, to_yaml
from kforge.pipeline.storage import PROVENANCE, all_committed, iter_records, open_store, verify_dataset

REPOSITORY = Path(__file__).resolve().parents[1]


def _keeping_job() -> list[str]:
    """The test suite's job that keeps trajectories (tests/pipeline/conftest.py `KEEPING_JOB`), without its
    compilation cache setting (the rounds share one)."""
    spec = importlib.util.spec_from_file_location("chaos_test_helpers", REPOSITORY / "tests/pipeline/conftest.py")
    helpers = sys.modules[spec.name] = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(helpers)
    return [item for item in helpers.KEEPING_JOB if not item.startswith("compile_cache.")], helpers.KEEPING_BATCHES


JOB, TOTAL_BATCHES = _keeping_job()
LEASE = ["lease.stale_after_s=3", "lease.heartbeat_s=0.5"]
"""A lease that a stopped or killed job loses 3 s after its last heartbeat."""
STALE_WAIT_S = 5.0  # [s] how long a stopped or killed job's lease is left to go stale
ACTOR_STOP_S = 20.0  # [s] a stopped actor's process stays stopped this long
NODE_STOP_S = 45.0  # [s] a stopped node stays stopped this long (Ray marks a silent node dead after about 30 s)
JOB_TIMEOUT_S = 1200.0
NODE_START_S = 300.0  # [s] at most, for `ray start` to bring a node up
POLL_S = 0.05
TARGETS = ("driver", "worker", "coordinator", "node")
HOWS = ("sigkill", "sigterm", "stop")
SIGNALS = {"sigkill": signal.SIGKILL, "sigterm": signal.SIGTERM, "stop": signal.SIGSTOP}
ACTOR_PROCESS = {"worker": "ray::Worker", "coordinator": "ray::Coordinator"}
"""Title that Ray gives an actor's process (followed by the method it runs)."""
EXIT_INTERRUPTED, EXIT_DATA = 130, 1
RAY = [sys.executable, "-m", "ray.scripts.scripts"]
RAY_ENV = {"RAY_AUTH_MODE": "disabled", "RAY_USAGE_STATS_ENABLED": "0"}
S3_ENV = {
    "AWS_ACCESS_KEY_ID": "testing",
    "AWS_SECRET_ACCESS_KEY": "not-a-real-secret",
    "AWS_REGION": "us-east-1",
    "AWS_EC2_METADATA_DISABLED": "true",
}
BUCKET = "kforge-chaos"
LEASE_OBJECT = "lease.json"
"""The lease object at a dataset's root while a job holds it (docs/operating.md)."""


def committed(location: str) -> int:
    """Committed level batches of the dataset at `location` (0 before it exists)."""
    with contextlib.suppress(Exception):  # the dataset may not exist yet
        if open_store(location).exists("data/zarr.json"):
            return sum(len(batches) for batches in all_committed(location).values())
    return 0


def _holds_lease(location: str) -> bool:
    """Whether a job holds the lease of the dataset at `location` (its lease object exists)."""
    with contextlib.suppress(Exception):  # the store may not answer yet
        return open_store(location).exists(LEASE_OBJECT)
    return False


def records(location: str) -> dict[str, str]:
    """ "shard/batch" -> its commit record as JSON, provenance left out."""
    return {
        f"{record.shard}/{record.batch}": json.dumps(
            {key: value for key, value in record.to_json().items() if key != PROVENANCE}, sort_keys=True
        )
        for record in iter_records(location)
    }


def session_processes(session: int) -> dict[int, str]:
    """Pid -> command line of the live processes of a Unix session."""
    found = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
            if int(fields[3]) != session or fields[0] == "Z":
                continue
            found[int(stat.parent.name)] = (stat.parent / "cmdline").read_bytes().replace(b"\0", b" ").decode()
        except (OSError, IndexError, ValueError):
            continue
    return found


def signal_session(session: int, signum: int) -> None:
    """`signum` to every process of the session (for SIGKILL: until none is left)."""
    deadline = time.monotonic() + 60
    while True:
        pids = session_processes(session)
        for pid in pids:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signum)
        if signum != signal.SIGKILL or not pids or time.monotonic() > deadline:
            return
        time.sleep(0.1)


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

    def finish(self) -> tuple[int, str]:
        """(exit code, last output line) once it ends; (None, "timed out") if it is still running after
        `JOB_TIMEOUT_S` (then it is killed)."""
        try:
            output = self.process.communicate(timeout=JOB_TIMEOUT_S)[0].decode(errors="replace").strip()
        except subprocess.TimeoutExpired:
            self.kill()
            return None, "timed out"
        return self.process.returncode, (output.splitlines() or [""])[-1]

    def kill(self) -> None:
        signal_session(self.process.pid, signal.SIGKILL)
        self.process.wait()


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


class Cluster:
    """A head node and a second node started with `ray start --block` on 127.0.0.1, one CPU each, each in a session
    of its own (the node a round hits is the second)."""

    def __init__(self, env: dict):
        self.env = {**env, **RAY_ENV}
        self.address = f"127.0.0.1:{_free_port()}"
        self.temp_dir = tempfile.mkdtemp(prefix="kfray-")  # short: Ray's socket paths live below it
        port = self.address.rpartition(":")[2]
        self.head = self._start("--head", f"--port={port}", "--include-dashboard=false", f"--temp-dir={self.temp_dir}")
        self._wait_for_nodes(1)
        self.second = self._start(f"--address={self.address}")
        self._wait_for_nodes(2)

    def _start(self, *args: str) -> subprocess.Popen:
        return subprocess.Popen(
            [*RAY, "start", "--block", "--node-ip-address=127.0.0.1", "--num-cpus=1", *args],
            start_new_session=True,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            env=self.env,
        )

    def _wait_for_nodes(self, count: int) -> None:
        deadline = time.monotonic() + NODE_START_S
        while self.nodes_alive() < count:
            if time.monotonic() > deadline:
                raise RuntimeError(f"the Ray cluster at {self.address} did not reach {count} nodes")
            time.sleep(1.0)

    def nodes_alive(self) -> int:
        status = subprocess.run(
            [*RAY, "status", f"--address={self.address}"], capture_output=True, text=True, env=self.env
        )
        active = status.stdout.partition("Active:")[2].partition("Pending:")[0]
        return sum(1 for line in active.splitlines() if "node_" in line)

    def stop(self) -> None:
        for node in (self.second, self.head):
            signal_session(node.pid, signal.SIGCONT)
            signal_session(node.pid, signal.SIGKILL)
            node.wait()
        shutil.rmtree(self.temp_dir, ignore_errors=True)


def _actor_processes(session: int, target: str) -> list[int]:
    return sorted(
        pid for pid, command in session_processes(session).items() if command.startswith(ACTOR_PROCESS[target])
    )


def draw_round(seed: int, index: int, stores: list[str]) -> dict:
    """What round `index` does: target, how, after how many commits, store, and workers for a driver fault."""
    rng = np.random.default_rng([seed, index])
    return {
        "target": str(rng.choice(TARGETS)),
        "how": str(rng.choice(HOWS)),
        "after_commits": int(rng.integers(0, TOTAL_BATCHES)),  # 0 to all but one
        "store": str(rng.choice(stores)),
        "driver_workers": int(rng.choice([0, 2])),  # a driver fault hits a job without Ray or one on Ray
    }


def run_round(plan: dict, location: str, work: Path, env: dict, cache: Path) -> dict:
    """Apply one fault to a fresh job at `location`, then resume it to the end; what happened."""
    target, how, after = plan["target"], plan["how"], plan["after_commits"]
    workers = plan["driver_workers"] if target == "driver" else 2
    cluster = Cluster(env) if target == "node" else None
    overrides = [f"output_dir={location}", *JOB, *LEASE, f"compile_cache.dir={cache}", f"ray.num_workers={workers}"]
    if cluster is not None:
        overrides.append(f"ray.address={cluster.address}")
    config_file = work / f"job-{uuid.uuid4().hex[:8]}.yaml"
    config_file.write_text(to_yaml(load_config(None, overrides)))
    job_env = {**env, **RAY_ENV}
    notes = []
    fired = False
    job = Job(config_file, job_env)
    try:
        if target in ACTOR_PROCESS:
            reached = job.wait_for(lambda: committed(location) >= after and _actor_processes(job.process.pid, target))
        elif target == "node":  # once a worker runs there (a worker never placed would wait for a node for ever)
            reached = job.wait_for(
                lambda: committed(location) >= after and _actor_processes(cluster.second.pid, "worker")
            )
        else:  # once the job holds the lease (a job stopped or ended before it took it has nothing to lose)
            reached = job.wait_for(lambda: committed(location) >= after and _holds_lease(location))
        if not reached:
            notes.append("the job ended before the fault")  # not a failure: the round tests the resume only
        elif target == "driver":
            fired = _hit_driver(job, how, config_file, job_env, notes)
        elif target in ACTOR_PROCESS:
            fired = _hit_actor(job, target, how)
        else:
            fired = _hit_node(cluster, how)
        if job.process.poll() is None or target != "driver":
            code, last = job.finish()
            if target != "driver" and code != 0:
                notes.append(f"the job after its {target} was hit: exit {code} ({last})")
    finally:
        if job.process.poll() is None:
            job.kill()
        if cluster is not None:
            cluster.stop()
    if notes == ["the job ended before the fault"]:
        notes = []
    resumed = Job(config_file, {**env, **RAY_ENV})
    code, last = resumed.finish()
    if code != 0:
        notes.append(f"resume: exit {code} ({last})")
    return {**plan, "fired": fired, "notes": notes}


def _hit_driver(job: Job, how: str, config_file: Path, env: dict, notes: list) -> bool:
    if how == "sigkill":
        job.kill()
        time.sleep(STALE_WAIT_S)  # its lease goes stale: a resume sooner is refused (`LeaseHeld`), as designed
    elif how == "sigterm":
        with contextlib.suppress(ProcessLookupError):
            os.kill(job.process.pid, signal.SIGTERM)
        code, last = job.finish()
        if code not in (EXIT_INTERRUPTED, 0):  # 0: it finished before the signal landed
            notes.append(f"SIGTERM: exit {code} ({last})")
    else:
        signal_session(job.process.pid, signal.SIGSTOP)
        time.sleep(STALE_WAIT_S)
        taker = Job(config_file, env)
        code, last = taker.finish()
        if code != 0:
            notes.append(f"taking job: exit {code} ({last})")
        signal_session(job.process.pid, signal.SIGCONT)
        code, last = job.finish()
        if code != EXIT_DATA or "lease" not in last:  # fenced: `LeaseLost` at its next step
            notes.append(f"stopped job after the take-over: exit {code} ({last})")
    return True


def _hit_actor(job: Job, target: str, how: str) -> bool:
    pids = _actor_processes(job.process.pid, target)
    if not pids:
        return False
    pid = pids[0]
    with contextlib.suppress(ProcessLookupError):
        os.kill(pid, SIGNALS[how])
        if how == "stop":
            time.sleep(ACTOR_STOP_S)
            os.kill(pid, signal.SIGCONT)
    return True


def _hit_node(cluster: Cluster, how: str) -> bool:
    session = cluster.second.pid
    if how == "stop":
        signal_session(session, signal.SIGSTOP)
        time.sleep(NODE_STOP_S)
        signal_session(session, signal.SIGCONT)
    else:
        signal_session(session, SIGNALS[how])
    return True


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


def totals_of(rounds: list[dict]) -> dict:
    faults = collections.Counter(f"{r['target']}-{r['how']}" for r in rounds if r["fired"])
    return {
        "rounds": len(rounds),
        "survived": sum(r["survived"] for r in rounds),
        "faults_fired": sum(r["fired"] for r in rounds),
        "lost": sum(r["lost"] for r in rounds),
        "duplicated": sum(r["duplicated"] for r in rounds),
        "rounds_whose_bytes_differ": sum(r["bytes_differ"] for r in rounds),
        "by_fault": dict(sorted(faults.items())),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=50)
    parser.add_argument("--stores", default="local,s3", help="comma-separated: local, s3")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--work", type=Path, default=None, help="folder for the datasets (default: a temporary one)")
    parser.add_argument("--out", type=Path, required=True, help="the JSON report; an existing one is continued")
    args = parser.parse_args()
    stores = args.stores.split(",")
    if set(stores) - {"local", "s3"}:
        parser.error(f"--stores: unknown store in {args.stores!r} (local, s3)")
    report = json.loads(args.out.read_text()) if args.out.exists() else {}
    if report and (report.get("seed"), report.get("stores")) != (args.seed, stores):
        parser.error(f"--out {args.out} holds rounds of another --seed or --stores; name another file")
    report.setdefault("provenance", provenance())  # of the run that started the series
    report.setdefault("machine", describe_machine())
    report.update(
        command=provenance()["command"],
        seed=args.seed,
        stores=stores,
        job=JOB,
        level_batches=TOTAL_BATCHES,
    )
    rounds, references = report.setdefault("rounds", []), report.setdefault("references", {})
    base_env = {**os.environ, **RAY_ENV}
    with contextlib.ExitStack() as stack:
        work = args.work or Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="kforge-chaos-")))
        work.mkdir(parents=True, exist_ok=True)
        cache = work / "jax-cache"
        s3_env = stack.enter_context(s3_server()) if "s3" in stores else {}
        env_of = {"local": base_env, "s3": {**base_env, **s3_env}}
        run_id = uuid.uuid4().hex[:6]

        def location(store: str, name: str) -> str:
            return f"s3://{BUCKET}/{name}" if store == "s3" else str(work / name)

        for store in stores:
            if store in references:
                continue
            reference = location(store, f"reference-{run_id}")
            os.environ.update(env_of[store])  # this process reads the datasets too
            config = load_config(None, [f"output_dir={reference}", *JOB, f"compile_cache.dir={cache}"])
            config_file = work / f"reference-{store}.yaml"
            config_file.write_text(to_yaml(config))
            code, last = Job(config_file, env_of[store]).finish()
            if code != 0:
                raise SystemExit(f"the uninterrupted {store} run failed: {last}")
            references[store] = records(reference)
            kept = [json.loads(text)["num_kept"] for text in references[store].values()]
            print(json.dumps({"reference": store, "kept_per_batch": kept}), flush=True)
        for index in range(len(rounds), args.rounds):
            plan = draw_round(args.seed, index, stores)
            store = plan["store"]
            target = location(store, f"round-{index:03d}-{run_id}")
            os.environ.update(env_of[store])
            started = time.perf_counter()
            outcome = {
                "round": index,
                "commit": provenance()["commit"],
                **run_round(plan, target, work, env_of[store], cache),
            }
            try:
                found, verifies = records(target), all(report.ok for report in verify_dataset(target))
            except Exception as error:  # noqa: BLE001 (a round that left no readable dataset is reported, not fatal)
                found, verifies = {}, False
                outcome["notes"].append(f"unreadable dataset: {type(error).__name__}: {error}".splitlines()[0])
            reference = references[store]
            kept = collections.Counter(
                level["level_id"] for text in found.values() for level in json.loads(text)["levels"] if level["kept"]
            )
            outcome |= {
                "seconds": round(time.perf_counter() - started, 1),
                "lost": len(set(reference) - set(found)),
                "duplicated": sum(count - 1 for count in kept.values()),
                "bytes_differ": any(found.get(key) != value for key, value in reference.items()),
                "kept": sum(kept.values()),
            }
            outcome["verifies"] = verifies
            outcome["survived"] = not outcome["notes"] and outcome["verifies"] and not outcome["lost"]
            rounds.append(outcome)
            report["totals"] = totals_of(rounds)
            args.out.write_text(json.dumps(report, indent=1))
            print(json.dumps(outcome), flush=True)
            if store == "local":
                shutil.rmtree(target, ignore_errors=True)
    print(json.dumps(report["totals"]))


if __name__ == "__main__":
    main()
