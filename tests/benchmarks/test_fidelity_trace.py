"""The paired trace of benchmarks/fidelity_trace.py: episode ends, the first step two traces part, kforge's side."""

import numpy as np
import pytest

from benchmarks import fidelity_trace
from benchmarks.fidelity_trace import (
    EPISODE_STEPS,
    episode_ends,
    first_divergence,
    kinetix_state_at,
    parse_from_step,
    random_actions,
    trace_kinetix,
    trace_ours,
)
from kforge.engine import SimParams
from kforge.env import MULTI_DISCRETE_SIZES, bundled_level_path, load_level


def _trace(done_at: dict, reward_at: dict, episodes: int = 3) -> dict:
    done = np.zeros((episodes, EPISODE_STEPS), bool)
    reward = np.zeros((episodes, EPISODE_STEPS), np.float32)
    for episode, step in done_at.items():
        done[episode, step:] = True  # a trace runs on without reset
    for episode, value in reward_at.items():
        reward[episode, done_at[episode]] = value
    return {"done": done, "reward": reward}


def test_episode_ends_give_the_first_end_and_its_outcome():
    trace = _trace({0: 10, 1: 40, 2: EPISODE_STEPS - 1}, {0: 1.0, 1: -1.0})
    step, outcome = episode_ends(trace)
    np.testing.assert_array_equal(step, [10, 40, EPISODE_STEPS - 1])
    np.testing.assert_array_equal(outcome, [1, 2, 0])  # success, failure, timeout


def test_episode_ends_of_a_trace_that_starts_later_are_counted_in_its_own_length():
    """A trace from --from-step is shorter than an episode: an episode that never ends there ends at its length."""
    trace = {key: value[:, : EPISODE_STEPS - 100] for key, value in _trace({0: 10, 1: 200}, {0: -1.0}).items()}
    step, outcome = episode_ends(trace)
    np.testing.assert_array_equal(step, [10, EPISODE_STEPS - 100, EPISODE_STEPS - 100])
    np.testing.assert_array_equal(outcome, [2, 0, 0])


def test_from_step_reads_an_episode_and_a_step_within_an_episode():
    assert parse_from_step("3:21") == (3, 21)
    assert parse_from_step("0:0") == (0, 0)


@pytest.mark.parametrize("text", ["21", "a:b", "1:2:3", "-1:5", f"0:{EPISODE_STEPS}"])
def test_from_step_refuses_what_is_not_an_episode_and_a_step_in_one_line(text, capsys):
    with pytest.raises(SystemExit):
        fidelity_trace.main(["s/h1_thrust_over_ball", f"--from-step={text}"])
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert "--from-step" in error and repr(text) in error


def test_from_step_refuses_an_episode_that_was_not_drawn_before_it_looks_for_kinetix(tmp_path, capsys):
    """Refused before anything else happens: a missing Kinetix virtualenv is not built for it."""
    venv = tmp_path / "no-kinetix-here"
    with pytest.raises(SystemExit):
        fidelity_trace.main(
            ["s/h1_thrust_over_ball", "--episodes", "2", "--from-step", "2:10", "--kinetix-venv", str(venv)]
        )
    assert "episode 2 of 2 paired episodes does not exist" in capsys.readouterr().err
    assert not venv.exists()


def test_first_divergence_is_the_first_step_a_shape_is_further_apart_than_the_tolerance():
    shape = (2, EPISODE_STEPS, 3, 2)
    ours = {"polygon_position": np.zeros(shape), "circle_position": np.zeros((2, EPISODE_STEPS, 1, 2))}
    theirs = {"polygon_position": np.zeros(shape), "circle_position": np.zeros((2, EPISODE_STEPS, 1, 2))}
    theirs["polygon_position"][0, 7:, 1, 0] = 0.02  # episode 0: polygon 1 is 2 cm off from step 7
    theirs["polygon_position"][1, 3:, 2, 1] = 0.5  # episode 1: only an inactive polygon differs...
    theirs["circle_position"][1, 9:, 0, 1] = 0.005  # ...and a circle by less than the tolerance
    active_polygons, active_circles = np.array([True, True, False]), np.array([True])
    np.testing.assert_array_equal(first_divergence(ours, theirs, active_polygons, active_circles, 0.01), [7, -1])


def test_random_actions_are_valid_multi_discrete_actions_and_repeat_with_the_seed():
    actions = random_actions(4, seed=3)
    assert actions.shape == (4, EPISODE_STEPS, len(MULTI_DISCRETE_SIZES))
    assert np.all((actions >= 0) & (actions < np.array(MULTI_DISCRETE_SIZES)))
    np.testing.assert_array_equal(actions, random_actions(4, seed=3))


def test_kforge_side_of_a_no_op_trace_keeps_static_shapes_still_and_ends_at_the_time_limit():
    """s/h1_thrust_over_ball's no-op: nothing is driven, the episode times out; the floor never moves."""
    loaded = load_level(bundled_level_path("s/h1_thrust_over_ball"))
    trace = trace_ours(loaded, np.zeros((1, EPISODE_STEPS, 6), np.int32), {})
    step, outcome = episode_ends(trace)
    assert outcome[0] == 0 and step[0] == EPISODE_STEPS - 1
    floor = trace["polygon_position"][0, :, 0]
    np.testing.assert_array_equal(floor, np.broadcast_to(floor[0], floor.shape))
    np.testing.assert_allclose(floor[0], [2.5, -4.8], atol=1e-6)


def test_kforge_side_plays_the_solver_scheme_it_is_given():
    """s/h1_thrust_over_ball's ball starts in free fall. An env step is two physics steps: in one substep each, a
    body falls 3 g dt^2 more than its start velocity carries it, in four substeps 2.25 g dt^2 (docs/fidelity.md), so
    under one substep of 10 passes the ball is 0.75 g dt^2 lower after the first env step."""
    loaded = load_level(bundled_level_path("s/h1_thrust_over_ball"))
    no_op = np.zeros((1, EPISODE_STEPS, 6), np.int32)
    default = trace_ours(loaded, no_op, {})["circle_position"][0, 0, 0, 1]
    one_step = trace_ours(loaded, no_op, {}, {"substeps": 1, "iterations": 10, "relax_iterations": 0})
    dt, gravity = SimParams().dt, 9.81
    assert default - one_step["circle_position"][0, 0, 0, 1] == pytest.approx(0.75 * gravity * dt**2, rel=1e-3)


def test_kforge_side_plays_the_physics_scheme_named():
    """As above: under the "kinetix" scheme (one step of 10 passes, gravity at the step's start) the free-falling ball
    is 0.75 g dt^2 lower after the first env step than under the default's four substeps."""
    loaded = load_level(bundled_level_path("s/h1_thrust_over_ball"))
    no_op = np.zeros((1, EPISODE_STEPS, 6), np.int32)
    default = trace_ours(loaded, no_op, {})["circle_position"][0, 0, 0, 1]
    kinetix = trace_ours(loaded, no_op, {}, physics="kinetix")["circle_position"][0, 0, 0, 1]
    dt, gravity = SimParams().dt, 9.81
    assert default - kinetix == pytest.approx(0.75 * gravity * dt**2, rel=1e-3)


def test_the_trace_refuses_a_solver_count_below_its_least(capsys):
    with pytest.raises(SystemExit):
        fidelity_trace.main(["s/h1_thrust_over_ball", "--iterations", "0"])
    assert "--iterations must be at least 1, got 0" in capsys.readouterr().err


@pytest.mark.slow  # builds Kinetix's virtualenv on first use (minutes), then three short Kinetix runs: about 1 minute
def test_kinetixs_state_at_a_step_is_where_its_trace_was_and_ours_loads_it_there(tmp_path):
    """The state that Kinetix writes after 12 random env steps of s/h3_point_the_thruster is, loaded by ours, where
    Kinetix's own trace had every shape after those 12 steps; and Kinetix going on from that file plays the next step
    as its trace did (up to the warm-starting impulses, which a level file keeps)."""
    from benchmarks.kinetix_venv import DEFAULT_KINETIX_VENV, kinetix_python

    python = kinetix_python(DEFAULT_KINETIX_VENV, print)
    path = bundled_level_path("s/h3_point_the_thruster")
    actions = random_actions(1, seed=5)
    full = trace_kinetix(python, path, actions, tmp_path)
    state_file = kinetix_state_at(python, path, actions, 12, tmp_path)
    loaded = load_level(state_file)
    start = fidelity_trace.state_to_kinetix(fidelity_trace.reset(loaded.level), loaded.static)
    for kind in ("polygon", "circle"):
        np.testing.assert_allclose(start[f"{kind}/position"], full[f"{kind}_position"][0, 11], atol=1e-5)
        np.testing.assert_allclose(start[f"{kind}/velocity"], full[f"{kind}_velocity"][0, 11], atol=1e-5)
    again = trace_kinetix(python, state_file, actions[:, 12:], tmp_path)
    for kind in ("polygon", "circle"):
        np.testing.assert_allclose(again[f"{kind}_position"][0, 0], full[f"{kind}_position"][0, 12], atol=1e-4)
