"""benchmarks/fidelity_paired.py: the paired inputs, episodes compared with their twins (ends alike, pose errors),
the shares per set and size against the ceiling, the plot; kforge's and Kinetix's sides on real levels (slow)."""

import hashlib

import numpy as np
import pytest

from benchmarks import fidelity_paired
from benchmarks.fidelity_paired import (
    PERTURBATION_M,
    active_shapes,
    compare_level,
    kept_trace,
    kinetix_traces,
    paired_inputs,
    play_ours,
    pose_errors,
    same_ends,
    summarize,
)
from benchmarks.fidelity_trace import EPISODE_STEPS
from kforge.env import MULTI_DISCRETE_SIZES, bundled_level_path

SHAPES = 3


def trace(episodes: int = 4, ends: dict | None = None, seed: int = 0) -> dict:
    """A trace of `episodes` episodes over SHAPES shapes, random poses; `ends` maps an episode to (step, reward)."""
    rng = np.random.default_rng(seed)
    done = np.zeros((episodes, EPISODE_STEPS), bool)
    reward = np.zeros((episodes, EPISODE_STEPS), np.float32)
    for episode, (step, value) in (ends or {}).items():
        done[episode, step:] = True
        reward[episode, step] = value
    return {
        "position": rng.normal(size=(episodes, EPISODE_STEPS + 1, SHAPES, 2)),
        "rotation": rng.normal(size=(episodes, EPISODE_STEPS + 1, SHAPES)),
        "reward": reward,
        "done": done,
    }


def test_inputs_are_multi_discrete_actions_and_start_offsets_of_exactly_the_perturbation(tmp_path):
    level = tmp_path / "level.json"
    level.write_text('{"level": "a"}')
    inputs = paired_inputs(str(level), episodes=5, seed=0, shapes=7)
    actions, offsets = inputs["actions"], inputs["offsets"]
    assert actions.shape == (5, EPISODE_STEPS, len(MULTI_DISCRETE_SIZES)) and actions.dtype == np.int32
    assert np.all((actions >= 0) & (actions < np.array(MULTI_DISCRETE_SIZES)))
    assert offsets.shape == (5, 7, 2)
    np.testing.assert_allclose(np.linalg.norm(offsets, axis=-1), PERTURBATION_M, rtol=1e-12)
    assert PERTURBATION_M == 1e-6


def test_inputs_are_the_same_bytes_for_the_same_level_file_and_seed_and_differ_otherwise(tmp_path):
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    a.write_text('{"level": "a"}')
    b.write_text('{"level": "a"}')  # the same bytes elsewhere: the same inputs
    first, again = paired_inputs(str(a), 3, 0, 4), paired_inputs(str(b), 3, 0, 4)
    for name in ("actions", "offsets"):
        assert first[name].tobytes() == again[name].tobytes()
    assert paired_inputs(str(a), 3, 1, 4)["actions"].tobytes() != first["actions"].tobytes()
    b.write_text('{"level": "b"}')
    assert paired_inputs(str(b), 3, 0, 4)["actions"].tobytes() != first["actions"].tobytes()


def test_identical_runs_end_alike_with_zero_error():
    ours = trace(ends={0: (10, 1.0), 1: (40, -1.0)})
    kinetix = {"plain": ours, "perturbed": {key: value.copy() for key, value in ours.items()}}
    compared = compare_level(ours, kinetix, np.ones(SHAPES, bool))
    for label in ("kforge", "ceiling"):
        assert compared[label]["same_end"].all()
        assert not compared[label]["position"].any() and not compared[label]["angle"].any()


def test_ends_differ_in_the_outcome_or_in_the_step():
    base = trace(ends={0: (10, 1.0), 1: (40, -1.0), 2: (50, 1.0)})
    other = trace(ends={0: (11, 1.0), 1: (40, 1.0), 2: (50, 1.0)})  # a step later; a success for a failure; alike
    np.testing.assert_array_equal(same_ends(base, other), [False, False, True, True])


def test_pose_errors_are_the_largest_over_active_shapes_with_angles_taken_around_the_circle():
    a, b = trace(episodes=1), trace(episodes=1)
    b["position"], b["rotation"] = a["position"].copy(), a["rotation"].copy()
    b["position"][0, 5, 0] += [3.0, 4.0]  # 5 m on an active shape
    b["position"][0, 6, 2] += [10.0, 0.0]  # an inactive shape: not counted
    b["rotation"][0, 7, 1] += 2 * np.pi + 0.25  # a full turn more is no error
    b["rotation"][0, 8, 0] -= 2 * np.pi - 0.5
    position, angle = pose_errors(a, b, np.array([True, True, False]))
    assert position.shape == angle.shape == (1, EPISODE_STEPS + 1)
    assert position[0, 5] == pytest.approx(5.0) and position[0, 6] == 0.0
    assert angle[0, 7] == pytest.approx(0.25) and angle[0, 8] == pytest.approx(0.5)
    assert np.count_nonzero(position) == 1 and np.count_nonzero(angle) == 2


def test_an_unstable_episode_counts_in_the_curves_until_it_goes_nan_and_is_counted():
    a, b = trace(episodes=3), trace(episodes=3, seed=1)
    b["position"][2, 100:] = np.nan  # one engine's third episode blows up at step 100
    b["rotation"][2, 100:] = np.nan
    position, angle = pose_errors(a, b, np.ones(SHAPES, bool))
    assert (
        np.isnan(position[2, 100:]).all() and np.isnan(angle[2, 100:]).all() and not np.isnan(position[2, :100]).any()
    )
    zeros = np.zeros(3, bool)
    summary = summarize(
        {
            "random/l/x": {
                label: {"same_end": zeros, "position": position, "angle": angle} for label in ("kforge", "ceiling")
            }
        }
    )
    curve = summary["size/l"]["kforge"]["position_error"]
    assert curve["nan_episodes"] == 1
    assert curve["median"][EPISODE_STEPS] == pytest.approx(float(np.median(position[:2, EPISODE_STEPS])), rel=1e-2)


def test_shares_per_set_and_size_and_ours_minus_the_ceiling_in_points():
    def level(kforge_alike: list[bool], ceiling_alike: list[bool]) -> dict:
        zeros = np.zeros((len(kforge_alike), EPISODE_STEPS + 1))
        return {
            "kforge": {"same_end": np.array(kforge_alike), "position": zeros + 0.1, "angle": zeros},
            "ceiling": {"same_end": np.array(ceiling_alike), "position": zeros, "angle": zeros},
        }

    summary = summarize(
        {
            "hand/s/a": level([True, False], [True, True]),
            "random/s/k0-00000": level([True, True], [True, True]),
            "random/m/k0-00000": level([False, False], [True, False]),
        }
    )
    assert set(summary) == {"hand/s", "random/s", "random/m", "size/s", "size/m"}
    assert summary["hand/s"]["kforge"]["share"] == 0.5 and summary["hand/s"]["ceiling"]["share"] == 1.0
    assert summary["size/s"]["episodes"] == 4 and summary["size/s"]["kforge"]["same_end"] == 3
    assert summary["size/s"]["kforge_minus_ceiling_points"] == pytest.approx(-25.0)
    assert summary["random/m"]["kforge_minus_ceiling_points"] == pytest.approx(-50.0)
    curve = summary["size/s"]["kforge"]["position_error"]
    assert len(curve["median"]) == EPISODE_STEPS + 1 and set(curve["median"]) == {0.1}


def test_the_plot_is_written(tmp_path):
    zeros = np.zeros((2, EPISODE_STEPS + 1))
    same = {"same_end": np.array([True, True]), "position": zeros + 1e-3, "angle": zeros + 1e-4}
    summary = summarize({"hand/s/a": {"kforge": same, "ceiling": same}})
    fidelity_paired.plot(summary, tmp_path / "errors.png")
    assert (tmp_path / "errors.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_a_kept_kinetix_trace_of_other_actions_is_refused(tmp_path):
    """Kinetix's kept trace names the digest of the actions it played: a trace of other actions never pairs."""
    path = str(bundled_level_path("s/h1_thrust_over_ball"))
    inputs = {"a": paired_inputs(path, 2, 0, 7)}
    other = paired_inputs(path, 2, 1, 7)["actions"]
    np.savez(kept_trace(tmp_path, path, 2, 0), actions_sha256=hashlib.sha256(other.tobytes()).hexdigest())
    with pytest.raises(RuntimeError, match="played other actions than ours"):
        kinetix_traces(None, {"a": path}, inputs, 0, tmp_path, 1, print)


def test_a_count_of_random_levels_per_size_must_match_the_sizes_before_kinetix_is_looked_for(tmp_path, capsys):
    venv = tmp_path / "no-kinetix-here"
    with pytest.raises(SystemExit):
        fidelity_paired.main(["--sizes", "s", "m", "--random-levels", "1", "2", "3", "--kinetix-venv", str(venv)])
    assert "one count or one per size (2), got 3" in capsys.readouterr().err
    assert not venv.exists()


@pytest.mark.slow  # compiles kforge's program for one and for two levels: about a minute
def test_our_engine_against_itself_with_identical_inputs_ends_every_episode_alike_with_zero_error():
    """The same inputs played twice, once alone and once beside another level: 100 % alike, no error at any step."""
    names = {"hand/s/a": "s/h1_thrust_over_ball", "hand/s/b": "s/h3_point_the_thruster"}
    paths = {name: str(bundled_level_path(level)) for name, level in names.items()}
    inputs = {name: paired_inputs(path, 3, 0, len(active_shapes(path))) for name, path in paths.items()}
    alone = play_ours({"hand/s/a": paths["hand/s/a"]}, inputs, "kinetix", print)["hand/s/a"]
    beside = play_ours(paths, inputs, "kinetix", print)["hand/s/a"]
    twin = {"plain": alone, "perturbed": alone}
    compared = compare_level(beside, twin, active_shapes(paths["hand/s/a"]))
    assert summarize({"hand/s/a": compared})["hand/s"]["kforge"]["share"] == 1.0
    assert not compared["kforge"]["position"].any() and not compared["kforge"]["angle"].any()


@pytest.mark.slow  # Kinetix's virtualenv (built on first use), one compiled Kinetix call on two levels: 2-3 minutes
def test_kinetix_plays_our_actions_and_moves_only_active_shapes_by_the_perturbation(tmp_path, monkeypatch):
    """Two hand-designed s levels: Kinetix's trace names our actions' digest; its plain start is ours; its perturbed
    start is the plain one moved by the offsets on active shapes (to float32 rounding) and not at all elsewhere; a
    second call reads the kept traces without running Kinetix."""
    from benchmarks.kinetix_venv import DEFAULT_KINETIX_VENV, kinetix_python

    python = kinetix_python(DEFAULT_KINETIX_VENV, print)
    names = {"hand/s/a": "s/h1_thrust_over_ball", "hand/s/b": "s/h3_point_the_thruster"}
    paths = {name: str(bundled_level_path(level)) for name, level in names.items()}
    active = {name: active_shapes(path) for name, path in paths.items()}
    inputs = {name: paired_inputs(path, 2, 0, len(active[name])) for name, path in paths.items()}
    theirs = kinetix_traces(python, paths, inputs, 0, tmp_path, 2, print)
    ours = play_ours(paths, inputs, "kinetix", print)
    for name in paths:
        stored = np.load(kept_trace(tmp_path, paths[name], 2, 0))
        assert str(stored["actions_sha256"]) == hashlib.sha256(inputs[name]["actions"].tobytes()).hexdigest()
        plain, perturbed = theirs[name]["plain"]["position"][:, 0], theirs[name]["perturbed"]["position"][:, 0]
        np.testing.assert_array_equal(plain[:, active[name]], ours[name]["position"][:, 0, active[name]])
        shift = perturbed.astype(np.float64) - plain
        magnitude = np.maximum(np.abs(plain), np.abs(perturbed)).astype(np.float32)
        rounding = np.spacing(magnitude).astype(np.float64)  # of the offset to float32, and of the sum
        assert np.all(np.abs(shift - inputs[name]["offsets"])[:, active[name]] <= rounding[:, active[name]])
        assert not shift[:, ~active[name]].any()
        compared = compare_level(ours[name], theirs[name], active[name])
        assert not compared["kforge"]["position"][:, 0].any()
        assert np.all(np.abs(compared["ceiling"]["position"][:, 0] - PERTURBATION_M) <= 2 * rounding.max())
    monkeypatch.setattr(fidelity_paired, "run_kinetix", lambda *args, **kwargs: pytest.fail("Kinetix ran again"))
    again = kinetix_traces(python, paths, inputs, 0, tmp_path, 2, print)
    np.testing.assert_array_equal(again["hand/s/a"]["plain"]["position"], theirs["hand/s/a"]["plain"]["position"])
