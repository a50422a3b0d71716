"""jobs/: what `kforge.jobs.submit` sends, the cluster-launcher template, and (slow) real runs on this machine: a
tiny job submitted through the Ray Jobs API to a `ray start --head` cluster, and jobs/slurm.sbatch under a fake
one-node SLURM. Each slow test checks the dataset and that every process it started, and no other, is gone.
"""

import contextlib
import copy
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml
from pipeline_test_helpers import TINY_JOB

from kforge.jobs.submit import REPO_ROOT, UPLOAD_EXCLUDES, build_submission, parse_env_vars
from kforge.pipeline.generation import ConfigError
from kforge.pipeline.storage.manifest import committed_batches
from kforge.pipeline.storage.verify import verify_dataset
from tests.pipeline.test_tracking import wandb_history

SPLIT_CONFIG = "configs/splits/1M/s.yaml"
"""A config file inside the checkout; TINY_JOB overrides every key of it (seed 0 is the schema default too)."""
SBATCH = REPO_ROOT / "jobs" / "slurm.sbatch"
CLUSTER_YAML = REPO_ROOT / "jobs" / "ray-cluster.yaml"

CLUSTER_CPUS = 2
OBJECT_STORE_BYTES = 512 << 20  # [B] instead of 30 % of RAM
HEAD_START_SECONDS = 120  # [s] until the dashboard answers (about 10 s on an idle 2-core machine)
HEAD_STOP_SECONDS = 60  # [s] for `ray start --block` to stop its processes after SIGTERM
JOB_SECONDS = 900  # [s] for the tiny job (about 100 s on a busy 2-core machine)
PROCESS_EXIT_SECONDS = 15  # [s] for stopped processes to disappear
NODE_PORT_FLAGS = (
    "--node-manager-port",
    "--object-manager-port",
    "--dashboard-agent-grpc-port",
    "--dashboard-agent-listen-port",
    "--metrics-export-port",
    "--runtime-env-agent-port",
)
"""`ray start` ports that default to fixed or shared values; each test cluster takes free ones (other Ray instances
may run on this machine)."""


def test_the_submission_runs_kforge_in_the_uploaded_checkout_against_its_own_cluster(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    submission = build_submission(
        REPO_ROOT / SPLIT_CONFIG, [*TINY_JOB, "output_dir=data/tiny"], scale="tiny", env_vars={"A": "1"}
    )
    assert submission.output_dir == tmp_path / "data" / "tiny"  # relative: resolved where the submitter runs
    command = submission.entrypoint.split()
    assert command[:8] == ["python", "-m", "kforge", "run", "--no-progress", "--json", "--scale", "tiny"]
    assert command[8] == SPLIT_CONFIG  # relative to the working dir, which is the job's cwd
    assert command[-2:] == [f"output_dir={tmp_path / 'data' / 'tiny'}", "ray.address=auto"]  # last: they win
    assert submission.runtime_env == {
        "working_dir": str(REPO_ROOT),
        "excludes": UPLOAD_EXCLUDES,
        "env_vars": {"A": "1"},
    }


def test_a_submission_keeps_an_object_store_output_dir_as_given(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    submission = build_submission(REPO_ROOT / SPLIT_CONFIG, [*TINY_JOB, "output_dir=s3://bucket/datasets/tiny"])
    assert submission.output_dir == "s3://bucket/datasets/tiny"
    assert submission.entrypoint.split()[-2] == "output_dir=s3://bucket/datasets/tiny"


def test_a_submission_that_cannot_work_is_refused_before_anything_is_sent(tmp_path):
    outside = tmp_path / "job.yaml"
    shutil.copy(REPO_ROOT / SPLIT_CONFIG, outside)
    with pytest.raises(ConfigError, match=r"config .*job\.yaml is outside the working dir"):
        build_submission(outside, TINY_JOB)
    with pytest.raises(ConfigError, match=r"scale .*job\.yaml is outside the working dir"):
        build_submission(REPO_ROOT / SPLIT_CONFIG, TINY_JOB, scale=str(outside))
    with pytest.raises(ConfigError, match=r"ppo\.num_envs"):
        build_submission(REPO_ROOT / SPLIT_CONFIG, [*TINY_JOB, "ppo.num_envs=many"])
    with pytest.raises(ConfigError, match=r"--env expects KEY=VALUE, got 'WANDB_MODE'"):
        parse_env_vars(["WANDB_MODE"])


def test_the_cluster_template_passes_ray_validation_for_aws_and_on_premise():
    from ray.autoscaler._private.util import prepare_config, validate_config

    template = yaml.safe_load(CLUSTER_YAML.read_text())
    validate_config(prepare_config(copy.deepcopy(template)))
    # The on-premise edit described in the file's header.
    on_premise = copy.deepcopy(template)
    on_premise["provider"] = {"type": "local", "head_ip": "10.0.0.1", "worker_ips": ["10.0.0.2", "10.0.0.3"]}
    on_premise["auth"] = {"ssh_user": "kforge", "ssh_private_key": "~/.ssh/id_ed25519"}
    for key in ("max_workers", "available_node_types", "head_node_type"):
        del on_premise[key]
    prepared = prepare_config(on_premise)
    validate_config(prepared)
    assert prepared["max_workers"] == 2


def test_the_slurm_script_needs_a_config():
    result = subprocess.run(["bash", str(SBATCH)], capture_output=True, text=True, timeout=30)
    assert result.returncode == 2 and "usage: sbatch jobs/slurm.sbatch" in result.stderr


@pytest.mark.slow
def test_a_job_submitted_to_a_local_ray_cluster_writes_a_dataset_that_verifies(tmp_path):
    output = tmp_path / "dataset"
    env = cluster_env(tmp_path / "home")
    with ray_head(env) as address:
        result = subprocess.run(
            [sys.executable, "-m", "kforge.jobs.submit", "--address", address, SPLIT_CONFIG, *TINY_JOB]
            + [f"output_dir={output}", "tracking.wandb=offline"],
            cwd=REPO_ROOT,
            env=env,
            capture_output=True,
            text=True,
            timeout=JOB_SECONDS,
        )
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    assert re.search(r"job \S+ SUCCEEDED", result.stderr)
    summary = job_summary(result.stdout)  # streamed from the job's driver
    assert summary["committed_batches"] == 4 and summary["worker_failures"] == []
    assert [committed_batches(output, shard) for shard in range(2)] == [[0, 1], [0, 1]]
    assert all(report.ok for report in verify_dataset(output))
    (run_dir,) = (output / "logs" / "wandb").glob("offline-run-*")  # the job's tracking, in the dataset's logs
    rows, summary = wandb_history(run_dir)
    assert sum("batch/seconds" in row for row in rows) == 4 and sum("shard/levels" in row for row in rows) == 2
    assert summary["run/committed_batches"] == 4


@pytest.mark.slow
def test_the_slurm_script_runs_a_job_on_a_fake_one_node_allocation(tmp_path):
    fake_bin = tmp_path / "bin"
    fake_bin.mkdir()
    write_script(fake_bin / "scontrol", 'tr "," "\\n" <<< "$3"  # `scontrol show hostnames LIST`')
    write_script(fake_bin / "srun", 'while [[ $1 == --* ]]; do shift; done\nexec "$@"  # run the step here')
    job_id = f"kforge-test-{os.getpid()}"
    env = cluster_env(tmp_path / "home") | {
        "PATH": f"{fake_bin}:{Path(sys.executable).parent}:{os.environ['PATH']}",
        "SLURM_JOB_ID": job_id,
        "SLURM_JOB_NODELIST": "localhost",
        "SLURM_CPUS_PER_TASK": str(CLUSTER_CPUS),
        "KFORGE_PYTHON": sys.executable,
        "RAY_PORT": str(free_port()),
        "RAY_DASHBOARD_PORT": str(free_port()),
        "RAY_START_ARGS": " ".join(node_port_args() + [f"--object-store-memory={OBJECT_STORE_BYTES}"]),
    }
    output = tmp_path / "dataset"
    script = subprocess.Popen(
        ["bash", str(SBATCH), SPLIT_CONFIG, *TINY_JOB, f"output_dir={output}"],
        cwd=REPO_ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,  # every process the script starts stays in this session
    )
    temp_dir = Path(f"/tmp/ray-{job_id}")  # the script's Ray temp dir
    try:
        log, _ = script.communicate(timeout=JOB_SECONDS)
    finally:
        leftovers = stop_processes(session_processes(script.pid, temp_dir))
        shutil.rmtree(temp_dir, ignore_errors=True)
    assert script.returncode == 0, log[-5000:]
    assert leftovers == [], f"the script's teardown left {leftovers}"
    assert "1 Ray nodes up" in log and job_summary(log)["committed_batches"] == 4
    assert all(report.ok for report in verify_dataset(output))


def cluster_env(home: Path) -> dict[str, str]:
    """Environment of a test cluster and its clients: no token auth or usage stats, a private HOME (a stray
    ~/.ray/auth_token would turn auth on), CPU JAX, no address of another cluster, immediate SIGTERM teardown. The
    run-wide WANDB_MODE=disabled is dropped so that the job's `tracking.wandb` decides."""
    home.mkdir(parents=True, exist_ok=True)
    dropped = ("RAY_ADDRESS", "RAY_API_SERVER_ADDRESS", "WANDB_MODE")
    inherited = {name: value for name, value in os.environ.items() if name not in dropped}
    return inherited | {
        "HOME": str(home),
        "PATH": f"{Path(sys.executable).parent}:{os.environ['PATH']}",  # the job's `python` is this one
        "RAY_AUTH_MODE": "disabled",
        "RAY_USAGE_STATS_ENABLED": "0",
        "RAY_GRACEFUL_SHUTDOWN_DRAIN_TIMEOUT_S": "0",
        "JAX_PLATFORMS": "cpu",
    }


@contextlib.contextmanager
def ray_head(env: dict[str, str]) -> Iterator[str]:
    """A one-node cluster from `ray start --head --block` on 127.0.0.1 with free ports and its own temp dir; yields
    the dashboard address. Afterwards SIGTERM to that command stops its processes; the test fails if any process of
    its session or its temp dir survives (they are killed first), and nothing else is touched."""
    temp_dir = Path(tempfile.mkdtemp(prefix="kf-ray-", dir="/tmp"))  # short: Ray puts unix sockets under it
    dashboard_port = free_port()
    command = [str(Path(sys.executable).parent / "ray"), "start", "--head", "--block", "--node-ip-address=127.0.0.1"]
    command += [f"--port={free_port()}", f"--ray-client-server-port={free_port()}", *node_port_args()]
    command += ["--include-dashboard=true", "--dashboard-host=127.0.0.1", f"--dashboard-port={dashboard_port}"]
    command += [f"--temp-dir={temp_dir}", f"--num-cpus={CLUSTER_CPUS}", f"--object-store-memory={OBJECT_STORE_BYTES}"]
    log_path = temp_dir / "ray-start.log"
    with open(log_path, "w") as log:
        head = subprocess.Popen(command, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    leftovers = []
    try:
        dashboard = f"http://127.0.0.1:{dashboard_port}"
        wait_for_dashboard(dashboard, head, log_path)
        yield dashboard
    finally:
        head.send_signal(signal.SIGTERM)
        try:
            head.wait(timeout=HEAD_STOP_SECONDS)
        except subprocess.TimeoutExpired:
            head.kill()
        leftovers = stop_processes(session_processes(head.pid, temp_dir))
        shutil.rmtree(temp_dir, ignore_errors=True)
    assert leftovers == [], f"`ray start --block` left {leftovers} after SIGTERM"


def wait_for_dashboard(address: str, head: subprocess.Popen, log_path: Path) -> None:
    """Return once the dashboard answers /api/version (what the Jobs API client checks first)."""
    deadline = time.monotonic() + HEAD_START_SECONDS
    while True:
        try:
            with urllib.request.urlopen(f"{address}/api/version", timeout=2):
                return
        except OSError:
            if head.poll() is not None:
                raise RuntimeError(f"ray start exited with {head.returncode}: {log_path.read_text()[-3000:]}") from None
            if time.monotonic() > deadline:
                raise TimeoutError(f"no Ray dashboard at {address} after {HEAD_START_SECONDS} s") from None
            time.sleep(1)


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def node_port_args() -> list[str]:
    return [f"{flag}={free_port()}" for flag in NODE_PORT_FLAGS]


def session_processes(session: int, temp_dir: Path) -> dict[int, str]:
    """pid -> command line of the live processes in `session` or working under / naming `temp_dir` (a Ray job's
    driver runs in a session of its own, in a copy of the working dir under the cluster's temp dir)."""
    found = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            stat = (entry / "stat").read_text()
            command = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace").strip()
            cwd = os.readlink(entry / "cwd")
        except OSError:  # exited meanwhile, or not ours to inspect
            continue
        state, _, _, process_session = stat[stat.rindex(")") + 2 :].split()[:4]
        ours = int(process_session) == session or str(temp_dir) in command or cwd.startswith(str(temp_dir))
        if ours and state != "Z":
            found[int(entry.name)] = command
    return found


def alive(pid: int) -> bool:
    """The process exists and is not a zombie."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat[stat.rindex(")") + 2] != "Z"


def stop_processes(processes: dict[int, str]) -> list[str]:
    """Wait for `processes` to exit, SIGKILL those that do not, by pid; the command lines of the ones killed."""
    deadline = time.monotonic() + PROCESS_EXIT_SECONDS
    while processes and time.monotonic() < deadline:
        time.sleep(0.5)
        processes = {pid: command for pid, command in processes.items() if alive(pid)}
    for pid in processes:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
    return sorted(processes.values())


def write_script(path: Path, body: str) -> None:
    path.write_text(f"#!/usr/bin/env bash\n{body}\n")
    path.chmod(0o755)


def job_summary(log: str) -> dict:
    """The JSON summary `kforge run --json` prints last."""
    match = re.search(r'^\{\n "committed_batches".*?^\}', log, re.MULTILINE | re.DOTALL)
    assert match, f"no kforge run summary in: {log[-3000:]}"
    return json.loads(match[0])
