"""Test group F: vmap equals a Python loop, jit equals eager, runs are bitwise repeatable, no retracing."""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from engine_test_helpers import PARAMS, SIZE_M, random_scene

from benchmarks.kernels import count_hlo_kernels
from kforge import engine
from kforge.engine import SceneBuilder, SimParams
from kforge.engine.batch_last import BATCH_CHUNK, SOLVER_LOOP_FORMS, vmap_in_chunks
from tests.helpers import stack
from tests.rollouts import ROLLOUT_STEPS, python_loop, random_actions, run_batch

COMPARE_STEPS = 50
VMAP_ATOL = 1e-6
VMAP_RTOL = 1e-5
"""Tolerance of one step. The batched and the single-scene step are compiled separately: XLA fuses them differently
and contracts different multiply-adds into FMAs, so float32 results may differ in the last bits. Steps are compared
from the same state, since over a whole trajectory chaotic scenes amplify such differences without bound."""
EAGER_RTOL = 1e-5
"""Relative jit-vs-eager tolerance: XLA fuses and reorders float32 operations differently from eager."""
EAGER_ATOL = 1e-5
EAGER_STEPS = 3


def _stack_scene():
    b = SceneBuilder(SIZE_M)
    b.add_box((2.5, 0.65), (0.6, 0.5), friction=0.8)
    b.add_box((2.55, 1.16), (0.4, 0.5), rotation=0.05)
    b.add_circle((2.5, 1.7), 0.15, restitution=0.3)
    return b.build()


def _pendulum_scene():
    b = SceneBuilder(SIZE_M)
    link1 = b.add_box((3.0, 4.0), (1.0, 0.1), rotation=0.0)
    link2 = b.add_box((3.5, 3.5), (0.1, 1.0))
    b.add_revolute_joint(3, link1, (2.5, 4.0))  # hinge on the ceiling
    b.add_revolute_joint(link1, link2, (3.5, 4.0), limits=(-0.8, 0.8))
    return b.build()


def _thruster_scene():
    b = SceneBuilder(SIZE_M)
    box = b.add_box((1.0, 0.6), (0.4, 0.4), friction=0.3)
    ball = b.add_circle((3.0, 2.0), 0.2)
    b.add_thruster(box, (1.1, 0.6), np.pi / 2 + 0.3, 2.0)
    b.add_thruster(ball, (3.0, 2.0), 0.5, 1.0)
    return b.build()


def _vehicle_scene():
    """Motorised wheels on the floor, a thruster on the chassis, and a triangle falling onto it: every feature."""
    b = SceneBuilder(SIZE_M)
    chassis = b.add_box((2.0, 0.9), (1.0, 0.2))
    wheel_a = b.add_circle((1.6, 0.65), 0.25, friction=1.0)
    wheel_b = b.add_circle((2.4, 0.65), 0.25, friction=1.0)
    b.add_revolute_joint(chassis, wheel_a, (1.6, 0.65), motor_on=True, motor_speed=1.0, motor_power=2.0)
    b.add_revolute_joint(
        chassis, wheel_b, (2.4, 0.65), motor_on=True, motor_speed=-1.0, motor_power=1.0, limits=(-0.3, 0.3)
    )
    b.add_thruster(chassis, (1.5, 0.9), 0.2, 1.0)
    b.add_polygon((2.1, 1.3), np.array([[-0.15, 0.0], [0.15, 0.0], [0.0, 0.2]]), rotation=0.4, angular_velocity=2.0)
    return b.build()


def _circles_scene():
    b = SceneBuilder(SIZE_M)
    b.add_circle((1.0, 1.0), 0.2, velocity=(3.0, 0.0), restitution=1.0)
    b.add_circle((2.0, 1.05), 0.3, velocity=(-1.0, 0.5), restitution=0.5)
    b.add_circle((4.0, 3.0), 0.15, velocity=(-2.0, -3.0), friction=0.0)
    b.add_polygon((3.0, 2.0), np.array([[0.0, 0.0], [0.4, 0.0], [0.1, 0.3]]), angular_velocity=4.0)
    return b.build()


def _scenes():
    rng = np.random.default_rng(7)
    return {
        "stack": _stack_scene(),
        "pendulum": _pendulum_scene(),
        "thrusters": _thruster_scene(),
        "vehicle": _vehicle_scene(),
        "circles": _circles_scene(),
        "empty_arena": SceneBuilder(SIZE_M).build(),
        "empty": SceneBuilder(SIZE_M, boundaries=False).build(),
        "random": random_scene(rng, overlapping=True),
    }


@pytest.fixture(scope="module")
def batch():
    scenes = _scenes()
    names = list(scenes)
    states = [scenes[k] for k in names]
    motors, thrusters = random_actions(np.random.default_rng(3), SIZE_M, batch=len(states))
    final, traj = run_batch(states, motors, thrusters)
    return dict(names=names, states=states, motors=motors, thrusters=thrusters, final=final, traj=traj)


def _dynamic_fields(bodies):
    return {f: np.asarray(getattr(bodies, f)) for f in ("position", "rotation", "velocity", "angular_velocity")}


def test_scenes_are_not_trivial(batch):
    """Guard: the comparison below is meaningless if nothing moves."""
    traj = batch["traj"]
    for i, name in enumerate(batch["names"]):
        if name.startswith("empty"):
            continue
        moved = np.abs(traj.bodies.position[i, COMPARE_STEPS - 1] - batch["states"][i].bodies.position).max()
        assert moved > 1e-3, name
    assert np.any(traj.info.touching[batch["names"].index("stack"), :COMPARE_STEPS])


def _state_before(batch, i: int, k: int):
    """Scene `i`'s full state before step `k` (0-based) of the batched rollout."""
    start = batch["states"][i]
    if k == 0:
        return start
    traj = batch["traj"]

    def at(tree):
        return jax.tree_util.tree_map(lambda x: jnp.asarray(x[i, k - 1]), tree)

    return start.replace(bodies=at(traj.bodies), joints=at(traj.joints), contacts=at(traj.contacts))


def test_vmap_equals_python_loop(batch):
    """Each step of each scene of the vmapped batch equals `engine.step` of that scene alone from the same state."""
    traj = batch["traj"]
    failures = []
    for i, name in enumerate(batch["names"]):
        worst, first_bad = {}, None
        for k in range(COMPARE_STEPS):
            motors, thrusters = jnp.asarray(batch["motors"][i, k]), jnp.asarray(batch["thrusters"][i, k])
            state, info = engine.step(_state_before(batch, i, k), PARAMS, motors, thrusters, static=SIZE_M)
            pairs = {
                f"bodies.{f}": (traj_f[i, k], loop_f)
                for f, traj_f, loop_f in (
                    (f, np.asarray(getattr(traj.bodies, f)), np.asarray(getattr(state.bodies, f)))
                    for f in ("position", "rotation", "velocity", "angular_velocity")
                )
            }
            for f in ("linear_impulse", "motor_impulse", "limit_impulse"):
                pairs[f"joints.{f}"] = (np.asarray(getattr(traj.joints, f))[i, k], np.asarray(getattr(state.joints, f)))
            np.testing.assert_array_equal(
                traj.info.touching[i, k], np.asarray(info.touching), err_msg=f"{name} step {k + 1}"
            )
            sep_loop, sep_vmap = np.asarray(info.separation), traj.info.separation[i, k]
            np.testing.assert_array_equal(np.isfinite(sep_loop), np.isfinite(sep_vmap), err_msg=f"{name} step {k + 1}")
            finite = np.isfinite(sep_loop)
            pairs["info.separation"] = (sep_vmap[finite], sep_loop[finite])
            for field, (got, expected) in pairs.items():
                # Error in units of the tolerance: > 1 fails.
                err = float(np.max(np.abs(got - expected) / (VMAP_ATOL + VMAP_RTOL * np.abs(expected)), initial=0.0))
                worst[field] = max(worst.get(field, 0.0), err)
                if err > 1.0 and first_bad is None:
                    first_bad = (k + 1, field, err)
        if first_bad is not None:
            field, err = max(worst.items(), key=lambda item: item[1])
            failures.append(
                f"{name}: first step beyond tolerance {first_bad[0]} ({first_bad[1]}, {first_bad[2]:.3g}x); "
                f"worst over {COMPARE_STEPS} steps {err:.3g}x ({field})"
            )
    assert not failures, f"vmap vs single steps (atol {VMAP_ATOL:g}, rtol {VMAP_RTOL:g}):\n" + "\n".join(failures)


def test_vmap_in_chunks_equals_one_vmap():
    """Batches larger than the chunk limit run as equal chunks (the last one padded), with identical results."""

    def function(tree, scale):
        return {"sum": tree["a"] * scale + tree["b"].sum(), "pair": (tree["a"] - 1.0, tree["b"] * 2.0)}

    rng = np.random.default_rng(0)
    tree = {"a": rng.normal(size=7).astype(np.float32), "b": rng.normal(size=(7, 2)).astype(np.float32)}
    chunked = jax.jit(jax.vmap(vmap_in_chunks(function, chunk_limit=3), in_axes=(0, None)))
    plain = jax.jit(jax.vmap(function, in_axes=(0, None)))
    for size in (1, 3, 7):  # one partial chunk, one full chunk, three chunks of which the last is padded
        part = jax.tree_util.tree_map(lambda x, n=size: x[:n], tree)
        got, expected = chunked(part, np.float32(1.5)), plain(part, np.float32(1.5))
        jax.tree_util.tree_map(np.testing.assert_array_equal, got, expected)


def test_batched_runs_are_bitwise_repeatable(batch):
    final, traj = run_batch(batch["states"], batch["motors"], batch["thrusters"])
    first = jax.tree_util.tree_leaves((batch["final"], batch["traj"]))
    for got, expected in zip(jax.tree_util.tree_leaves((final, traj)), first, strict=True):
        np.testing.assert_array_equal(got, expected)
    assert traj.bodies.position.shape[1] == ROLLOUT_STEPS


def test_single_steps_are_bitwise_repeatable(batch):
    i = batch["names"].index("random")
    first = python_loop(batch["states"][i], batch["motors"][i, :5], batch["thrusters"][i, :5])
    second = python_loop(batch["states"][i], batch["motors"][i, :5], batch["thrusters"][i, :5])
    for a, b in zip(jax.tree_util.tree_leaves(first), jax.tree_util.tree_leaves(second), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.slow  # eager execution compiles every primitive separately: about a minute on 2 CPU cores
def test_jit_equals_eager(batch):
    name = "vehicle"
    i = batch["names"].index(name)
    state = batch["states"][i]
    motors, thrusters = batch["motors"][i, :EAGER_STEPS], batch["thrusters"][i, :EAGER_STEPS]
    jitted = python_loop(state, motors, thrusters)
    with jax.disable_jit():
        eager = python_loop(state, motors, thrusters)
    for k, ((s_jit, i_jit), (s_eager, i_eager)) in enumerate(zip(jitted, eager, strict=True)):
        for field, value in _dynamic_fields(s_jit.bodies).items():
            np.testing.assert_allclose(
                value,
                _dynamic_fields(s_eager.bodies)[field],
                atol=EAGER_ATOL,
                rtol=EAGER_RTOL,
                err_msg=f"{name} step {k + 1} {field}: jit vs eager",
            )
        finite = np.isfinite(np.asarray(i_jit.separation))
        np.testing.assert_array_equal(finite, np.isfinite(np.asarray(i_eager.separation)))
        np.testing.assert_allclose(
            np.asarray(i_eager.separation)[finite], np.asarray(i_jit.separation)[finite], atol=EAGER_ATOL, rtol=0
        )


# --------------------------------------------------------------------------- retracing
_traces: list[int] = []


@functools.partial(jax.jit, static_argnames="static")
def _counted_step(state, params, motor_actions, thruster_actions, static):
    _traces.append(1)  # runs only while tracing
    return engine.step(state, params, motor_actions, thruster_actions, static=static)


def test_no_retrace_for_new_scenes_of_the_same_size(batch):
    """Different scenes, step outputs fed back, and new parameter values all reuse the compiled step."""
    zeros_m, zeros_t = jnp.zeros(SIZE_M.num_joints), jnp.zeros(SIZE_M.num_thrusters)
    states = batch["states"]
    call, count = _counted_step, lambda: len(_traces)  # engine.step is a plain function over a jitted step
    first, _ = call(states[0], PARAMS, zeros_m, zeros_t, static=SIZE_M)
    before = count()
    after_step, _ = call(first, PARAMS, zeros_m, zeros_t, static=SIZE_M)
    for state in states[1:]:
        call(state, PARAMS, zeros_m, zeros_t, static=SIZE_M)
    fresh = SceneBuilder(SIZE_M)
    fresh.add_circle((1.0, 1.0), 0.3)
    call(fresh.build(), PARAMS, zeros_m, zeros_t, static=SIZE_M)
    # Same array types as before (strong float32), new values; parameters are traced floats.
    half = jnp.asarray(np.full(SIZE_M.num_thrusters, 0.5, np.float32))
    call(
        after_step,
        SimParams(dt=1.0 / 120.0, base_friction=0.7),
        jnp.ones(SIZE_M.num_joints, jnp.float32),
        half,
        static=SIZE_M,
    )
    assert count() == before, f"step was retraced: cache size {before} -> {count()}"


TEST_CHUNK_LIMIT = 4
"""A chunk limit small enough that the mode test batch (`MODE_SCENES` scenes) runs as three chunks, the last one
padded: a batch larger than a chunk, split as the default `BATCH_CHUNK` (256) splits a larger one, at a size that
steps cheaply."""
MODE_SCENES = 2 * TEST_CHUNK_LIMIT + 2
"""Three chunks of four scenes under `TEST_CHUNK_LIMIT`, the last one padded with two copies of its last scene."""
MODE_STEPS = 3


def _mode_picks(batch) -> list[int]:
    """The scene of each of the `MODE_SCENES` rows of the mode test batch (the batch's scenes, repeated)."""
    return [k % len(batch["states"]) for k in range(MODE_SCENES)]


def _step_batch_in_mode(mode: str, batch, solver_loops: str = "auto"):
    """`MODE_STEPS` vmapped steps of the mode test batch under `engine.Batching(mode, TEST_CHUNK_LIMIT,
    solver_loops)`: the first step's (state, info), the state after the last step, and the compiled program's text."""
    picks = _mode_picks(batch)
    states = stack(*[batch["states"][k] for k in picks])
    motors, thrusters = batch["motors"][picks], batch["thrusters"][picks]
    static = dataclasses.replace(SIZE_M, batching=engine.Batching(mode, TEST_CHUNK_LIMIT, solver_loops))
    stepped = jax.jit(jax.vmap(lambda s, m, t: engine.step(s, PARAMS, m, t, static=static)))
    compiled = stepped.lower(states, motors[:, 0], thrusters[:, 0]).compile()
    first = compiled(states, motors[:, 0], thrusters[:, 0])
    states = first[0]
    for k in range(1, MODE_STEPS):
        states, _ = compiled(states, motors[:, k], thrusters[:, k])
    return first, states, compiled.as_text()


@pytest.fixture(scope="module")
def chunked_run(batch):
    """The mode test batch stepped in chunks of at most `TEST_CHUNK_LIMIT` (one compile for two tests)."""
    return _step_batch_in_mode("chunked", batch)


def test_batches_larger_than_a_chunk_equal_single_steps(batch, request):
    """A vmapped step over more than a chunk of scenes (run in chunks, the last one padded) equals each scene stepped
    alone, row by row (`chunked_run`: chunks of `TEST_CHUNK_LIMIT`, the program that
    test_chunked_and_whole_batching_and_every_solver_loop_form_give_the_same_states compares with whole vmaps)."""
    picks = _mode_picks(batch)
    motors, thrusters = batch["motors"][picks, 0], batch["thrusters"][picks, 0]
    alone = {}
    for k in sorted(set(picks)):  # each scene stepped alone
        state, info = engine.step(
            batch["states"][k], PARAMS, jnp.asarray(motors[k]), jnp.asarray(thrusters[k]), static=SIZE_M
        )
        alone[k] = (_dynamic_fields(state.bodies), np.asarray(info.touching))
    (stepped, info), _, _ = request.getfixturevalue("chunked_run")
    for index, k in enumerate(picks):
        fields, touching = alone[k]
        for field, expected in fields.items():
            np.testing.assert_allclose(
                np.asarray(getattr(stepped.bodies, field))[index],
                expected,
                atol=VMAP_ATOL,
                rtol=VMAP_RTOL,
                err_msg=f"row {index} (scene {batch['names'][k]}): {field}",
            )
        np.testing.assert_array_equal(np.asarray(info.touching)[index], touching, err_msg=f"row {index}")


def test_chunked_and_whole_batching_and_every_solver_loop_form_give_the_same_states(batch, chunked_run):
    """Chunked with batch-last layout and the solver's loops looped (the CPU's "auto":
    test_auto_batching_chunks_and_loops_on_cpu_only), and one whole vmap with the solver's loops looped, with only
    its sweeps unrolled, and unrolled (an accelerator's "auto") step a batch larger than a chunk alike; the more is
    written out, the fewer kernels the whole step runs."""
    _, chunked, chunked_program = chunked_run
    whole, programs = {}, {}
    for form in SOLVER_LOOP_FORMS:
        _, whole[form], programs[form] = _step_batch_in_mode("whole", batch, solver_loops=form)
    assert len({chunked_program, *programs.values()}) == 4, "the batching option did not change the program"
    for form, stepped in whole.items():
        for field, expected in _dynamic_fields(chunked.bodies).items():
            np.testing.assert_allclose(
                np.asarray(getattr(stepped.bodies, field)),
                expected,
                atol=VMAP_ATOL * MODE_STEPS,
                rtol=VMAP_RTOL * MODE_STEPS,
                err_msg=f"whole vmap, solver's loops {form}, vs chunked: {field}",
            )
    kernels = {form: count_hlo_kernels(program).kernels for form, program in programs.items()}
    assert kernels["unrolled"] < kernels["unrolled_sweeps"] < 0.7 * kernels["looped"], kernels


def test_the_batching_is_a_static_option_of_each_step_not_a_physics_option(batch):
    """Two programs traced side by side (as an env's step traces `engine.step`) under static params that differ only
    in their batching are different programs; the batching is not among the physics options a dataset's definition
    holds."""
    zeros_m, zeros_t = jnp.zeros(SIZE_M.num_joints), jnp.zeros(SIZE_M.num_thrusters)
    states = stack(*batch["states"][:2])
    jaxprs = {}
    for mode in ("chunked", "whole"):
        static = dataclasses.replace(SIZE_M, batching=engine.Batching(mode))
        wrapper = jax.jit(lambda s, static=static: engine.step(s, PARAMS, zeros_m, zeros_t, static=static)[0])
        jaxprs[mode] = str(jax.make_jaxpr(jax.vmap(wrapper))(states))
    assert jaxprs["chunked"] != jaxprs["whole"]
    unrolled = dataclasses.replace(SIZE_M, batching=engine.Batching("whole", 8, "unrolled"))
    assert unrolled != SIZE_M and unrolled.physics_options() == SIZE_M.physics_options()
    assert "batching" not in SIZE_M.physics_options()


def test_auto_batching_chunks_and_loops_on_cpu_only():
    assert jax.default_backend() == "cpu"
    assert SIZE_M.batching == engine.Batching("auto", BATCH_CHUNK, "auto")
    assert SIZE_M.batching.resolved() == engine.Batching("chunked", BATCH_CHUNK, "looped")
    assert SIZE_M.batching.resolved("gpu") == engine.Batching("whole", BATCH_CHUNK, "unrolled")
    assert engine.Batching("whole", 8, "looped").resolved("gpu") == engine.Batching("whole", 8, "looped")
    with pytest.raises(ValueError, match="batching mode 'gpu'"):
        engine.Batching("gpu")
    with pytest.raises(ValueError, match="solver_loops mode 'fast' is not one of"):
        engine.Batching(solver_loops="fast")
    with pytest.raises(ValueError, match="chunk_limit must be a positive number of scenes, got 0"):
        engine.Batching(chunk_limit=0)


def _elastic_drop_scene(restitution: float):
    """A ball falling onto a floor, both of `restitution` (a pair bounces with the smaller of its two)."""
    b = SceneBuilder(SIZE_M, boundaries=False)
    b.add_box((2.5, -0.1), (10.0, 1.0), static=True, slot=0, restitution=restitution)
    b.add_circle((2.5, 1.0), 0.15, velocity=(0.0, -4.0), restitution=restitution)
    return b.build()


def test_a_bounce_beside_scenes_that_do_not_bounce():
    """The batched step skips the restitution sweep only when no point of the whole batch bounces: an elastic ball
    falling onto the floor beside resting scenes rebounds at nearly its impact speed, and an inelastic one does not."""
    resting = [_stack_scene(), SceneBuilder(SIZE_M).build()]
    _, trajectory = run_batch([_elastic_drop_scene(1.0), _elastic_drop_scene(0.0), *resting])
    ball = SIZE_M.num_polygons  # the first circle slot
    vertical = trajectory.bodies.velocity[:, :, ball, 1]
    impact = -np.min(vertical[0])
    assert impact > 4.0  # guard: the ball fell onto the floor within the rollout
    assert np.max(vertical[0]) > 0.9 * impact
    assert np.max(vertical[1, np.argmin(vertical[1]) :]) < 0.1 * impact
