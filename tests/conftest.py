"""Run-wide test settings: wandb is disabled and writes nowhere but a temporary directory, so no test needs the
network or a wandb login (a test that checks tracking turns it back on with its own `WANDB_MODE`); and every process
of the run (pytest's workers, the jobs and Ray workers they start) shares one JAX compilation cache in the run's
temporary directory, so a program is compiled once per run, not once per process."""

import os

import pytest

from kforge.pipeline.generation.compile_cache import MIN_COMPILE_SECONDS, NO_MIN_ENTRY_SIZE, enable_compile_cache

WANDB_DIR_VARIABLES = ("WANDB_DIR", "WANDB_CONFIG_DIR", "WANDB_CACHE_DIR", "WANDB_DATA_DIR")
"""wandb's environment variables for where it writes runs, settings, caches and artifacts."""

COMPILATION_CACHE_VARIABLES = {
    "JAX_COMPILATION_CACHE_DIR": None,  # set to the run's folder
    "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": str(MIN_COMPILE_SECONDS),
    "JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES": str(NO_MIN_ENTRY_SIZE),
}
"""JAX's environment variables for its persistent compilation cache, as `enable_compile_cache` sets them in-process:
the processes the tests start read them at import."""


@pytest.fixture(autouse=True, scope="session")
def wandb_disabled(tmp_path_factory):
    """WANDB_MODE=disabled (it overrides `tracking.wandb`, see pipeline/generation/tracking.py) and wandb's folders
    in tmp."""
    directory = tmp_path_factory.mktemp("wandb")
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("WANDB_MODE", "disabled")
        for name in WANDB_DIR_VARIABLES:
            patch.setenv(name, str(directory / name.lower()))
        yield


@pytest.fixture(autouse=True, scope="session")
def shared_compilation_cache(tmp_path_factory):
    """One compilation cache for the whole run: the run's temporary directory, which pytest-xdist's workers share
    (each has a folder of its own below it). Never the user's cache: nothing of a test run outlives pytest's own
    temporary directories."""
    run_directory = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        run_directory = run_directory.parent
    folder = run_directory / "jax-compilation-cache"
    with pytest.MonkeyPatch.context() as patch:
        for name, value in COMPILATION_CACHE_VARIABLES.items():
            patch.setenv(name, value or str(folder))
        enable_compile_cache(str(folder))
        yield folder
