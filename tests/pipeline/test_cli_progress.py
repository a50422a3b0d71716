"""Time left comes from the pace measured once compiling is over, not from the first batch's or step's wall time."""

import numpy as np
import pytest

from kforge.pipeline.generation.console import seconds_left

BC_STEPS = 2000
BC_COMPILE_SECONDS = 30.0  # [s] the first step compiles
BC_STEP_SECONDS = 0.5  # [s] each step after it


def test_bc_time_left_follows_the_steps_after_the_compiling_one():
    """A recorded sequence: step k's end time, with the compile in the first step and 10 % jitter in the others."""
    jitter = np.random.default_rng(0).uniform(0.9, 1.1, BC_STEPS - 1)
    finished = np.concatenate([[BC_COMPILE_SECONDS], BC_COMPILE_SECONDS + np.cumsum(BC_STEP_SECONDS * jitter)])
    since = (finished[0], 1)  # the first step done: compiling is over
    assert seconds_left(since, finished[0], 1, BC_STEPS) is None  # no pace measured yet
    for step in (11, 101, 1001):
        now = finished[step - 1]
        left = seconds_left(since, now, step, BC_STEPS)
        assert left == pytest.approx(finished[-1] - now, rel=0.05)
    first_steps = seconds_left(since, finished[10], 11, BC_STEPS)
    from_wall_time = finished[10] / 11 * (BC_STEPS - 11)  # the compile spread over the steps: far too long
    assert from_wall_time > 5 * first_steps


def test_run_time_left_leaves_the_first_batchs_compile_out():
    """A tiny run of two level batches: compiling ends at 235 s, the first batch commits at 268 s (33 s of
    training), so the second is 33 s away, not the 268 s the first batch's wall time would say."""
    assert seconds_left(None, 200.0, 0.0, 2) is None  # still compiling
    assert seconds_left((235.0, 0.0), 250.0, 0.0, 2) is None  # the first batch trains, no estimate of its share
    assert seconds_left((235.0, 0.0), 268.0, 1.0, 2) == pytest.approx(33.0)
    assert seconds_left((235.0, 0.0), 268.0 + 16.5, 1.5, 2) == pytest.approx(16.5)  # half the second batch trained
