"""The benchmark scenes' batches: its distinct scenes repeated in order, field by field as built."""

import jax
import numpy as np

from benchmarks.scenes import DISTINCT_SCENES, batched_scenes, build_scene

BATCH = 2 * DISTINCT_SCENES + 3  # two whole repetitions and a part of a third


def test_a_batch_repeats_the_distinct_scenes_in_order():
    batch = batched_scenes("s", BATCH)
    scenes = [build_scene("s", seed)[0] for seed in range(DISTINCT_SCENES)]
    for index in (0, 1, DISTINCT_SCENES - 1, DISTINCT_SCENES, BATCH - 1):
        expected = scenes[index % DISTINCT_SCENES]
        for got, want in zip(jax.tree.leaves(batch), jax.tree.leaves(expected), strict=True):
            assert got.shape == (BATCH, *want.shape) and got.dtype == want.dtype
            np.testing.assert_array_equal(np.asarray(got[index]), np.asarray(want))
    positions = np.asarray(batch.bodies.position)
    assert not np.array_equal(positions[0], positions[1])  # the jitter seeds differ
