"""benchmarks/fidelity.py's agreement rule: rates agree within two standard errors of their difference plus 0.02,
and the no-op outcome must be the same; per set and size, the share of levels that agree. Kinetix's outcomes kept
per level file, so that a long measurement resumes and grows."""

import argparse
import dataclasses
import json
import math
import subprocess
from pathlib import Path

import pytest

from benchmarks import fidelity
from benchmarks.fidelity import KinetixStore, compare, summarize
from benchmarks.kinetix_variants import parse_variant
from benchmarks.kinetix_venv import DEFAULT_KINETIX_VENV, REPOSITORY, kinetix_python
from kforge.env import bundled_level_path, load_level


def counts(success: int, failure: int, episodes: int = 100) -> dict:
    return {"success": success, "failure": failure, "timeout": episodes - success - failure, "unstable": 0}


def level(noop: str, success: int, failure: int) -> dict:
    return {"noop": noop, "random": counts(success, failure)}


def test_a_kinetix_virtualenv_named_relative_to_the_working_folder_is_found_from_any_folder(tmp_path, monkeypatch):
    """Kinetix's side runs from the top of the checkout, so a `--kinetix-venv` given relative to where the command was
    typed is made absolute first (here a virtualenv whose python answers the import check)."""
    python = tmp_path / "kx" / "bin" / "python"
    python.parent.mkdir(parents=True)
    python.write_text("#!/bin/sh\nexit 0\n")
    python.chmod(0o755)
    monkeypatch.chdir(tmp_path)
    found = kinetix_python(Path("kx"), print)
    assert found.is_absolute() and found == python


def test_equal_rates_agree_and_far_rates_do_not():
    ours = {"hand/s/a": level("timeout", 50, 10), "hand/s/b": level("timeout", 62, 0)}
    theirs = {"hand/s/a": level("timeout", 50, 10), "hand/s/b": level("timeout", 6, 0)}
    report = compare(ours, theirs)
    assert report["hand/s/a"]["agree"]
    assert not report["hand/s/b"]["agree"]
    assert not report["hand/s/b"]["random_success"]["agree"] and report["hand/s/b"]["random_failure"]["agree"]
    # 0.62 against 0.06 over 100 episodes each: standard error sqrt(.62 .38 / 100 + .06 .94 / 100) = 0.0540.
    assert abs(report["hand/s/b"]["random_success"]["standard_error"] - 0.05404) < 1e-4


def test_the_threshold_is_two_standard_errors_plus_two_points():
    # 0.30 against 0.20 over 100 episodes: standard error 0.0608, threshold 0.1416 > 0.10: agree;
    # 0.35 against 0.20: 0.15 > 2 x 0.0622 + 0.02 = 0.1445: disagree.
    report = compare(
        {"r/s/near": level("timeout", 30, 0), "r/s/far": level("timeout", 35, 0)},
        {"r/s/near": level("timeout", 20, 0), "r/s/far": level("timeout", 20, 0)},
    )
    assert report["r/s/near"]["agree"] and not report["r/s/far"]["agree"]


def test_a_different_noop_outcome_disagrees_and_shares_are_per_set_and_size():
    same = {"hand/s/b": level("timeout", 0, 0), "hand/m/c": level("failure", 0, 0)}
    ours = {"hand/s/a": level("success", 0, 0), **same}
    theirs = {"hand/s/a": level("timeout", 0, 0), **same}
    summary = summarize(compare(ours, theirs))
    assert summary["hand/s"] == {"levels": 2, "agree": 1, "disagree": ["hand/s/a"], "share": 0.5}
    assert summary["hand/m"]["share"] == 1.0


def _outcome(noop: str, success: int) -> dict:
    return {"size": "s", "noop": noop, "random": counts(success, 0, episodes=10)}


def test_kinetix_outcomes_are_kept_per_level_file_and_survive_a_new_store(tmp_path):
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    a.write_text('{"level": "a"}')
    b.write_text('{"level": "b"}')
    file = tmp_path / "kinetix.json"
    store = KinetixStore(file, episodes=10, seed=0)
    names = {"random/s/a": str(a), "random/s/b": str(b)}
    assert store.missing(names) == names
    store.add({str(a): _outcome("success", 7)})  # a chunk played: kept on disk at once
    again = KinetixStore(file, episodes=10, seed=0)
    assert again.missing(names) == {"random/s/b": str(b)}
    assert again.of({"random/s/a": str(a)}) == {"random/s/a": {"noop": "success", "random": counts(7, 0, 10)}}
    assert not file.with_name(file.name + ".partial").exists()


def test_stored_outcomes_are_keyed_by_the_level_bytes_the_episodes_and_the_seed(tmp_path):
    level = tmp_path / "a.json"
    level.write_text('{"level": "a"}')
    file = tmp_path / "kinetix.json"
    KinetixStore(file, episodes=10, seed=0).add({str(level): _outcome("timeout", 3)})
    names = {"random/s/a": str(level)}
    assert KinetixStore(file, episodes=10, seed=0).missing(names) == {}
    assert KinetixStore(file, episodes=20, seed=0).missing(names) == names
    assert KinetixStore(file, episodes=10, seed=1).missing(names) == names
    level.write_text('{"level": "a, edited"}')
    assert KinetixStore(file, episodes=10, seed=0).missing(names) == names


def test_a_store_file_of_another_format_is_refused_in_one_line(tmp_path):
    file = tmp_path / "kinetix.json"
    file.write_text(json.dumps({"key": {"levels": [], "episodes": 280, "seed": 0}, "outcomes": {}}))
    with pytest.raises(SystemExit, match="not a file of Kinetix's outcomes") as refused:
        KinetixStore(file, episodes=280, seed=0)
    assert "\n" not in str(refused.value)


def test_a_variant_of_kinetix_is_stored_under_keys_of_its_own(tmp_path):
    file, path = tmp_path / "kinetix.json", tmp_path / "level.json"
    path.write_text("{}")
    released = KinetixStore(file, episodes=8, seed=0)
    released.add({str(path): level("success", 8, 0)})
    changed = KinetixStore(file, episodes=8, seed=0, variant={"padding_writes": 0})
    assert changed.missing({"x": str(path)}) == {"x": str(path)}
    changed.add({str(path): level("timeout", 1, 0)})
    reread = KinetixStore(file, episodes=8, seed=0)
    assert reread.of({"x": str(path)})["x"]["noop"] == "success"
    reread_changed = KinetixStore(file, episodes=8, seed=0, variant={"padding_writes": 0})
    assert reread_changed.of({"x": str(path)})["x"]["noop"] == "timeout"


@pytest.mark.parametrize(
    "text",
    [
        "padding_writes=2",
        "solver_iterations=0",
        "solver_iterations=2.5",
        "slop=-0.01",
        "slop=wide",
        "substeps=0",
        "exact_disc_inertia=2",
        "gravity=1",
        "x",
    ],
)
def test_an_unknown_or_out_of_range_kinetix_variant_is_refused(text):
    with pytest.raises(argparse.ArgumentTypeError):
        parse_variant(text)


def test_a_kinetix_variant_reads_its_value_as_its_type():
    assert parse_variant("solver_batch_size=1") == ("solver_batch_size", 1)
    assert parse_variant("baumgarte_collision=0.05") == ("baumgarte_collision", 0.05)
    assert parse_variant("substeps=4") == ("substeps", 4)


def test_sim_switches_and_a_kinetix_variant_are_not_given_together(capsys):
    with pytest.raises(SystemExit):
        fidelity.main(["--sim", "speculative_reach=0", "--kinetix-variant", "padding_writes=0"])
    assert "give one of them" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        fidelity.main(["--substeps", "8", "--kinetix-variant", "padding_writes=0"])
    assert "give one of them" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        fidelity.main(["--iterations", "10", "--kinetix-variant", "padding_writes=0"])
    assert "give one of them" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        fidelity.main(["--no-relax-contacts", "--kinetix-variant", "padding_writes=0"])
    assert "give one of them" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        fidelity.main(["--physics", "kinetix", "--kinetix-variant", "padding_writes=0"])
    assert "give one of them" in capsys.readouterr().err


@pytest.mark.slow  # two env programs compiled (a minute)
def test_the_kinetix_physics_scheme_plays_as_the_measured_setting_spelled_out():
    """`--physics kinetix` (a job's env.physics=kinetix) is the setting docs/fidelity.md measured with options:
    Jax2D's solver scheme and contact geometry give the same outcomes, episode for episode."""
    paths = {"s/h5_rotate_fall": str(bundled_level_path("s/h5_rotate_fall"))}
    setting = {
        "contact_law": 1.0,
        "force_timing": 1.0,
        "speculative_distance": 0.0,
        "speculative_reach": 0.0,
        "contact_points": 1.0,
        "collision_rules": 1.0,
        "joint_law": 1.0,
        "contact_order": 1.0,
    }
    solver = {"substeps": 1, "iterations": 10, "relax_iterations": 0}
    named = fidelity.play_ours(paths, 4, 0, {}, lambda line: None, None, "kinetix")
    spelled_out = fidelity.play_ours(paths, 4, 0, setting, lambda line: None, solver)
    assert named == spelled_out and sum(named["s/h5_rotate_fall"]["random"].values()) == 4


def test_the_solver_scheme_options_change_only_ours_solver_counts():
    static = load_level(bundled_level_path("s/h5_rotate_fall")).static
    changed = fidelity.with_solver_scheme(static, {"substeps": 1, "iterations": 10, "relax_iterations": 0})
    assert (changed.sim.num_substeps, changed.sim.num_iterations, changed.sim.num_relax_iterations) == (1, 10, 0)
    assert (static.sim.num_substeps, static.sim.num_iterations, static.sim.num_relax_iterations) == (4, 1, 1)
    assert dataclasses.replace(changed, sim=static.sim) == static
    blocked = fidelity.with_solver_scheme(static, {"block_contacts": True})
    assert blocked.sim == dataclasses.replace(static.sim, block_contacts=True) and not static.sim.block_contacts
    joints_relaxed = fidelity.with_solver_scheme(static, {"relax_contacts": False})
    assert joints_relaxed.sim == dataclasses.replace(static.sim, relax_contacts=False) and static.sim.relax_contacts
    only_substeps = fidelity.with_solver_scheme(static, {"substeps": 8, "iterations": None})
    assert only_substeps.sim == dataclasses.replace(static.sim, num_substeps=8)
    assert fidelity.with_solver_scheme(static, {"substeps": None}) == static


@pytest.mark.parametrize(
    ("option", "value", "message"),
    [
        ("--substeps", "0", "--substeps must be at least 1, got 0"),
        ("--iterations", "0", "--iterations must be at least 1, got 0"),
        ("--relax-iterations", "-1", "--relax-iterations must be at least 0, got -1"),
    ],
)
def test_solver_counts_below_their_least_are_refused(capsys, option, value, message):
    with pytest.raises(SystemExit):
        fidelity.main([option, value])
    assert message in capsys.readouterr().err


STACKED_DISCS = """
import json, sys
import jax, jax.numpy as jnp
import jax2d.engine
from jax2d.engine import create_empty_sim
from jax2d.scene import add_circle_to_scene
from jax2d.sim_state import SimParams, StaticSimParams
if sys.argv[1] == "0":
    from benchmarks.kinetix_fidelity_baseline import drop_padding_writes
    drop_padding_writes()
static = StaticSimParams(num_polygons=5, num_circles=2, num_joints=1, num_thrusters=1)
state = create_empty_sim(static)
for height in (0.4 + 0.5, 0.4 + 1.5):  # the floor's top is at 0.4 m; discs of radius 0.5 m, one on the other
    state, _ = add_circle_to_scene(state, static, jnp.array([2.5, height]), 0.5)
step = jax.jit(jax2d.engine.PhysicsEngine(static).step)
for _ in range(120):
    state, _ = step(state, SimParams(), jnp.zeros(2))
print(json.dumps(float(state.acc_cc_manifolds.acc_impulse_normal[0])))
"""


@pytest.mark.slow  # builds Kinetix's virtualenv on first use (minutes), then two short Jax2D runs: about 1 minute
def test_kinetix_with_padding_writes_dropped_keeps_its_last_pairs_impulse():
    """Size s has one disc-disc pair, the last of its kind, which Jax2D's padding rows reset (B1): a disc resting
    on another carries its weight through the pair, m g dt per step (m = pi r^2 at density 1), only once the
    padding writes are dropped."""
    python = kinetix_python(DEFAULT_KINETIX_VENV, print)
    impulse = {}
    for writes in ("1", "0"):
        run = subprocess.run(
            [str(python), "-c", STACKED_DISCS, writes], capture_output=True, text=True, check=True, cwd=REPOSITORY
        )
        impulse[writes] = json.loads(run.stdout.splitlines()[-1])
    weight_per_step = math.pi * 0.5**2 * 9.81 / 60.0
    assert impulse["1"] == 0.0
    assert impulse["0"] == pytest.approx(weight_per_step, rel=0.02)


SLIDING_DISC = """
import json, sys
import jax, jax.numpy as jnp
import jax2d.engine
from jax2d.engine import create_empty_sim
from jax2d.scene import add_circle_to_scene
from jax2d.sim_state import SimParams, StaticSimParams
from benchmarks.kinetix_fidelity_baseline import with_exact_disc_inertia
static = StaticSimParams(num_polygons=5, num_circles=2, num_joints=1, num_thrusters=1)
state, _ = add_circle_to_scene(create_empty_sim(static), static, jnp.array([1.0, 0.4 + 0.5]), 0.5)  # on the floor
state = state.replace(circle=state.circle.replace(velocity=state.circle.velocity.at[0].set(jnp.array([3.0, 0.0]))))
if sys.argv[1] == "1":
    state = with_exact_disc_inertia(state)
step = jax.jit(jax2d.engine.PhysicsEngine(static).step)
for _ in range(60):
    state, _ = step(state, SimParams(), jnp.zeros(2))
print(json.dumps([float(state.circle.velocity[0, 0]), float(state.circle.angular_velocity[0])]))
"""


@pytest.mark.slow  # builds Kinetix's virtualenv on first use (minutes), then two one-second Jax2D runs: about 1 minute
def test_kinetix_with_exact_disc_inertia_rolls_a_sliding_disc_on_at_two_thirds_of_its_speed():
    """A disc sliding without spin onto a floor keeps its angular momentum about the contact point: it rolls on at
    v0 / (1 + I / (m r^2)), 2/3 of v0 for a uniform disc (the variant) and 4/5 with Jax2D's I = m r^2 / 4."""
    python = kinetix_python(DEFAULT_KINETIX_VENV, print)
    for exact, share_of_v0 in (("0", 4 / 5), ("1", 2 / 3)):
        run = subprocess.run(
            [str(python), "-c", SLIDING_DISC, exact], capture_output=True, text=True, check=True, cwd=REPOSITORY
        )
        speed, spin = json.loads(run.stdout.splitlines()[-1])
        assert speed == pytest.approx(share_of_v0 * 3.0, rel=0.02)
        assert -spin * 0.5 == pytest.approx(speed, rel=0.02)  # rolling: v = -w r


FALLING_DISC = """
import json, sys
import jax.numpy as jnp
from jax2d.scene import add_circle_to_scene
from kinetix.environment import ActionType, ObservationType, make_kinetix_env
from kinetix.environment.utils import create_empty_env
from benchmarks.kinetix_fidelity_baseline import variant_env_params
params, static = variant_env_params("s", {"substeps": int(sys.argv[1])})
env = make_kinetix_env(ActionType.MULTI_DISCRETE, ObservationType.SYMBOLIC_FLAT, None, params, static, auto_reset=False)
state, _ = add_circle_to_scene(create_empty_env(static), static, jnp.array([2.5, 3.0]), 0.1)
no_op = jnp.zeros(static.num_joints + static.num_thrusters)
after = env.engine_step(state, no_op, params)[1]  # (obs, state, reward, done, info)
print(json.dumps([3.0 - float(after.circle.position[0, 1]), int(after.timestep)]))
"""


@pytest.mark.slow  # builds Kinetix's virtualenv on first use (minutes), then two one-step Kinetix runs: about 1 minute
def test_kinetix_with_substeps_takes_that_many_shorter_physics_steps_per_env_step():
    """An env step of Kinetix is 2 physics steps of dt = 1/60 s (its frame skip); with N substeps, 2 N semi-implicit
    Euler steps of dt/N. A disc falling from rest falls g (dt/N)^2 (2N)(2N + 1) / 2 in it: 3 g dt^2 as released,
    2.25 g dt^2 with 4 substeps; the env step counts once."""
    python = kinetix_python(DEFAULT_KINETIX_VENV, print)
    dt = 1.0 / 60.0
    for substeps, share_of_g_dt2 in ((1, 3.0), (4, 2.25)):
        run = subprocess.run(
            [str(python), "-c", FALLING_DISC, str(substeps)],
            capture_output=True,
            text=True,
            check=True,
            cwd=REPOSITORY,
        )
        fall, timestep = json.loads(run.stdout.splitlines()[-1])
        assert fall == pytest.approx(share_of_g_dt2 * 9.81 * dt**2, rel=1e-4)
        assert timestep == 1


@pytest.mark.slow  # builds Kinetix's virtualenv on first use (minutes), then plays 10 levels: about 2 minutes
def test_a_level_plays_the_same_in_kinetix_alone_or_in_a_chunk_and_a_second_run_plays_nothing(tmp_path, capsys):
    file = tmp_path / "kinetix.json"
    arguments = ["--sizes", "s", "--episodes", "12", "--chunk-levels", "4", "--kinetix-results", str(file), "--json"]
    fidelity.main([*arguments, "--level-dir", str(tmp_path / "levels")])
    first = json.loads(capsys.readouterr().out)
    assert first["summary"]["hand/s"]["levels"] == 10

    store = KinetixStore(file, episodes=12, seed=0)
    level = str(bundled_level_path("s/h5_rotate_fall"))
    alone = []
    python = kinetix_python(DEFAULT_KINETIX_VENV, print)
    fidelity.run_kinetix(python, ["--levels", level, "--episodes", "12"], print, alone.append)
    played = alone[0]["played"][level]
    assert store.of({"x": level})["x"] == {"noop": played["noop"], "random": played["random"]}
    assert played["random"]["success"] not in (0, 12)  # a level whose outcomes depend on the actions drawn

    capsys.readouterr()
    fidelity.main([*arguments, "--level-dir", str(tmp_path / "levels")])
    second = capsys.readouterr()
    assert "Kinetix's outcomes of 10 of 10 levels read from" in second.err
    assert json.loads(second.out)["levels"] == first["levels"]
