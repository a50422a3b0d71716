"""One rule for exit codes in every subcommand: Ctrl-C (a real SIGINT) ends each with 130 and one line; argument and
input errors exit 2 (tests/pipeline/test_cli_fast.py; here a URL that holds no dataset, against a real S3 API server),
damaged data 1 (tests/pipeline/test_verify.py)."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from pipeline_test_helpers import as_a_terminal_job, environment

from kforge.pipeline.cli import EXIT_INTERRUPTED, EXIT_USAGE, main

REPO = Path(__file__).resolve().parents[2]
SIGINT_AFTER_SECONDS = 1.5
"""[s] Every command below is still importing JAX, compiling or playing by then on any machine."""
LONG_PLAY = ("--steps", "20000")
"""Steps for the GIF commands: minutes of frames, so that one whose programs are in the compilation cache is still
running when interrupted (a 256-step render ended before the signal once on a loaded machine)."""


def interruptible(dataset: Path, tmp: Path) -> dict[str, list[str]]:
    return {
        "verify": ["verify", str(dataset)],
        "stats": ["stats", str(dataset), "--out", str(tmp / "card")],
        "export": ["export", "--format", "kinetix", str(dataset), str(tmp / "export")],
        "levels sample": ["levels", "sample", "--size", "s", "--seed", "0", "--num", "64", "--out", str(tmp / "lv")],
        "levels preview": ["levels", "preview", "s/h0_weak_thrust", "--out", str(tmp / "h0.gif"), *LONG_PLAY],
        "render": ["render", "s/h0_weak_thrust", "--out", str(tmp / "render.gif"), *LONG_PLAY],
        "demo": ["demo", "--out", str(tmp / "demo.gif"), *LONG_PLAY],
        "bc train": ["bc", "train", str(dataset), f"output_dir={tmp / 'bc'}", "tracking.wandb=disabled"],
    }


@pytest.mark.parametrize(
    "name",
    [
        "verify",
        "stats",
        "export",
        "levels sample",
        "levels preview",
        "render",
        "demo",
        "bc train",
    ],
)
def test_sigint_exits_130_with_one_line(name, dataset_dir, tmp_path):
    argv = interruptible(dataset_dir, tmp_path)[name]
    process = subprocess.Popen(
        [sys.executable, "-m", "kforge", *argv],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=as_a_terminal_job,
    )
    time.sleep(SIGINT_AFTER_SECONDS)
    assert process.poll() is None, f"kforge {name} ended before it could be interrupted"
    process.send_signal(signal.SIGINT)
    _, err = process.communicate(timeout=120)
    assert process.returncode == EXIT_INTERRUPTED, err
    lines = err.strip().splitlines()
    assert "Traceback" not in err and len(lines) >= 1 and "interrupted" in lines[-1], err


S3_ENV = {
    "AWS_ACCESS_KEY_ID": "testing",
    "AWS_SECRET_ACCESS_KEY": "not-a-real-secret",
    "AWS_REGION": "us-east-1",
    "AWS_EC2_METADATA_DISABLED": "true",
}
BUCKET = "kforge-exit-codes"


def test_a_url_that_holds_no_dataset_exits_2_in_every_subcommand(tmp_path, capsys):
    """A prefix that holds other objects and one that holds nothing: input errors, not damaged data."""
    import boto3
    from moto.server import ThreadedMotoServer

    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    try:
        with environment(**S3_ENV, AWS_ENDPOINT_URL=f"http://{host}:{port}"):
            client = boto3.client("s3", endpoint_url=f"http://{host}:{port}", region_name=S3_ENV["AWS_REGION"])
            client.create_bucket(Bucket=BUCKET)
            client.put_object(Bucket=BUCKET, Key="notes/readme.txt", Body=b"not a dataset")
            codes = {}
            for url in (f"s3://{BUCKET}/notes", f"s3://{BUCKET}/empty"):
                for argv in (
                    ["verify", url],
                    ["stats", url, "--out", str(tmp_path / "card")],
                    ["export", "--format", "kinetix", url, str(tmp_path / "export")],
                    ["bc", "train", url, f"output_dir={tmp_path / 'bc'}", "tracking.wandb=disabled"],
                    ["run", url],
                ):
                    with pytest.raises(SystemExit) as stop:
                        main(argv)
                    codes[" ".join(argv)] = stop.value.code
                    assert url in capsys.readouterr().err.strip().splitlines()[-1]
    finally:
        server.stop()
    assert set(codes.values()) == {EXIT_USAGE}, codes
    assert not (tmp_path / "card").exists() and not (tmp_path / "export").exists() and not (tmp_path / "bc").exists()


SIGTERM_BIT = 1 << (signal.SIGTERM - 1)
"""SIGTERM's bit in the signal masks of /proc/PID/status."""
POLL_SECONDS = 0.001


def _caught_signals(pid: int) -> int:
    status = Path(f"/proc/{pid}/status").read_text()
    return int(next(line.split()[1] for line in status.splitlines() if line.startswith("SigCgt:")), 16)


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads the signal masks of Linux's /proc")
def test_a_sigterm_before_jax_is_imported_ends_the_run_with_130_and_one_line(tmp_path):
    """The kforge process catches SIGTERM from its first line of its own code, before JAX is imported (an operator's
    SIGTERM while a job starts): caught while no jaxlib library is loaded, it ends the run as Ctrl-C does."""
    process = subprocess.Popen(
        [sys.executable, "-m", "kforge", "run", "1M/s", "--scale", "tiny", f"output_dir={tmp_path / 'data'}"],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        while process.poll() is None and not _caught_signals(process.pid) & SIGTERM_BIT:
            time.sleep(POLL_SECONDS)
        assert process.poll() is None, "kforge run ended before it caught SIGTERM"
        jax_loaded = "jaxlib" in Path(f"/proc/{process.pid}/maps").read_text()
        process.send_signal(signal.SIGTERM)
        _, err = process.communicate(timeout=120)
    finally:
        process.kill()
    assert not jax_loaded, "SIGTERM was caught only once JAX was imported"
    assert process.returncode == EXIT_INTERRUPTED, err
    lines = err.strip().splitlines()
    assert "Traceback" not in err and len(lines) >= 1 and "interrupted" in lines[-1], err
