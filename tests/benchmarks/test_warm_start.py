"""The warm-start report's arithmetic: where a success curve first reaches a target, and the steps each arm needs to
reach the from-scratch run's final success."""

import numpy as np

from benchmarks.warm_start import first_reaching, steps_to_reach

POINTS = np.array([0, 100, 200, 300, 400])


def test_a_curve_reaches_a_target_at_its_first_point_at_or_above_it():
    success = np.array([0.0, 0.2, 0.5, 0.4, 0.6])
    assert first_reaching(POINTS, success, 0.5) == 200
    assert first_reaching(POINTS, success, 0.0) == 0
    assert first_reaching(POINTS, success, 0.7) is None


def test_steps_to_reach_the_scratch_final_success():
    scratch = np.array(
        [
            [0.0, 0.0, 0.25, 0.5, 1.0],  # needs 400 steps to its final 1.0
            [0.0, 0.5, 0.5, 0.5, 0.5],  # needs 100 steps to its final 0.5
            [0.0, 0.0, 0.0, 0.0, 0.0],  # never solved: left out level by level
        ]
    )
    warm = np.array(
        [
            [0.5, 1.0, 1.0, 1.0, 1.0],  # reaches 1.0 at 100: within half of 400
            [0.0, 0.0, 0.5, 0.5, 0.5],  # reaches 0.5 at 200: not within half of 100
            [0.0, 0.0, 0.0, 0.0, 0.0],
        ]
    )
    reach = steps_to_reach(POINTS, warm, scratch)
    assert reach["scratch_final_success"] == 0.5  # mean of 1.0, 0.5 and 0.0
    # Mean curves: warm (0.17, 0.33, 0.5, ...) reaches 0.5 at 200; scratch (0, 0.17, 0.25, 0.33, 0.5) at 400.
    assert reach["warm_steps_to_scratch_final"] == 200
    assert reach["scratch_steps_to_own_final"] == 400
    assert reach["levels_with_scratch_success"] == 2
    assert reach["levels_scratch_needed_steps"] == 2
    assert reach["levels_warm_within_half_the_steps"] == 1
    assert reach["per_level"][0] == {"target": 1.0, "warm": 100, "scratch": 400}
    assert reach["per_level"][1] == {"target": 0.5, "warm": 200, "scratch": 100}
