"""Shared data for the storage tests: a batch of hand-built size-s levels rolled out for 256 steps with random actions.

Levels (all have a motorised arm pinned to the floor and a thruster, so joint impulses and contacts vary):
- 0, 1: a green disc dropped onto a static blue disc from two heights -> every episode ends in success (kept);
- 2: the green disc dropped onto a static red disc -> every episode fails (not kept, "unsolved").
The rollout runs once per test session.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import zarr

from kforge.engine import SceneBuilder
from kforge.env import ActionType, EnvParams, Role, StaticEnvParams, random_action
from kforge.env.level_builder import build_level
from kforge.pipeline.generation import load_config, to_yaml
from kforge.pipeline.generation.run import run_job
from kforge.pipeline.storage import PROVENANCE, Lease, all_committed, iter_records, open_store
from kforge.pipeline.storage.layout import make_layout
from kforge.pipeline.storage.lease import LEASE_KEY, LeaseHeld, LeaseHolder, read_holder
from kforge.pipeline.storage.records import Outcome
from kforge.pipeline.storage.shard_store import DatasetSpec, Geometry, create_dataset
from kforge.pipeline.storage.writer import BatchTrajectories, write_level_batch
from tests.helpers import stack
from tests.rollouts import env_loop

# Test modules import these helpers as `pipeline_test_helpers` (works under every pytest import mode).
sys.modules["pipeline_test_helpers"] = sys.modules[__name__]

STATIC = StaticEnvParams.for_size("s")
PARAMS = EnvParams()
ACTION_TYPE = ActionType.MULTI_DISCRETE
NUM_STEPS = 256
FLOOR_TOP = 0.4  # [m]
RADIUS = 0.2  # [m] green and target discs
FLOOR = 0  # body index of the static floor (a Kinetix boundary)
DROP_HEIGHTS = (1.0, 1.6)  # [m] gap between the green disc's bottom and the target disc's top, levels 0 and 1


def drop_level(gap: float, target: Role):
    """A green disc `gap` above a static target disc on the floor; a motorised arm pinned to the floor, a thruster."""
    scene = SceneBuilder(STATIC.sim)
    target_y = FLOOR_TOP + RADIUS
    green = scene.add_circle((1.0, target_y + 2 * RADIUS + gap), RADIUS)
    blue = scene.add_circle((1.0, target_y), RADIUS, static=True)
    arm = scene.add_box((3.9, FLOOR_TOP + 0.3), (0.8, 0.1))
    scene.add_revolute_joint(FLOOR, arm, (3.5, FLOOR_TOP + 0.3), motor_speed=1.0, motor_power=1.0, motor_on=True)
    scene.add_thruster(arm, (4.2, FLOOR_TOP + 0.3), jnp.pi / 2, power=0.5)
    return build_level(scene, roles={green: Role.GREEN, blue: target})


def rollout(levels, seed: int = 0):
    """(states (L, T), actions, done, success) of random-action windows from each level's start.

    Steps with the jitted `env.step` one state at a time (`env_loop`), so the only compiled program is the one the
    replay test uses too.
    """
    num_levels = jax.tree.leaves(levels)[0].shape[0]
    keys = jax.random.split(jax.random.PRNGKey(seed), (num_levels, NUM_STEPS))
    actions = np.asarray(jax.vmap(jax.vmap(random_action, in_axes=(0, None)), in_axes=(0, None))(keys, ACTION_TYPE))
    windows = []
    for index in range(num_levels):
        level = jax.tree.map(lambda x, i=index: x[i], levels)
        states, results = env_loop(level, actions[index], PARAMS, STATIC, ACTION_TYPE)
        windows.append((states, np.asarray(results.done), np.asarray(results.success)))
    states = jax.tree.map(np.asarray, stack(*(w[0] for w in windows)))
    return states, actions, np.stack([w[1] for w in windows]), np.stack([w[2] for w in windows])


@pytest.fixture(scope="session")
def levels():
    return stack(
        drop_level(DROP_HEIGHTS[0], Role.BLUE), drop_level(DROP_HEIGHTS[1], Role.BLUE), drop_level(1.0, Role.RED)
    )


@pytest.fixture(scope="session")
def rolled_out(levels):
    return rollout(levels)


def batch_result(rolled_out, level_ids=(10, 11, 12)) -> BatchTrajectories:
    """The rollout as a level batch: levels 0 and 1 kept, level 2 "unsolved"."""
    states, action, done, success = rolled_out
    kept = np.array([True, True, False])
    return BatchTrajectories(
        states=states,
        action=action,
        done=done,
        success=success,
        kept=kept,
        level_id=np.asarray(level_ids),
        level_seed=np.asarray(level_ids) * 1000 + 7,
        expert_success_rate=np.array([1.0, 0.75, 0.0], np.float32),
        outcome=(Outcome.KEPT, Outcome.KEPT, "unsolved"),
        expert_env_steps=np.array([2000, 1000, 4000]),
    )


GEOMETRY = Geometry(num_shards=2, batches_per_shard=2, levels_per_batch=3)
"""Four level batches of three levels; each batch stores the rollout (two kept trajectories)."""


def dataset_spec(**overrides) -> DatasetSpec:
    values = {
        "layout": make_layout(STATIC, ACTION_TYPE, NUM_STEPS),
        "geometry": GEOMETRY,
        "split": "train",
        "attributes": {"config_hash": "test"},
    }
    return DatasetSpec(**(values | overrides))


def write_all(root, rolled_out):
    """A complete dataset: batch g holds the rollout with level ids 10 g + (0, 1, 2)."""
    dataset = create_dataset(root, dataset_spec())
    for shard in range(GEOMETRY.num_shards):
        for batch in range(GEOMETRY.batches_per_shard):
            g = GEOMETRY.global_batch(shard, batch)
            write_level_batch(dataset, shard, batch, batch_result(rolled_out, (10 * g, 10 * g + 1, 10 * g + 2)))
    return dataset


@pytest.fixture(scope="session")
def dataset_dir(tmp_path_factory, rolled_out):
    """A complete dataset, shared read-only by the tests (copy it before changing anything)."""
    root = tmp_path_factory.mktemp("dataset")
    write_all(root, rolled_out)
    return root


TINY_JOB = [
    "split.name=test/s",
    "split.size=s",
    "split.num_levels=6",
    "split.expert_budget=256",
    "work.levels_per_shard=4",
    "work.levels_per_batch=2",
    "ppo.num_envs=4",
    "ppo.num_steps=16",
    "ppo.num_minibatches=2",
    "ppo.update_epochs=1",
    "ppo.select_episodes=2",
    "collect.window_steps=24",
    "filter.noop_steps=24",
    "compile_cache.dir=null",
]
"""A job small enough for tests: 6 levels in 2 shards of 2 level batches; every test uses these shapes, so the
training and rollout programs compile once per test session. No persistent compilation cache: the suite writes
nothing into the user's cache, and the tests that interrupt a job keep the time it takes to compile as their window."""


def tiny_job(output_dir, *extra):
    return load_config(None, [f"output_dir={output_dir}", *TINY_JOB, *extra])


def run_in_process(job, max_batches=None) -> dict:
    """The job run without Ray (`ray.num_workers=0`): its summary."""
    in_process = dataclasses.replace(job, ray=dataclasses.replace(job.ray, num_workers=0))
    return run_job(in_process, max_batches=max_batches, show_progress=False, report=lambda line: None)


@pytest.fixture(scope="session")
def uninterrupted(tmp_path_factory):
    """The tiny job run once without interruption, in-process: the dataset that interrupted, resumed, repaired, grown
    or raced runs must equal (shared read-only by the tests: copy it before changing anything)."""
    root = tmp_path_factory.mktemp("uninterrupted")
    run_in_process(tiny_job(root))
    return root


KEEPING_JOB = [
    *(item for item in TINY_JOB if not item.startswith(("split.num_levels=", "work.", "compile_cache."))),
    "split.num_levels=64",
    "split.seed=10",
    "work.levels_per_shard=32",
    "work.levels_per_batch=16",
    "filter.enabled=false",
]
"""The job of the kill-and-resume tests and of benchmarks/chaos.py: the tiny job's training over 64 levels in 2
shards of 2 level batches of 16, without the trivial-level filter, at split seed 10, where its 4 level batches keep
3, 4, 3 and 3 trajectories (seeds 1, 4 and 8 keep at least 2 per batch too; 0, 2, 3, 5, 6, 7, 9 and 11 do not), so
every kill is checked on stored trajectories (`assert_keeps_in_every_batch`)."""
KEEPING_BATCHES = 4
MIN_KEPT_PER_BATCH = 2


def keeping_job(output_dir, compile_cache, *extra):
    """`KEEPING_JOB` writing to `output_dir`, its programs in the test session's compilation cache."""
    return load_config(None, [f"output_dir={output_dir}", *KEEPING_JOB, f"compile_cache.dir={compile_cache}", *extra])


@pytest.fixture(scope="session")
def keeping_cache(tmp_path_factory):
    """A compilation cache for `KEEPING_JOB`'s programs, shared by the test session's job processes (each would
    compile them for minutes otherwise; a killed job still has its training and writing as its window)."""
    return tmp_path_factory.mktemp("keeping-cache")


@pytest.fixture(scope="session")
def uninterrupted_keeping(tmp_path_factory, keeping_cache):
    """`KEEPING_JOB` run once without interruption, as a `kforge run` process (it fills `keeping_cache`): the dataset
    the kill-and-resume tests must end with (shared read-only)."""
    root = tmp_path_factory.mktemp("uninterrupted-keeping") / "dataset"
    config_file = root.parent / "job.yaml"
    config_file.write_text(to_yaml(keeping_job(root, keeping_cache, "ray.num_workers=0")))
    run_job_process(config_file)
    assert_keeps_in_every_batch(root)
    return root


def assert_keeps_in_every_batch(root) -> None:
    """Every level batch of the dataset is committed and keeps at least `MIN_KEPT_PER_BATCH` trajectories."""
    kept = {(record.shard, record.batch): record.num_kept for record in iter_records(root)}
    assert len(kept) == KEEPING_BATCHES, kept
    assert min(kept.values()) >= MIN_KEPT_PER_BATCH, kept


def batch_file(dataset, name: str, global_batch: int) -> Path:
    """The local file of a level batch's shard object in field `name`'s array (tests that damage files)."""
    return Path(dataset.root) / dataset.batch_key(name, global_batch)


def session_processes(session: int) -> list[int]:
    """Pids of the live processes of a Unix session (the job's driver and everything Ray started under it)."""
    pids = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (FileNotFoundError, ProcessLookupError, IndexError):
            continue
        if int(fields[3]) == session and fields[0] != "Z":  # fields after ")": state, ppid, pgrp, session
            pids.append(int(stat.parent.name))
    return pids


def actor_processes(session: int, title: str = "ray::Worker") -> list[int]:
    """Pids of the processes of a Unix session whose title starts with `title` (Ray titles an actor's process
    "ray::<class>", followed by the method it runs: "ray::Worker", "ray::Coordinator")."""
    pids = []
    for pid in session_processes(session):
        with contextlib.suppress(OSError):
            if Path(f"/proc/{pid}/cmdline").read_bytes().startswith(title.encode()):
                pids.append(pid)
    return sorted(pids)


def kill_session(session: int) -> None:
    """SIGKILL every process of the session (a job killed without warning), and wait until they are gone."""
    deadline = time.monotonic() + KILL_WAIT_SECONDS
    while (pids := session_processes(session)) and time.monotonic() < deadline:
        for pid in pids:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        time.sleep(0.1)
    assert not session_processes(session), "processes of the killed job survived"


KILL_WAIT_SECONDS = 30.0
POLL_SECONDS = 0.05
JOB_TIMEOUT_SECONDS = 900.0


def as_a_terminal_job() -> None:
    """`preexec_fn` of a job the test interrupts: default SIGINT handling, as a shell gives a foreground command (an
    ignored SIGINT is inherited across exec, so a test run started in the background would pass it on)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def run_job_process(config_file: Path, until=None) -> str:
    """Run `python -m kforge run` in a session of its own; with `until`, SIGKILL the whole session as soon as
    `until()` holds (the job dies mid-work), else wait for it to finish and check it succeeded."""
    process = subprocess.Popen(
        [sys.executable, "-m", "kforge", "run", str(config_file), "--no-progress"],
        start_new_session=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        env={**os.environ, "RAY_AUTH_MODE": "disabled"},
    )
    deadline = time.monotonic() + JOB_TIMEOUT_SECONDS
    try:
        while process.poll() is None and time.monotonic() < deadline:
            if until is not None and until():
                kill_session(process.pid)
                process.wait()
                return ""
            time.sleep(POLL_SECONDS)
        output = process.communicate(timeout=KILL_WAIT_SECONDS)[0].decode(errors="replace")
        assert until is None, f"the job ended before the kill point:\n{output[-3000:]}"
        assert process.returncode == 0, output[-3000:]
        return output
    finally:
        kill_session(process.pid)


def start_job(config_file: Path, *options: str) -> subprocess.Popen:
    """`python -m kforge run CONFIG --no-progress [options]` started in a session of its own, stdout and stderr piped
    (the test signals it or its Ray processes, then `communicate`s)."""
    return subprocess.Popen(
        [sys.executable, "-m", "kforge", "run", str(config_file), "--no-progress", *options],
        start_new_session=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env={**os.environ, "RAY_AUTH_MODE": "disabled"},
    )


def json_summary(stdout: bytes) -> dict:
    """The summary that `kforge run --json` printed last."""
    text = stdout.decode()
    return json.loads(text[text.index("{\n") :])


def committed_count(root: Path) -> int:
    """Committed level batches of a local dataset (0 before its manifest exists)."""
    return sum(map(len, all_committed(root).values())) if (root / "manifest").is_dir() else 0


def kill_at_points(config_file: Path, kill_points: dict, stale_after_s: float = 0.0) -> None:
    """Run the job once per kill point (name -> predicate on the dataset), SIGKILLing its session as soon as the
    point is reached; each point must not hold before its run and must hold after it. After each kill, wait
    `stale_after_s` (the job's lease stale limit) so that the next run may take the killed job's lease over."""
    for where, reached in kill_points.items():
        assert not reached(), f"already past the kill point '{where}' before the run"
        run_job_process(config_file, until=reached)
        assert reached(), where
        time.sleep(stale_after_s)


def dataset_contents(root):
    """Every stored array and every commit record of a dataset directory."""
    group = zarr.open_group(str(root / "data"), mode="r")
    arrays = {name: np.asarray(array[...]) for name, array in group.arrays()}
    for name, array in group.groups():
        arrays.update({f"{name}/{k}": np.asarray(v[...]) for k, v in array.arrays()})
    records = sorted(
        json.dumps({key: value for key, value in record.to_json().items() if key != PROVENANCE}, sort_keys=True)
        for record in iter_records(root)
    )
    return arrays, records


def assert_same_dataset(first, second):
    arrays_a, records_a = dataset_contents(first)
    arrays_b, records_b = dataset_contents(second)
    assert sorted(arrays_a) == sorted(arrays_b)
    for name in arrays_a:
        np.testing.assert_array_equal(arrays_a[name], arrays_b[name], err_msg=name)
    assert records_a == records_b


def jax_leaves(tree) -> list:
    return jax.tree.leaves(tree)


def assert_same_batches(first, second) -> None:
    """Two loaders give the same batches for one epoch and the first batch of the next."""
    assert first.length == second.length > 0
    for _ in range(first.batches_per_epoch + 1):
        a, b = first.load_next_batch(), second.load_next_batch()
        np.testing.assert_array_equal(a.trajectory_index, b.trajectory_index)
        for x, y in zip(
            [a.action, a.done, a.action_mask, *jax_leaves(a.env_state)],
            [b.action, b.done, b.action_mask, *jax_leaves(b.env_state)],
            strict=True,
        ):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def assert_lease_refuses_and_takes_over(url: str) -> None:
    """On the dataset `url`: a second job is refused while the first holds the lease, the lease is gone after it,
    and a crashed job's stale lease is taken over with a message."""
    with Lease.acquire(url, job_id="first", heartbeat_s=60) as lease:
        assert read_holder(url) == lease.holder
        with pytest.raises(LeaseHeld, match=r"in use by job first \(host .*, pid \d+\), last heartbeat \d+ s ago"):
            Lease.acquire(url, job_id="second")
        assert read_holder(url) == lease.holder
    assert read_holder(url) is None
    an_hour_ago = time.time() - 3600
    open_store(url).write(LEASE_KEY, LeaseHolder("elsewhere", 1, "crashed", an_hour_ago, an_hour_ago).to_bytes())
    messages = []
    with Lease.acquire(url, job_id="third", log=messages.append):
        assert read_holder(url).job_id == "third"
    assert len(messages) == 1
    assert messages[0].startswith(f"{url}: taking over the stale lease of job crashed (host elsewhere, pid 1)")
    assert read_holder(url) is None


@contextlib.contextmanager
def environment(**values: str):
    """Set environment variables for the duration, then restore them as they were."""
    saved = {name: os.environ.get(name) for name in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value
