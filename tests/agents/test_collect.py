"""Expert windows record replayable states and flag a window successful only when every episode end succeeds."""

import jax
import numpy as np
from agents_test_helpers import ENV_PARAMS, STATIC, TRAIN_CONFIG, keys, mirrored_level, stack, thruster_level

from kforge.agents import initial_params
from kforge.agents.collect import WindowPlan, collect_windows
from kforge.engine import SceneBuilder
from kforge.env import Role, step
from kforge.env.level_builder import build_level

WINDOW_STEPS = 96  # [env steps] of each window
WINDOW_PLAN = WindowPlan(TRAIN_CONFIG, STATIC, num_steps=WINDOW_STEPS)


def _level(index: int, levels):
    return jax.tree.map(lambda x: x[index], levels)


def test_trained_experts_give_successful_replayable_windows(trained_mixed):
    levels = stack(thruster_level(), mirrored_level())
    window = jax.device_get(collect_windows(trained_mixed.params, levels, keys(5, 6), WINDOW_PLAN, ENV_PARAMS))
    for i in range(2):
        done, success = window.done[i], window.success[i]
        # Independent re-derivation of the success criterion from the per-step flags.
        expected = bool(done.any()) and bool(np.all(success[done]))
        assert bool(window.successful[i]) == expected
        assert int(window.episodes_ended[i]) == int(done.sum()) and int(window.successes[i]) == int(success.sum())
        assert bool(window.successful[i]), f"trained expert {i} failed its window: ends {np.flatnonzero(done)}"
        np.testing.assert_array_equal(window.action_mask[i], [False] * 4 + [True, False])
        # Replaying any stored state with the stored action reproduces the next stored state exactly.
        level = _level(i, levels)
        for t in (0, 17, int(np.flatnonzero(done)[0])):
            state = jax.tree.map(lambda x, i=i, t=t: x[i, t], window.states)
            following, _ = step(state, window.actions[i, t], level, ENV_PARAMS, STATIC)
            jax.tree.map(
                np.testing.assert_array_equal,
                jax.device_get(following),
                jax.tree.map(lambda x, i=i, t=t: x[i, t + 1], window.states),
            )


def test_a_window_with_a_failed_episode_is_not_successful():
    # Green falls onto red: every episode fails whatever the (masked, actuator-less) policy does.
    scene = SceneBuilder(STATIC.sim)
    red = scene.add_circle((2.5, 0.6), 0.2, static=True)
    green = scene.add_circle((2.5, 1.5), 0.2)
    blue = scene.add_box((4.5, 0.6), (0.4, 0.4), static=True)
    level = build_level(scene, roles={green: Role.GREEN, red: Role.RED, blue: Role.BLUE})
    # Two seeds, and the batch shape and window of the test above, so both run one compiled program.
    params = jax.vmap(lambda k: initial_params(k, TRAIN_CONFIG, STATIC))(keys(0, 2))
    window = collect_windows(params, stack(level, level), keys(1, 3), WINDOW_PLAN, ENV_PARAMS)
    for i in range(2):
        assert int(window.episodes_ended[i]) >= 2 and int(window.successes[i]) == 0
        assert not bool(window.successful[i])
        np.testing.assert_array_equal(np.asarray(window.actions[i]), 0)  # no valid slot: the policy cannot act
