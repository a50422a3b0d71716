"""JAX's persistent compilation cache (`compile_cache.dir`): a re-run loads the workers' programs, same data."""

import os
import subprocess
import sys

import pytest
from pipeline_test_helpers import tiny_job

from kforge.pipeline.generation import load_config, resolve, to_yaml
from kforge.pipeline.generation.compile_cache import cache_folder
from kforge.pipeline.storage import iter_records
from tests.conftest import COMPILATION_CACHE_VARIABLES

JOB_TIMEOUT_SECONDS = 1800  # [s] a busy 2-core machine compiles slowly
CACHE_ENTRY_SUFFIX = "-cache"
"""Name ending of JAX's cache entries (one per compiled program)."""
TRAIN_PROGRAM_ENTRY = "jit_train-"
"""Name start of the fixed-budget training program's entry (the longest compile of a level batch)."""


def run_job_in_subprocess(tmp_path, name: str, *overrides) -> list:
    """`kforge run` of a two-level job in a fresh process; the data digests of its commit records."""
    output = tmp_path / name
    config_file = tmp_path / f"{name}.yaml"
    job = tiny_job(output, "split.num_levels=2", "work.levels_per_shard=2", *overrides)
    config_file.write_text(to_yaml(job))
    command = [sys.executable, "-m", "kforge", "run", str(config_file), "--no-progress"]
    environment = {k: v for k, v in os.environ.items() if k not in COMPILATION_CACHE_VARIABLES}  # the job's own cache
    environment["RAY_AUTH_MODE"] = "disabled"
    subprocess.run(command, check=True, capture_output=True, timeout=JOB_TIMEOUT_SECONDS, env=environment)
    return sorted((r.global_batch, n, e.data_sha256) for r in iter_records(output) for n, e in r.arrays.items())


def entries(folder) -> set[str]:
    return {path.name for path in folder.rglob(f"*{CACHE_ENTRY_SUFFIX}")}


@pytest.mark.slow
def test_a_second_run_finds_every_program_in_the_cache_and_writes_the_same_data(tmp_path):
    cache = tmp_path / "jax-cache"
    first = run_job_in_subprocess(tmp_path, "first", f"compile_cache.dir={cache}")
    cached = entries(cache)
    assert any(name.startswith(TRAIN_PROGRAM_ENTRY) for name in cached), "the training program was not stored"
    second = run_job_in_subprocess(tmp_path, "second", f"compile_cache.dir={cache}")
    assert entries(cache) == cached  # nothing compiled anew: every program was loaded
    assert second == first and first


def test_the_cache_folder_expands_the_home_directory_and_null_turns_it_off(monkeypatch, tmp_path):
    monkeypatch.setenv("HOME", str(tmp_path))
    assert cache_folder("~/.cache/kforge/jax") == tmp_path / ".cache" / "kforge" / "jax"
    assert cache_folder(None) is None
    assert load_config(None, ["split.name=test/s", f"output_dir={tmp_path}"]).compile_cache.dir == "~/.cache/kforge/jax"


def test_a_worker_told_to_turns_on_deterministic_gpu_ops_before_it_computes(tmp_path, monkeypatch):
    import dataclasses

    from kforge.pipeline.generation.worker import Worker

    monkeypatch.setenv("XLA_FLAGS", "--xla_force_host_platform_device_count=1")
    job = tiny_job(tmp_path / "out")
    Worker(resolve(dataclasses.replace(job, ray=dataclasses.replace(job.ray, deterministic_gpu_ops=True))), "local")
    assert os.environ["XLA_FLAGS"].split() == [
        "--xla_force_host_platform_device_count=1",
        "--xla_gpu_deterministic_ops=true",
    ]


def test_a_worker_leaves_xla_flags_alone_by_default(tmp_path, monkeypatch):
    from kforge.pipeline.generation.worker import Worker

    monkeypatch.setenv("XLA_FLAGS", "--xla_force_host_platform_device_count=1")
    Worker(resolve(tiny_job(tmp_path / "out")), "local")
    assert os.environ["XLA_FLAGS"] == "--xla_force_host_platform_device_count=1"
