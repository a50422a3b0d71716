"""The evaluation sets and how they are played: Kinetix's physics unless the dataset's job named another scheme,
--max-levels bounding every set, the unseen levels a fixed range checked disjoint from the dataset's, the baselines
on the same starts with the same keys, and the standard errors."""

import enum

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from pipeline_test_helpers import tiny_job

from kforge.engine import physics_scheme
from kforge.env import EnvParams, StaticEnvParams, list_levels, load_level, under_scheme
from kforge.pipeline.generation import resolve
from kforge.pipeline.learning.evaluation import play_physics
from kforge.pipeline.learning.evaluation_sets import hand_starts

SIZE_S = StaticEnvParams.for_size("s")
KINETIX_PARAMS, KINETIX_S = under_scheme(physics_scheme("kinetix"), EnvParams(), SIZE_S)
KFORGE_PARAMS = under_scheme(physics_scheme("kforge"), EnvParams(), SIZE_S)[0]


def same(a, b) -> bool:
    """Equal leaf by leaf, numbers compared at float32 (the precision the params are stacked at)."""

    def equal(x, y) -> bool:
        if isinstance(x, enum.Enum) or isinstance(y, enum.Enum):
            return x == y
        return bool(np.all(np.asarray(x, np.float32) == np.asarray(y, np.float32)))

    return all(jax.tree.leaves(jax.tree.map(equal, a, b)))


def test_evaluation_plays_kinetix_unless_the_job_names_another_scheme(tmp_path):
    name, params = play_physics(None, KINETIX_S)  # data made without a job config
    assert name == "kinetix" and same(params, KINETIX_PARAMS)
    name, params = play_physics(resolve(tiny_job(tmp_path)), KINETIX_S)  # the default job
    assert name == "kinetix" and same(params.sim, KINETIX_PARAMS.sim)
    name, params = play_physics(resolve(tiny_job(tmp_path, "env.physics=kforge")), SIZE_S)
    assert name == "kforge" and same(params.sim, KFORGE_PARAMS.sim)


def test_hand_levels_default_to_kinetix_and_max_levels_bounds_them():
    starts = hand_starts(KINETIX_S, max_levels=2)
    first, second = list_levels("s")[:2]
    assert starts.level_ids == [first, second]
    own = under_scheme(physics_scheme("kinetix"), load_level(first).params, KINETIX_S)[0]
    assert same(jax.tree.map(lambda x: x[0], starts.params), own)
    assert len(hand_starts(KINETIX_S).level_ids) == len(list_levels("s")) > 2


@pytest.mark.slow
def test_unseen_levels_are_a_fixed_range_past_every_dataset_that_the_filter_keeps(tmp_path):
    """The unseen set starts at the documented level 2^31 whatever the dataset's size, holds only the levels the
    split's filter keeps there, in order, and is the same levels every time."""
    from kforge.env import filter_levels, reset
    from kforge.pipeline.generation import sample_batch
    from kforge.pipeline.learning.evaluation_sets import UNSEEN_FIRST_LEVEL, UNSEEN_SAMPLE_CHUNK, unseen_starts

    assert UNSEEN_FIRST_LEVEL == 2**31
    job = tiny_job(tmp_path)
    resolved = resolve(job)
    starts = unseen_starts(resolved, count=5)
    ids = starts.level_ids
    candidates = np.arange(2**31, 2**31 + UNSEEN_SAMPLE_CHUNK)
    levels = sample_batch(resolved, candidates)
    keep = np.asarray(filter_levels(levels, resolved.env_params, resolved.static, job.filter.noop_steps).keep)
    assert 0 < keep.sum() < len(keep)  # the filter drops some of the range: the set is not the range's first five
    assert candidates[keep][:5].tolist() == ids
    expected = jax.vmap(reset)(sample_batch(resolved, np.asarray(ids)))
    np.testing.assert_array_equal(starts.states.sim.bodies.position, expected.sim.bodies.position)
    again = unseen_starts(resolve(tiny_job(tmp_path / "grown", "split.num_levels=40")), count=5)  # a larger dataset
    assert again.level_ids == ids
    np.testing.assert_array_equal(again.states.sim.bodies.position, starts.states.sim.bodies.position)


def test_unseen_levels_that_are_dataset_levels_are_refused_in_one_line(tmp_path, dataset_dir):
    import dataclasses

    from kforge.pipeline.learning.evaluation_sets import check_unseen_disjoint, dataset_level_ids, unseen_starts
    from kforge.pipeline.storage import DatasetError

    held = dataset_level_ids(str(dataset_dir))
    assert held == {10 * g + k for g in range(4) for k in range(3)}  # kept and unsolved levels alike
    starts = unseen_starts(resolve(tiny_job(tmp_path)), count=2)
    check_unseen_disjoint(starts, str(dataset_dir), held)
    overlapping = dataclasses.replace(starts, level_ids=[starts.level_ids[0], 22])
    with pytest.raises(DatasetError, match=r"^\S+: 1 unseen levels are dataset levels \(first: 22\)[^\n]*$"):
        check_unseen_disjoint(overlapping, str(dataset_dir), held)


@pytest.mark.slow
def test_baselines_play_the_same_starts_with_the_same_keys(levels):
    """Both baselines play every start of the set, in its order (the drop levels force each outcome), and a
    player's episodes are a function of (seed, start) alone: played again, the same outcomes."""
    from pipeline_test_helpers import PARAMS, STATIC

    from kforge.env import action_mask, reset
    from kforge.pipeline.learning.evaluation import play_set
    from kforge.pipeline.learning.evaluation_sets import StartSet

    starts = StartSet(
        jax.vmap(reset)(levels),
        jax.vmap(action_mask)(levels),
        jax.tree.map(lambda x: jnp.broadcast_to(jnp.asarray(x), (3,) + jnp.shape(x)), PARAMS),
        [0, 1, 2],
    )
    outcomes = play_set(None, starts, STATIC, episodes=2, seed=3, greedy=False)
    assert set(outcomes) == {"noop", "random"}
    for success, failure in outcomes.values():
        np.testing.assert_array_equal(success, [[True, True], [True, True], [False, False]])
        np.testing.assert_array_equal(failure, [[False, False], [False, False], [True, True]])
    again = play_set(None, starts, STATIC, episodes=2, seed=3, greedy=False)
    for name in outcomes:
        np.testing.assert_array_equal(again[name][0], outcomes[name][0])


def test_rates_give_the_standard_errors_and_the_paired_difference_to_random():
    from kforge.pipeline.learning.evaluation import rates

    bc = np.array([[True, True], [True, False], [False, False]])  # per start: 1, 0.5, 0
    random = np.array([[True, False], [True, False], [False, False]])  # 0.5, 0.5, 0
    none = np.zeros((3, 2), bool)
    summary = rates({"bc": (bc, ~bc), "noop": (none, none), "random": (random, none)})
    assert summary["bc"]["success"] == pytest.approx(0.5)
    assert summary["bc"]["success_se"] == pytest.approx(np.sqrt(0.25 / 3))  # std (ddof 1) 0.5 over sqrt(3)
    assert summary["bc"]["failure"] == pytest.approx(0.5) and summary["bc"]["timeout"] == pytest.approx(0.0)
    assert summary["noop"] == {"success": 0.0, "success_se": 0.0, "failure": 0.0, "timeout": 1.0}
    # differences 0.5, 0, 0: mean 1/6, std (ddof 1) sqrt(1/12), over sqrt(3): 1/6
    assert summary["bc_minus_random"]["difference"] == pytest.approx(1 / 6)
    assert summary["bc_minus_random"]["se"] == pytest.approx(1 / 6)
