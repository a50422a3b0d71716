"""The loader: Kinetix-shaped batches, determinism by seed, disjoint data-parallel readers, epochs, rendering."""

from __future__ import annotations

import shutil

import jax
import numpy as np
import pytest
from pipeline_test_helpers import STATIC, batch_file

from kforge.env import ObservationType, StaticEnvParams, observe
from kforge.pipeline.reading.loader import TrajectoryDatasetManager
from kforge.pipeline.storage.layout import DatasetError
from kforge.pipeline.storage.shard_store import open_dataset
from kforge.pipeline.storage.verify import verify_dataset

pytestmark = pytest.mark.smoke

NUM_TRAJECTORIES = 8  # four batches of two kept trajectories
KEPT_SLOTS = [0, 1, 3, 4, 6, 7, 9, 10]  # slots 3g and 3g + 1 of each level batch g


def indices(manager, num_batches):
    return [manager.load_next_batch().trajectory_index.tolist() for _ in range(num_batches)]


def test_batch_shapes_and_broadcast_static_fields(dataset_dir, rolled_out):
    batch = TrajectoryDatasetManager(dataset_dir, batch_size=3, seed=0).load_next_batch()
    assert batch.action.shape == (3, 256, 6) and batch.action_mask.shape == (3, 256, 6)
    assert batch.done.shape == (3, 256) and batch.mask.shape == (3, 256) and bool(batch.mask.all())
    assert batch.env_state.sim.bodies.position.shape == (3, 256, 7, 2)
    assert batch.env_state.sim.bodies.inverse_mass.shape == (3, 256, 7)
    assert batch.env_state.sim.collision_matrix.shape == (3, 256, 7, 7)
    assert batch.env_state.timestep.shape == (3, 256)
    assert batch.obs is None
    # slot 3g + i holds level i of the rollout
    states, action, done, _ = rolled_out
    for row, slot in enumerate(batch.trajectory_index):
        level = slot % 3
        np.testing.assert_array_equal(batch.action[row], action[level])
        np.testing.assert_array_equal(batch.done[row], done[level])
        np.testing.assert_array_equal(batch.env_state.sim.bodies.position[row], states.sim.bodies.position[level])
        np.testing.assert_array_equal(batch.env_state.task.roles[row, 200], states.task.roles[level, 0])
        np.testing.assert_array_equal(batch.action_mask[row, 17], [1, 0, 0, 0, 1, 0])


def test_one_epoch_is_a_permutation_and_the_next_epoch_reshuffles(dataset_dir):
    manager = TrajectoryDatasetManager(dataset_dir, batch_size=4, seed=3)
    assert manager.length == NUM_TRAJECTORIES and manager.batches_per_epoch == 2
    epochs = [sum(indices(manager, 2), []) for _ in range(3)]
    assert all(sorted(epoch) == KEPT_SLOTS for epoch in epochs)
    assert len({tuple(epoch) for epoch in epochs}) > 1


def test_the_order_depends_only_on_the_seed(dataset_dir):
    first = indices(TrajectoryDatasetManager(dataset_dir, batch_size=2, seed=5), 6)
    again = indices(TrajectoryDatasetManager(dataset_dir, batch_size=2, seed=5), 6)
    other = indices(TrajectoryDatasetManager(dataset_dir, batch_size=2, seed=6), 6)
    assert first == again and first != other


def test_a_reader_of_some_levels_sees_only_their_trajectories(dataset_dir):
    # Level batch g holds levels 10 g, 10 g + 1 (kept, slots 3 g and 3 g + 1) and 10 g + 2 (not kept).
    manager = TrajectoryDatasetManager(dataset_dir, batch_size=2, seed=0, level_ids=[1, 20, 21, 32, 999])
    assert manager.length == 3 and manager.batches_per_epoch == 1
    seen = {slot for _ in range(4) for slot in manager.load_next_batch().trajectory_index.tolist()}
    assert seen == {1, 6, 7}
    with pytest.raises(DatasetError, match="1 committed trajectories of the 2 selected levels"):
        TrajectoryDatasetManager(dataset_dir, batch_size=2, level_ids=[0, 2])


def test_starting_at_batch_n_continues_the_sequence_of_a_reader_that_loaded_n(dataset_dir):
    first = indices(TrajectoryDatasetManager(dataset_dir, batch_size=3, seed=4), 7)
    for start in (1, 2, 5):
        later = TrajectoryDatasetManager(dataset_dir, batch_size=3, seed=4, start_batch=start, prefetch=start % 2)
        assert indices(later, 7 - start) == first[start:]
    with pytest.raises(ValueError, match="start_batch must be >= 0"):
        TrajectoryDatasetManager(dataset_dir, batch_size=3, start_batch=-1)


def test_prefetching_gives_the_same_batches_and_epochs(dataset_dir):
    """Three epochs of batches of 3 (two per epoch), read ahead by a background thread or not; closing the
    prefetching loader midway continues the same sequence."""
    plain = TrajectoryDatasetManager(dataset_dir, batch_size=3, seed=4)
    expected = [(plain.load_next_batch(), plain.epoch) for _ in range(6)]
    with TrajectoryDatasetManager(dataset_dir, batch_size=3, seed=4, prefetch=2) as ahead:
        got = [(ahead.load_next_batch(), ahead.epoch) for _ in range(3)]
        ahead.close()
        got += [(ahead.load_next_batch(), ahead.epoch) for _ in range(3)]
    assert [epoch for _, epoch in got] == [epoch for _, epoch in expected] == [0, 0, 1, 1, 2, 2]
    for (batch, _), (reference, _) in zip(got, expected, strict=True):
        np.testing.assert_array_equal(batch.trajectory_index, reference.trajectory_index)
        np.testing.assert_array_equal(batch.action, reference.action)
        np.testing.assert_array_equal(batch.env_state.sim.bodies.velocity, reference.env_state.sim.bodies.velocity)


@pytest.mark.parametrize("readers", [2, 3])
def test_data_parallel_readers_are_disjoint_and_cover_the_epoch(dataset_dir, readers):
    per_reader = NUM_TRAJECTORIES // readers
    seen = [
        sum(indices(TrajectoryDatasetManager(dataset_dir, 1, 9, r, readers), per_reader), []) for r in range(readers)
    ]
    flat = sum(seen, [])
    assert len(flat) == len(set(flat)) == per_reader * readers  # disjoint; 8 % 3 = 2 left out of this epoch
    assert set(flat) <= set(KEPT_SLOTS)


def test_render_fn_is_applied_to_every_step(dataset_dir, rolled_out):
    def render(state):
        return observe(state, STATIC, ObservationType.SYMBOLIC_FLAT)

    batch = TrajectoryDatasetManager(dataset_dir, batch_size=2, seed=0, render_fn=render).load_next_batch()
    assert batch.obs.shape == (2, 256, 140)
    states = rolled_out[0]
    level = int(batch.trajectory_index[0]) % 3
    direct = observe(jax.tree.map(lambda x: x[level, 50], states), STATIC, ObservationType.SYMBOLIC_FLAT)
    np.testing.assert_array_equal(batch.obs[0, 50], direct)


def test_bad_requests_are_named(dataset_dir, tmp_path):
    with pytest.raises(DatasetError, match="only 2 per epoch, fewer than batch_size 3"):
        TrajectoryDatasetManager(dataset_dir, batch_size=3, shard_index=0, total_shard_count=4)
    with pytest.raises(DatasetError, match="stored with .*num_polygons=5.* but .*num_polygons=6"):
        TrajectoryDatasetManager(dataset_dir, batch_size=1, static_env_params=StaticEnvParams.for_size("m"))
    with pytest.raises(DatasetError, match="not a dataset"):
        TrajectoryDatasetManager(tmp_path, batch_size=1)
    with pytest.raises(ValueError, match=r"shard_index 2 out of range \[0, 2\)"):
        TrajectoryDatasetManager(dataset_dir, batch_size=1, shard_index=2, total_shard_count=2)
    with pytest.raises(ValueError, match="prefetch must be >= 0, got -1"):
        TrajectoryDatasetManager(dataset_dir, batch_size=1, prefetch=-1)


def test_a_missing_or_corrupt_data_file_is_a_named_error(dataset_dir, tmp_path):
    root = tmp_path / "ds"
    shutil.copytree(dataset_dir, root)
    dataset = open_dataset(root)
    path = batch_file(dataset, "action", 1)
    data = bytearray(path.read_bytes())
    data[50] ^= 0xFF
    path.write_bytes(bytes(data))
    # tensorstore reports the chunk's crc32c mismatch or, for most bytes, Blosc's own check failing first
    with pytest.raises(
        DatasetError, match="^shard-000000 batch 1: .*cannot read action: .*([Dd]igest mismatch|[Bb]losc)"
    ):
        TrajectoryDatasetManager(root, batch_size=1).load_slots(np.array([3]))


@pytest.mark.parametrize("name", ["done", "meta/valid", "env_state/sim/bodies/position", "env_state/timestep"])
@pytest.mark.parametrize("damage", ["missing", "truncated"])
def test_a_missing_or_truncated_object_in_any_array_fails_the_reader_and_verify_names_it(
    dataset_dir, tmp_path, name, damage
):
    """A lost `done` or state object would otherwise read as fill values (False, zeros) and decode silently wrong."""
    root = tmp_path / "ds"
    shutil.copytree(dataset_dir, root)
    path = batch_file(open_dataset(root), name, 2)  # global batch 2: shard 1, batch 0
    if damage == "missing":
        path.unlink()
        expected = f"shard-000001 batch 0: array {name}: committed object .* is missing"
    else:
        path.write_bytes(path.read_bytes()[:-7])
        expected = f"shard-000001 batch 0: array {name}: committed object .* bytes, its record says"
    with pytest.raises(DatasetError, match=expected) as error:
        TrajectoryDatasetManager(root, batch_size=1)
    assert "\n" not in str(error.value)
    reports = verify_dataset(root)
    assert [report.ok for report in reports] == [True, False]
    assert list(reports[1].bad_batches) == [0]
    assert any(f"{name}: file" in problem for problem in reports[1].bad_batches[0])


def test_a_reader_of_other_levels_ignores_a_damaged_batch(dataset_dir, tmp_path):
    root = tmp_path / "ds"
    shutil.copytree(dataset_dir, root)
    batch_file(open_dataset(root), "done", 2).unlink()  # levels 20, 21, 22
    reader = TrajectoryDatasetManager(root, batch_size=1, level_ids=[0, 1, 10, 11])
    assert sorted(reader.slots.tolist()) == [0, 1, 3, 4]


def test_a_cached_reader_gives_the_batches_of_a_streaming_one(dataset_dir):
    streaming = TrajectoryDatasetManager(dataset_dir, batch_size=3, seed=2)
    cached = TrajectoryDatasetManager(dataset_dir, batch_size=3, seed=2, cache_bytes=1 << 30, prefetch=1)
    too_small = TrajectoryDatasetManager(dataset_dir, batch_size=3, seed=2, cache_bytes=cached.decoded_bytes(8) - 1)
    assert cached.cached and not streaming.cached and not too_small.cached
    for _ in range(5):  # across an epoch boundary
        first, second = streaming.load_next_batch(), cached.load_next_batch()
        np.testing.assert_array_equal(first.trajectory_index, second.trajectory_index)
        for a, b in zip(jax.tree.leaves(first.env_state), jax.tree.leaves(second.env_state), strict=True):
            np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(first.action, second.action)
    cached.close()
