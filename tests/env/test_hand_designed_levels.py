"""Hand-designed Kinetix levels play as designed in our env: simple scripted policies win, the no-op and the wrong
motor direction do not, and random play on every level stays finite.

All rollouts of one size run as one vmapped batch of `ROLLOUT_BATCH` full episodes, so each size compiles once;
size m rollouts are marked slow.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from kforge import env
from kforge.env.level_files import LoadedLevel, load_level
from tests.helpers import stack
from tests.rollouts import env_episodes

EPISODE_STEPS = 256
"""Env steps per rollout: one full Kinetix episode."""

ROLLOUT_BATCH = 24
"""Every rollout batch is padded to this many episodes, so the compiled rollout is shared by all tests of a size."""

MOTOR_FORWARD, MOTOR_BACKWARD, THRUSTER_ON = 1, 2, 1
"""Multi-discrete choices: motor slot 1 -> action +1, 2 -> action -1; thruster slot 1 -> on."""

THRUSTER_0, MOTOR_0 = 4, 0
"""Unified action slots."""


def _script(**slots) -> np.ndarray:
    """(EPISODE_STEPS, 6) multi-discrete actions; keyword `slot_<i>=(choice, first_step, end_step)` holds a slot."""
    actions = np.zeros((EPISODE_STEPS, env.NUM_ACTION_SLOTS), np.int32)
    for name, (choice, start, end) in slots.items():
        actions[start:end, int(name.removeprefix("slot_"))] = choice
    return actions


ALWAYS = (0, EPISODE_STEPS)
SCRIPTS = {
    "noop": _script(),
    "thrust": _script(slot_4=(THRUSTER_ON, *ALWAYS)),
    # s/h4_thrust_aim: the green box's thruster gives 10 m/s^2 (power 0.2516 x 10 N on 0.2516 kg) to the left. Three
    # env steps (0.1 s) give 1 m/s; falling 3.3 m takes 0.82 s, so the box lands ~0.77 m left of its start (x 4.49):
    # on the blue ball at x 3.68 instead of the red ball below it.
    "thrust 3 steps": _script(slot_4=(THRUSTER_ON, 0, 3)),
    "motor +1": _script(slot_0=(MOTOR_FORWARD, *ALWAYS)),
    "motor -1": _script(slot_0=(MOTOR_BACKWARD, *ALWAYS)),
    # m/h18_thrust_right_very_easy: the up thruster lifts the box (net 9.8 m/s^2) to the ceiling within 30 steps; then
    # the right thruster slides it along the ceiling into the blue box in the top-right corner. Firing both from the
    # start pins it against the right wall, where friction outweighs the net lift.
    "up, then up and right": _script(slot_4=(THRUSTER_ON, *ALWAYS), slot_5=(THRUSTER_ON, 30, EPISODE_STEPS)),
}

# (size, level, script) -> first episode's outcome: "success" (green touched blue), "failure" (green touched red)
# or "timeout". Motor sign: +1 drives angular_velocity(wheel) - angular_velocity(body) positive, i.e. the wheel
# turns counter-clockwise and rolls left.
EXPECTED = {
    ("s", "h0_weak_thrust", "thrust"): "success",  # the thruster lifts the green ball up to the blue one
    ("s", "h0_weak_thrust", "noop"): "failure",  # it falls onto the red floor
    ("s", "h4_thrust_aim", "thrust 3 steps"): "success",
    ("s", "h4_thrust_aim", "noop"): "failure",  # falls straight onto the red ball
    ("s", "h4_thrust_aim", "thrust"): "timeout",  # flies past the blue ball
    ("s", "h6_unicycle_right", "motor -1"): "success",  # rolls right to the green ball
    ("s", "h6_unicycle_right", "motor +1"): "timeout",
    ("s", "h6_unicycle_right", "noop"): "timeout",
    ("s", "h7_unicycle_left", "motor +1"): "success",  # rolls left to the green ball
    ("s", "h7_unicycle_left", "noop"): "timeout",
    ("s", "h8_unicycle_balance", "noop"): "failure",  # unbalanced, the unicycle tips the green ball onto the red floor
    ("m", "h18_thrust_right_very_easy", "up, then up and right"): "success",
    ("m", "h18_thrust_right_very_easy", "noop"): "timeout",
    ("m", "h2_car_right", "motor -1"): "success",  # drives right into the blue ball
    ("m", "h2_car_right", "motor +1"): "failure",  # drives left into the red box
    ("m", "h2_car_right", "noop"): "timeout",
    ("m", "h1_car_left", "motor +1"): "success",
    ("m", "h1_car_left", "motor -1"): "failure",
    ("m", "h1_car_left", "noop"): "timeout",
}


def _has_nan(tree) -> jnp.ndarray:
    return jnp.any(
        jnp.stack([jnp.any(jnp.isnan(x)) for x in jax.tree.leaves(tree) if jnp.issubdtype(x.dtype, jnp.floating)])
    )


def _outcome_record(state: env.EnvState, result: env.StepResult) -> tuple[jnp.ndarray, ...]:
    """A step's success, failure, reward and "state has NaN", as `env_episodes` records them."""
    return result.success, result.failure, result.reward, _has_nan(state) | result.unstable


def _play(loaded: list[LoadedLevel], actions: np.ndarray) -> tuple[np.ndarray, ...]:
    """Per-step (B, T) success, failure, reward and "state has NaN" of same-size levels sharing one EnvParams, played
    with (B, T, 6) actions in one batch padded to ROLLOUT_BATCH."""
    count = len(loaded)
    assert 0 < count <= ROLLOUT_BATCH and all(item.params == loaded[0].params for item in loaded)
    padded = loaded + [loaded[-1]] * (ROLLOUT_BATCH - count)
    actions = np.concatenate([actions, np.zeros((ROLLOUT_BATCH - count, *actions.shape[1:]), actions.dtype)])
    levels = stack(*[item.level for item in padded])
    outputs = env_episodes(levels, jnp.asarray(actions), loaded[0].params, loaded[0].static, _outcome_record)
    return tuple(np.asarray(x)[:count] for x in outputs)


def _first_outcome(success: np.ndarray, failure: np.ndarray) -> str:
    decided = np.flatnonzero(success | failure)
    if decided.size == 0:
        return "timeout"
    return "success" if success[decided[0]] else "failure"


def _outcomes_of_size(size: str, levels_dir) -> dict[tuple[str, str, str], str]:
    cases = [case for case in EXPECTED if case[0] == size]
    loaded = [load_level(levels_dir / size / f"{name}.json") for _, name, _ in cases]
    success, failure, _, _ = _play(loaded, np.stack([SCRIPTS[script] for _, _, script in cases]))
    return {case: _first_outcome(s, f) for case, s, f in zip(cases, success, failure, strict=True)}


@pytest.fixture(scope="module")
def scripted_outcome(levels_dir):
    """case -> outcome; all cases of a size run together in one batch, on first use."""
    by_size: dict[str, dict] = {}

    def outcome(case: tuple[str, str, str]) -> str:
        size = case[0]
        if size not in by_size:
            by_size[size] = _outcomes_of_size(size, levels_dir)
        return by_size[size][case]

    return outcome


def _size_marks(size: str):
    """Size m compiles its own rollout (about a minute on 2 cores): slow."""
    return [pytest.mark.slow] if size == "m" else []


@pytest.mark.parametrize(
    "case", [pytest.param(case, id="/".join(case), marks=_size_marks(case[0])) for case in EXPECTED]
)
def test_scripted_policy_outcome(case, scripted_outcome):
    assert scripted_outcome(case) == EXPECTED[case]


@pytest.mark.parametrize("size", [pytest.param(size, marks=_size_marks(size)) for size in ("s", "m")])
def test_random_play_on_every_level_stays_finite(size, levels_dir):
    paths = sorted((levels_dir / size).glob("*.json"))
    loaded = [load_level(path) for path in paths]
    assert 0 < len(loaded) <= ROLLOUT_BATCH
    keys = jax.random.split(jax.random.PRNGKey(0), len(loaded) * EPISODE_STEPS)
    actions = jax.vmap(lambda key: env.random_action(key, env.ActionType.MULTI_DISCRETE))(keys)
    actions = np.asarray(actions).reshape(len(loaded), EPISODE_STEPS, env.NUM_ACTION_SLOTS)
    assert set(np.unique(actions[..., THRUSTER_0])) == {0, 1} and set(np.unique(actions[..., MOTOR_0])) == {0, 1, 2}
    _, _, reward, nan = _play(loaded, actions)
    for path, level_reward, level_nan in zip(paths, reward, nan, strict=True):
        assert not level_nan.any(), f"{path.stem}: NaN in the state at step {int(np.argmax(level_nan))}"
        assert np.all(np.isfinite(level_reward)), path.stem
        assert np.all(np.abs(level_reward) < 2.0), path.stem  # +-1 goal plus small shaping
