"""JAX's persistent compilation cache: compiled programs kept in a folder, so a second worker or a re-run loads them
instead of compiling again (on 2 CPU cores, compiling the training program takes most of a small job's time)."""

from __future__ import annotations

import os
from pathlib import Path

DEFAULT_COMPILE_CACHE_DIR = "~/.cache/kforge/jax"
"""Default folder of the cache: per user, on the machine that runs the worker."""

MIN_COMPILE_SECONDS = 0.0
"""[s] programs that compiled faster than this are not cached: 0 caches every program (loading is cheap)."""

NO_MIN_ENTRY_SIZE = -1
"""JAX's setting for "cache entries of any size" (its default lets the backend choose a minimum)."""


def cache_folder(directory: str | None) -> Path | None:
    """The cache folder a `compile_cache.dir` value names, with ~ and environment variables expanded; None: off."""
    if directory is None:
        return None
    return Path(os.path.expandvars(os.path.expanduser(directory)))


def enable_compile_cache(directory: str | None) -> Path | None:
    """Use `directory` (created if missing) as this process's persistent compilation cache, for every program
    compiled from now on; None leaves the cache off. Returns the folder used.

    Call it before the process compiles anything: JAX opens its cache at the first compilation.
    """
    import jax  # here, not at the top: the job config reads DEFAULT_COMPILE_CACHE_DIR without importing JAX

    folder = cache_folder(directory)
    if folder is None:
        return None
    folder.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_SECONDS)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", NO_MIN_ENTRY_SIZE)
    return folder
