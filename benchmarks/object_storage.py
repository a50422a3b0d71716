"""The storage layer against an S3 API server: transitions written per second and the loader's read rate, from S3 and
from a local folder, with and without `prefetch` (run by `python -m benchmarks.pipeline_speed --storage s3`).

The server is moto's standalone server in its own process on 127.0.0.1 (so it does not share this process's
interpreter lock); its latency and bandwidth are a loopback's, not a cloud store's, so the figures show the layer's
own cost per request and object, not what a region away from a bucket gives. The data are random-action windows of
sampled levels, written as kept trajectories (real states, so the compression is realistic); no expert is trained.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

import jax
import numpy as np
import tensorstore as ts

from kforge.env import ActionType, EnvParams, StaticEnvParams, random_action, reset, sample_levels, step
from kforge.pipeline.reading import TrajectoryDatasetManager
from kforge.pipeline.storage import (
    ACTION,
    DONE,
    VALID,
    BatchRecord,
    DatasetSpec,
    Geometry,
    Outcome,
    create_dataset,
    make_layout,
)
from kforge.pipeline.storage.layout import LEVEL_ID, LEVEL_SEED
from kforge.pipeline.storage.manifest import write_record
from kforge.pipeline.storage.records import ArrayEntry, LevelRecord

BUCKET = "kforge-bench"
SERVER_START_TIMEOUT_S = 60.0
RATES = ("write_transitions_per_second", "read_trajectories_per_second", "read_trajectories_per_second_prefetch")
PER_TRAJECTORY = "s3 per trajectory"
"""The S3 store read with `whole_object_bytes=0`: one range request per field and trajectory (the loader before it
read small shard objects whole), measured in the same run for comparison."""
S3_READS_METRIC = "/tensorstore/kvstore/s3/read"
"""tensorstore's count of S3 read requests (its metrics registry)."""
LOADER_BATCH = 8
"""Trajectories per loader batch."""
LOADER_BATCHES = 24
"""Timed loader batches per measurement (after one untimed batch)."""


@contextlib.contextmanager
def moto_server():
    """An S3 API server (moto) on a free port of 127.0.0.1 with one bucket; the AWS_* environment points at it."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    endpoint = f"http://127.0.0.1:{port}"
    server = subprocess.Popen(
        [sys.executable, "-m", "moto.server", "-H", "127.0.0.1", "-p", str(port)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    saved = dict(os.environ)
    try:
        deadline = time.monotonic() + SERVER_START_TIMEOUT_S
        while True:
            try:
                urllib.request.urlopen(urllib.request.Request(f"{endpoint}/{BUCKET}", method="PUT"), timeout=2)
                break
            except OSError:
                if time.monotonic() > deadline or server.poll() is not None:
                    raise RuntimeError(f"moto server on {endpoint} did not start") from None
                time.sleep(0.2)
        os.environ.update(
            AWS_ACCESS_KEY_ID="bench",
            AWS_SECRET_ACCESS_KEY="bench",
            AWS_REGION="us-east-1",
            AWS_ENDPOINT_URL=endpoint,
            AWS_EC2_METADATA_DISABLED="true",
        )
        yield f"s3://{BUCKET}"
    finally:
        os.environ.clear()
        os.environ.update(saved)
        server.terminate()
        server.wait()


def rollout_arrays(size: str, levels: int, steps: int, seed: int) -> tuple[dict[str, np.ndarray], object]:
    """(field -> (levels, ...) arrays of a level batch, layout): random-action windows of sampled levels."""
    static = StaticEnvParams.for_size(size)
    params = EnvParams()
    layout = make_layout(static, ActionType.MULTI_DISCRETE, num_steps=steps)
    level_batch = sample_levels(jax.random.split(jax.random.PRNGKey(seed), levels), static)

    def window(level, key):
        def one(state, k):
            action = random_action(k, ActionType.MULTI_DISCRETE)
            after, result = step(state, action, level, params, static, ActionType.MULTI_DISCRETE)
            return after, (state, action, result.done)

        _, (states, actions, done) = jax.lax.scan(one, reset(level), jax.random.split(key, steps))
        return states, actions, done

    keys = jax.random.split(jax.random.PRNGKey(seed + 1), levels)
    states, actions, done = jax.device_get(jax.jit(jax.vmap(window))(level_batch, keys))
    stored_states = zip((spec.name for spec in layout.state_fields), jax.tree.leaves(states), strict=True)
    given = {ACTION: np.asarray(actions), DONE: np.asarray(done), **dict(stored_states)}
    arrays = {}
    for spec in layout.fields:
        if spec.name in given:
            value = np.asarray(given[spec.name])
            arrays[spec.name] = (value if spec.per_step else value[:, 0]).astype(spec.dtype)
        else:
            arrays[spec.name] = np.zeros((levels,) + spec.full_shape(steps), spec.dtype)
    arrays[VALID] = np.ones(levels, bool)
    arrays[LEVEL_ID] = np.arange(levels, dtype=arrays[LEVEL_ID].dtype)
    arrays[LEVEL_SEED] = np.arange(levels, dtype=arrays[LEVEL_SEED].dtype)
    return arrays, layout


def array_entries(dataset, global_batch: int, arrays: dict[str, np.ndarray]) -> dict[str, ArrayEntry]:
    """The commit record's entries of a written level batch: each shard object's key, digests and size (read back,
    as the job's writer does)."""
    entries = {}
    for name, value in arrays.items():
        key = dataset.batch_key(name, global_batch)
        data = dataset.store.read(key)
        content = hashlib.sha256(np.ascontiguousarray(value).tobytes()).hexdigest()
        digest = None if data is None else hashlib.sha256(data).hexdigest()
        entries[name] = ArrayEntry(None if data is None else key, digest, content, None if data is None else len(data))
    return entries


def write_dataset(location: str, arrays: dict[str, np.ndarray], layout, batches: int) -> float:
    """Write `batches` level batches (the same arrays each) and their commit records (which read each object back to
    hash and size it, as the job's writer does); returns the seconds taken."""
    levels = len(arrays[VALID])
    geometry = Geometry(num_shards=1, batches_per_shard=batches, levels_per_batch=levels)
    dataset = create_dataset(location, DatasetSpec(layout, geometry, "bench"))
    started = time.perf_counter()
    for batch in range(batches):
        dataset.write_batch(batch, arrays)
        slots = geometry.slots(0, batch)
        record = BatchRecord(
            shard=0,
            batch=batch,
            global_batch=batch,
            slots=(slots.start, slots.stop),
            num_kept=levels,
            levels=tuple(LevelRecord(slot, Outcome.KEPT, slot, slot, None, ()) for slot in slots),
            arrays=array_entries(dataset, batch, arrays),
        )
        write_record(location, 0, batch, record)
    return time.perf_counter() - started


def s3_reads() -> int:
    """Read requests tensorstore's S3 driver has sent in this process so far."""
    metrics = ts.experimental_collect_matching_metrics(S3_READS_METRIC)
    return int(sum(value.get("value", 0) for metric in metrics for value in metric.get("values", ())))


def read_rate(location: str, prefetch: int, **loader_options) -> tuple[float, float]:
    """(trajectories per second the loader delivers, decoded and on the JAX device; S3 read requests per batch)."""
    with TrajectoryDatasetManager(
        location, batch_size=LOADER_BATCH, seed=0, prefetch=prefetch, **loader_options
    ) as manager:
        jax.block_until_ready(manager.load_next_batch().action)
        requests = s3_reads()
        started = time.perf_counter()
        for _ in range(LOADER_BATCHES):
            jax.block_until_ready(manager.load_next_batch().action)
        seconds = time.perf_counter() - started
    return LOADER_BATCHES * LOADER_BATCH / seconds, (s3_reads() - requests) / LOADER_BATCHES


def read_rates(location: str, prefetch: int, **loader_options) -> dict:
    """The loader's rates without and with prefetch, and S3 read requests per batch (0 for a local folder)."""
    rate, requests = read_rate(location, 0, **loader_options)
    return {
        "read_trajectories_per_second": rate,
        "read_trajectories_per_second_prefetch": read_rate(location, prefetch, **loader_options)[0],
        "s3_read_requests_per_batch": requests,
    }


def run(size: str, levels_per_batch: int, batches: int, steps: int, prefetch: int) -> dict:
    """Write and read the same data locally and on the S3 server; rates per store."""
    arrays, layout = rollout_arrays(size, levels_per_batch, steps, seed=0)
    transitions = batches * levels_per_batch * steps
    report = {
        "size": size,
        "levels_per_batch": levels_per_batch,
        "batches": batches,
        "window_steps": steps,
        "prefetch": prefetch,
        "stores": {},
    }
    with tempfile.TemporaryDirectory(prefix="kforge-bench-") as scratch, moto_server() as bucket:
        for store, location in (("local", str(Path(scratch) / "dataset")), ("s3", f"{bucket}/dataset")):
            seconds = write_dataset(location, arrays, layout, batches)
            report["stores"][store] = {"write_transitions_per_second": transitions / seconds}
            if store == "s3":
                report["stores"][PER_TRAJECTORY] = read_rates(location, prefetch, whole_object_bytes=0)
            report["stores"][store].update(read_rates(location, prefetch))
    for key in RATES:
        report[f"s3_over_local/{key}"] = report["stores"]["s3"][key] / report["stores"]["local"][key]
    for key in RATES[1:]:
        report[f"s3_over_per_trajectory/{key}"] = report["stores"]["s3"][key] / report["stores"][PER_TRAJECTORY][key]
    return report


def lines(report: dict) -> list[str]:
    steps = report["window_steps"]
    out = [
        f"storage benchmark, size {report['size']}: {report['batches']} level batches of {report['levels_per_batch']} "
        f"trajectories x {steps} steps; loader batches of {LOADER_BATCH}, prefetch {report['prefetch']}"
    ]
    for store, rates in report["stores"].items():
        written = rates.get("write_transitions_per_second")
        out.append(
            f"  {store:17s}: "
            + ("" if written is None else f"writes {written:10,.0f} transitions/s; ")
            + "the loader reads "
            f"{rates['read_trajectories_per_second']:7,.1f} trajectories/s "
            f"({rates['read_trajectories_per_second'] * steps:9,.0f} transitions/s), with prefetch "
            f"{rates['read_trajectories_per_second_prefetch']:7,.1f} trajectories/s; "
            f"{rates['s3_read_requests_per_batch']:.0f} S3 read requests per batch"
        )
    out.append(
        "  s3 / local: write {:.2f}x, read {:.2f}x, read with prefetch {:.2f}x".format(
            report["s3_over_local/write_transitions_per_second"],
            report["s3_over_local/read_trajectories_per_second"],
            report["s3_over_local/read_trajectories_per_second_prefetch"],
        )
    )
    out.append(
        "  s3 whole small objects / s3 per trajectory: read {:.2f}x, read with prefetch {:.2f}x".format(
            report["s3_over_per_trajectory/read_trajectories_per_second"],
            report["s3_over_per_trajectory/read_trajectories_per_second_prefetch"],
        )
    )
    return out
