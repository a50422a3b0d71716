"""Datasets on object storage, against a real S3 API server (moto's standalone server on 127.0.0.1): a tiny job
writes to `s3://`, verify passes and names a flipped byte, the loader, the Kinetix export and import, `kforge levels
export` and `kforge stats` read the same data as from a local copy, the lease works there too; slow: the whole job
killed mid-run and resumed equals an uninterrupted run."""

from __future__ import annotations

import dataclasses
import json
import os
import time
from pathlib import Path

import numpy as np
import pytest
import tensorstore as ts
from pipeline_test_helpers import (
    KEEPING_BATCHES,
    assert_keeps_in_every_batch,
    assert_lease_refuses_and_takes_over,
    assert_same_batches,
    environment,
    jax_leaves,
    keeping_job,
    run_in_process,
    run_job_process,
    tiny_job,
    write_all,
)

from kforge.pipeline.cli.levels import main as levels_main
from kforge.pipeline.cli.verify import main as verify_main
from kforge.pipeline.generation import ConfigError, ResumeRefused, load_config, run_job, to_yaml
from kforge.pipeline.kinetix import export_kinetix, load_kinetix_levels
from kforge.pipeline.reading import TrajectoryDatasetManager
from kforge.pipeline.reading.loader import WHOLE_OBJECT_BYTES
from kforge.pipeline.reading.stats import collect_stats
from kforge.pipeline.storage import (
    Lease,
    LeaseLost,
    Store,
    iter_records,
    open_dataset,
    read_record_json,
    record_key,
)
from kforge.pipeline.storage.layout import DatasetError
from kforge.pipeline.storage.lease import LEASE_KEY, read_holder
from kforge.pipeline.storage.manifest import commit_record, remove_record
from kforge.pipeline.storage.verify import verify_dataset

BUCKET = "kforge-test"
S3_ENV = {
    "AWS_ACCESS_KEY_ID": "testing",
    "AWS_SECRET_ACCESS_KEY": "not-a-real-secret",
    "AWS_REGION": "us-east-1",
    "AWS_EC2_METADATA_DISABLED": "true",
}


@pytest.fixture(scope="session")
def s3():
    """A moto S3 server on 127.0.0.1 (a free port) with one bucket; the AWS_* environment points at it."""
    from moto.server import ThreadedMotoServer

    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    endpoint = f"http://{host}:{port}"
    import boto3

    with environment(**S3_ENV, AWS_ENDPOINT_URL=endpoint):
        client = boto3.client("s3", endpoint_url=endpoint, region_name=S3_ENV["AWS_REGION"])
        client.create_bucket(Bucket=BUCKET)
        yield client
    server.stop()


def keys(client, prefix: str) -> list[str]:
    pages = client.get_paginator("list_objects_v2").paginate(Bucket=BUCKET, Prefix=prefix)
    return sorted(item["Key"] for page in pages for item in page.get("Contents", ()))


def download(client, prefix: str, target: Path) -> Path:
    """A local copy of everything below `s3://BUCKET/prefix/`."""
    for key in keys(client, f"{prefix}/"):
        path = target / key.removeprefix(f"{prefix}/")
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(client.get_object(Bucket=BUCKET, Key=key)["Body"].read())
    return target


def upload(client, folder: Path, prefix: str) -> str:
    """Every file below a local folder put below `s3://BUCKET/prefix/`; the URL."""
    for path in folder.rglob("*"):
        if path.is_file():
            key = f"{prefix}/{path.relative_to(folder).as_posix()}"
            client.put_object(Bucket=BUCKET, Key=key, Body=path.read_bytes())
    return f"s3://{BUCKET}/{prefix}"


def copy_prefix(client, source: str, target: str) -> None:
    for key in keys(client, f"{source}/"):
        client.copy_object(
            Bucket=BUCKET, Key=target + key.removeprefix(source), CopySource={"Bucket": BUCKET, "Key": key}
        )


@pytest.fixture(scope="session")
def s3_dataset(s3, tmp_path_factory):
    """(URL, local copy) of a tiny job's dataset generated straight to S3."""
    url = f"s3://{BUCKET}/tiny"
    run_in_process(tiny_job(url))
    return url, download(s3, "tiny", tmp_path_factory.mktemp("s3-copy"))


@pytest.fixture(scope="session")
def s3_trajectories(s3, rolled_out, tmp_path_factory):
    """(URL, local copy) of the hand-built dataset with kept trajectories (`write_all`), written straight to S3 (the
    tiny job's experts are too briefly trained to keep any)."""
    url = f"s3://{BUCKET}/handbuilt"
    write_all(url, rolled_out)
    return url, download(s3, "handbuilt", tmp_path_factory.mktemp("s3-handbuilt"))


def test_a_tiny_job_on_s3_commits_everything_verifies_and_leaves_no_lease(s3, s3_dataset, capsys):
    url, _ = s3_dataset
    stored = keys(s3, "tiny/")
    assert "tiny/data/zarr.json" in stored and "tiny/config.yaml" in stored and f"tiny/{LEASE_KEY}" not in stored
    assert len([key for key in stored if key.startswith("tiny/manifest/")]) == 4
    assert all(report.ok for report in verify_dataset(url))
    verify_main([url], prog="kforge verify")
    assert "bad shards: none" in capsys.readouterr().out
    endpoint = os.environ["AWS_ENDPOINT_URL"]
    for key in stored:
        if key.endswith((".json", ".yaml")):
            text = s3.get_object(Bucket=BUCKET, Key=key)["Body"].read().decode()
            assert endpoint.split("//")[1] not in text and S3_ENV["AWS_SECRET_ACCESS_KEY"] not in text, key


def test_a_location_with_an_unknown_scheme_or_no_bucket_is_named():
    from kforge.pipeline.storage import StoreError, open_store

    with pytest.raises(StoreError, match="ftp://host/x: unsupported URL scheme"):
        open_store("ftp://host/x")
    with pytest.raises(StoreError, match="s3:///x: no bucket in the URL"):
        open_store("s3:///x")


def s3_reads() -> int:
    """Read requests tensorstore's S3 driver has sent from this process (its metrics registry)."""
    metrics = ts.experimental_collect_matching_metrics("/tensorstore/kvstore/s3/read")
    return int(sum(value.get("value", 0) for metric in metrics for value in metric.get("values", ())))


def test_the_loader_reads_the_same_batches_from_s3_as_from_a_local_copy(s3_trajectories):
    """Slot by slot (`whole_object_bytes=0`) and reading the small shard objects whole, with and without prefetch;
    whole objects take fewer requests."""
    url, local = s3_trajectories
    requests = {}
    for prefetch, whole_object_bytes in ((0, 0), (0, WHOLE_OBJECT_BYTES), (2, WHOLE_OBJECT_BYTES)):
        before = s3_reads()
        with (
            TrajectoryDatasetManager(
                url, batch_size=2, seed=3, prefetch=prefetch, whole_object_bytes=whole_object_bytes
            ) as remote,
            TrajectoryDatasetManager(local, batch_size=2, seed=3) as here,
        ):
            assert_same_batches(remote, here)
        requests[prefetch, whole_object_bytes] = s3_reads() - before
    assert requests[0, WHOLE_OBJECT_BYTES] < requests[0, 0]


def test_kinetix_export_reads_from_s3(s3_trajectories, tmp_path):
    url, local = s3_trajectories
    remote = export_kinetix(url, tmp_path / "from-s3", show_progress=False)
    here = export_kinetix(local, tmp_path / "from-local", show_progress=False)
    kept = sum(len(record.kept_slots) for record in iter_records(url))
    assert remote.num_trajectories == here.num_trajectories == kept > 0
    files = sorted(p.relative_to(remote.group) for p in remote.group.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(here.group) for p in here.group.rglob("*") if p.is_file())
    chunks = [f for f in files if not f.name.startswith(".z")]  # attributes name the source; chunks must match
    assert chunks and all((remote.group / f).read_bytes() == (here.group / f).read_bytes() for f in chunks)


def test_kinetix_import_reads_a_split_and_a_shard_from_s3(s3, s3_trajectories, tmp_path):
    url, _ = s3_trajectories
    local = export_kinetix(url, tmp_path, trajectories_per_shard=3, show_progress=False)
    remote = upload(s3, local.group, "kinetix-split")
    assert len(local.shard_sizes) > 1
    for here, there in ((local.group, remote), (local.group / "shard-000001", f"{remote}/shard-000001")):
        a, b = load_kinetix_levels(here), load_kinetix_levels(there)
        assert a.static == b.static
        for x, y in zip(jax_leaves(a), jax_leaves(b), strict=True):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    with pytest.raises(DatasetError, match=f"{remote}/nothing: neither a Kinetix-Offline split"):
        load_kinetix_levels(f"{remote}/nothing")


def test_levels_export_and_run_read_a_dataset_config_from_s3(s3_dataset, tmp_path, capsys):
    url, local = s3_dataset
    remote, local_job = load_config(url), load_config(local)
    assert load_config(f"{url}/config.yaml") == remote and load_config(local / "config.yaml") == local_job
    # A remote dataset's config says nothing of where the job runs: the dataset is the output, the rest the defaults.
    defaults = {
        "ray": type(remote.ray)(),
        "tracking": type(remote.tracking)(),
        "compile_cache": type(remote.compile_cache)(),
    }
    assert remote.output_dir == url and remote.compile_cache == defaults["compile_cache"]
    assert (remote.ray.address, remote.tracking.dir) == (defaults["ray"].address, defaults["tracking"].dir)
    assert remote == dataclasses.replace(
        local_job,
        output_dir=url,
        compile_cache=remote.compile_cache,
        ray=dataclasses.replace(local_job.ray, address=remote.ray.address),
        tracking=dataclasses.replace(local_job.tracking, dir=remote.tracking.dir),
    )
    outputs = []
    for index, config in enumerate((url, str(local / "config.yaml"))):
        out = tmp_path / str(index)
        levels_main(["export", config, "1", "4", "--out", str(out), "--no-progress"])
        outputs.append({path.name: path.read_bytes() for path in sorted(out.iterdir())})
    assert list(outputs[0]) == ["level-0000001.json", "level-0000004.json"] and outputs[0] == outputs[1]
    with pytest.raises(ConfigError, match=f"config file not found: {url}-missing/config.yaml"):
        load_config(f"{url}-missing")


def test_stats_on_s3_sizes_objects_from_the_records_and_reads_them_only_for_older_records(
    s3, s3_trajectories, monkeypatch
):
    """Records written now carry each data object's size, so stats reads no data object; records without sizes
    (written before they were recorded) still give the same bytes, by reading the objects."""
    url, _ = s3_trajectories
    listed = {}
    for page in s3.get_paginator("list_objects_v2").paginate(Bucket=BUCKET, Prefix="handbuilt/"):
        listed.update({item["Key"].removeprefix("handbuilt/"): item["Size"] for item in page.get("Contents", ())})
    expected = sum(size for key, size in listed.items() if key.startswith("data/"))
    sized = []
    real_size = Store.size
    monkeypatch.setattr(Store, "size", lambda store, key: sized.append(key) or real_size(store, key))
    stats = collect_stats(url, show_progress=False)
    assert stats.data_bytes == expected
    assert stats.manifest_bytes == sum(size for key, size in listed.items() if key.startswith("manifest/"))
    data_objects = {file for record in iter_records(url) for file in record.object_sizes}
    assert data_objects and not data_objects & set(sized)  # only the arrays' zarr.json metadata are read

    copy_prefix(s3, "handbuilt", "unsized")
    for key in keys(s3, "unsized/manifest/"):
        record = json.loads(s3.get_object(Bucket=BUCKET, Key=key)["Body"].read())
        for entry in record["arrays"].values():
            entry.pop("size", None)
        s3.put_object(Bucket=BUCKET, Key=key, Body=json.dumps(record, indent=1, sort_keys=True).encode())
    sized.clear()
    old = collect_stats(f"s3://{BUCKET}/unsized", show_progress=False)
    assert all(size is None for record in iter_records(old.root) for size in record.object_sizes.values())
    assert old.data_bytes == expected and data_objects <= set(sized)


def test_a_flipped_byte_in_one_object_is_found_by_verify_and_named(s3, s3_trajectories, capsys):
    copy_prefix(s3, "handbuilt", "flipped")
    url = f"s3://{BUCKET}/flipped"
    key = next(k for k in keys(s3, "flipped/data/action/c/") if k.count("/") > 3)
    data = bytearray(s3.get_object(Bucket=BUCKET, Key=key)["Body"].read())
    data[len(data) // 2] ^= 0xFF
    s3.put_object(Bucket=BUCKET, Key=key, Body=bytes(data))
    with pytest.raises(SystemExit) as exit_info:
        verify_main([url], prog="kforge verify")
    assert exit_info.value.code == 1
    out = capsys.readouterr().out
    relative = key.removeprefix("flipped/")
    assert f"action: file {relative} sha256 mismatch" in out
    global_batch = int(relative.split("/")[3])
    assert f"shard-{global_batch // 2:06d}: BAD" in out


def test_the_lease_on_s3_refuses_a_second_job_and_is_taken_over_when_stale(s3):
    assert_lease_refuses_and_takes_over(f"s3://{BUCKET}/leased")


def test_the_lease_on_s3_is_gone_after_an_error(s3, s3_dataset):
    url = f"s3://{BUCKET}/erring"
    copy_prefix(s3, "tiny", "erring")
    with pytest.raises(ResumeRefused):
        run_job(tiny_job(url, "split.seed=1"), show_progress=False)
    assert read_holder(url) is None and keys(s3, "erring/manifest/")


def test_readers_take_no_lease_and_see_only_committed_batches_while_a_job_writes(s3, s3_trajectories, tmp_path):
    """A job holds the lease and has written a level batch's data but not its record: the loader, stats, verify
    and the export read the three committed batches and leave the lease as it is."""
    copy_prefix(s3, "handbuilt", "writing")
    url = f"s3://{BUCKET}/writing"
    uncommitted = next(iter_records(url))
    s3.delete_object(Bucket=BUCKET, Key=f"writing/{record_key(uncommitted.shard, uncommitted.batch)}")
    committed = sorted(slot for record in iter_records(url) for slot in record.kept_slots)
    assert len(committed) == 6 and not set(uncommitted.kept_slots) & set(committed)
    with Lease.acquire(url, job_id="writer", heartbeat_s=60) as lease:
        with TrajectoryDatasetManager(url, batch_size=2, seed=0) as loader:
            assert sorted(loader.slots.tolist()) == committed
            seen = {
                int(slot) for _ in range(loader.batches_per_epoch) for slot in loader.load_next_batch().trajectory_index
            }
            assert seen == set(committed)
        assert collect_stats(url, show_progress=False).batches_committed == 3
        assert export_kinetix(url, tmp_path, show_progress=False).num_trajectories == 6
        reports = verify_dataset(url, allow_incomplete=True)
        assert all(report.ok for report in reports) and sum(len(report.committed) for report in reports) == 3
        assert read_holder(url) == lease.holder
    assert read_holder(url) is None


def test_s3_honours_the_conditional_create(s3):
    """moto answers `If-None-Match: *` on an existing key with 412, so the lease's create is atomic there."""
    from kforge.pipeline.storage import open_store

    store = open_store(f"s3://{BUCKET}/conditional")
    assert store.create_exclusive("object", b"first") is not None
    assert store.create_exclusive("object", b"second") is None
    assert store.read("object") == b"first"


@pytest.mark.slow
def test_a_job_killed_mid_run_on_s3_and_resumed_equals_an_uninterrupted_run(
    s3, uninterrupted_keeping, keeping_cache, tmp_path
):
    url = f"s3://{BUCKET}/killed"
    config_file = tmp_path / "job.yaml"
    # The killed job leaves its lease behind: the resumed run takes it over once its heartbeat is a second old.
    job = keeping_job(url, keeping_cache, "lease.stale_after_s=1", "lease.heartbeat_s=0.25")
    config_file.write_text(to_yaml(job))
    run_job_process(config_file, until=lambda: len(keys(s3, "killed/manifest/")) >= 1)
    assert 1 <= len(keys(s3, "killed/manifest/")) < KEEPING_BATCHES
    assert f"killed/{LEASE_KEY}" in keys(s3, "killed/")
    output = run_job_process(config_file)
    assert "taking over the stale lease" in output
    assert f"killed/{LEASE_KEY}" not in keys(s3, "killed/")
    assert_keeps_in_every_batch(url)
    assert all(report.ok for report in verify_dataset(url))
    assert_same_contents(url, str(uninterrupted_keeping))  # the same bytes as the local uninterrupted run


def assert_same_contents(first: str, second: str) -> None:
    """Every array and every commit record (without provenance) of two datasets are equal."""
    a, b = open_dataset(first), open_dataset(second)
    assert a.spec.to_json() == b.spec.to_json()
    slots = range(a.geometry.num_slots)
    for spec in a.layout.fields:
        np.testing.assert_array_equal(a.read([spec.name], slots)[spec.name], b.read([spec.name], slots)[spec.name])
    records = [[dataclasses.replace(r, provenance=None) for r in iter_records(root)] for root in (first, second)]
    assert records[0] == records[1]


def test_commits_on_s3_are_fenced_a_record_is_never_overwritten_and_a_garbage_lease_is_lost(s3):
    """The fences of `test_fencing.py` on S3: a commit is a conditional create, an uncommit removes only the record
    it read (`If-Match`), and a lease overwritten with garbage is a lost lease, not a failed heartbeat."""
    url = f"s3://{BUCKET}/fenced"
    assert commit_record(url, 0, 1, {"shard": 0, "batch": 1, "by": "first"}) is not None
    assert commit_record(url, 0, 1, {"shard": 0, "batch": 1, "by": "second"}) is None
    assert read_record_json(url, 0, 1)["by"] == "first"
    assert remove_record(url, 0, 1) and not remove_record(url, 0, 1)
    with Lease.acquire(url, job_id="mine", heartbeat_s=0.05) as lease:
        s3.put_object(Bucket=BUCKET, Key=f"fenced/{LEASE_KEY}", Body=b"garbage")
        deadline = time.monotonic() + 30
        while lease.lost is None and time.monotonic() < deadline:
            time.sleep(0.02)
        with pytest.raises(LeaseLost, match="overwritten by an unreadable lease"):
            lease.fence()
