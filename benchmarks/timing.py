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


def best_times_interleaved(functions, repeats: int) -> list[float]:
    """Wall seconds of the fastest call of each of `functions`, over `repeats` rounds that call each once in turn.

    Every function gets one untimed warm-up call first. Alternating call by call exposes every side of a
    comparison to the same drift in machine load, so ratios of the results hold up on a shared host.
    """
    for function in functions:
        jax.block_until_ready(function())
    best = [float("inf")] * len(functions)
    for _ in range(repeats):
        for index, function in enumerate(functions):
            start = time.perf_counter()
            jax.block_until_ready(function())
            best[index] = min(best[index], time.perf_counter() - start)
    return best
