"""Timing of jitted calls, shared by the benchmarks and by the Kinetix baselines (which run in Kinetix's own
virtualenv and import this file from beside them: it needs only jax)."""

from __future__ import annotations

import time

import jax


def best_time(function, repeats: int) -> tuple[float, float]:
    """(wall, process CPU) seconds of the fastest of `repeats` calls of `function()`, after one untimed warm-up call."""
    jax.block_until_ready(function())
    best = (float("inf"), float("inf"))
    for _ in range(repeats):
        wall, cpu = time.perf_counter(), time.process_time()
        jax.block_until_ready(function())
        best = min(best, (time.perf_counter() - wall, time.process_time() - cpu))
    return best
