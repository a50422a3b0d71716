"""Evaluation plays under Kinetix's physics unless the dataset's job named another scheme, and --max-levels bounds
every level set, the hand-designed one included."""

import enum

import jax
import numpy as np
from pipeline_test_helpers import tiny_job

from kforge.engine import physics_scheme
from kforge.env import EnvParams, StaticEnvParams, list_levels, load_level, under_scheme
from kforge.pipeline.learning import hand_starts, play_physics

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
    name, params = play_physics(tiny_job(tmp_path), KINETIX_S)  # the default job
    assert name == "kinetix" and same(params.sim, KINETIX_PARAMS.sim)
    name, params = play_physics(tiny_job(tmp_path, "env.physics=kforge"), SIZE_S)
    assert name == "kforge" and same(params.sim, KFORGE_PARAMS.sim)


def test_hand_levels_default_to_kinetix_and_max_levels_bounds_them():
    starts = hand_starts(KINETIX_S, max_levels=2)
    first, second = list_levels("s")[:2]
    assert starts.level_ids == [first, second]
    own = under_scheme(physics_scheme("kinetix"), load_level(first).params, KINETIX_S)[0]
    assert same(jax.tree.map(lambda x: x[0], starts.params), own)
    assert len(hand_starts(KINETIX_S).level_ids) == len(list_levels("s")) > 2
