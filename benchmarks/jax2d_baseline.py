"""Jax2D baseline benchmark on fully populated Kinetix-sized scenes.

Builds the reference layout (a motorised joint chain plus a grid of loose
bodies, with thrusters) in the reference engine Jax2D and measures batched
``engine.step`` throughput, so a sibling script can compare our engine with
Jax2D on the same scenes in one run.

Usage: python -m benchmarks.jax2d_baseline --sizes s m l --batches 1 256
"""

import argparse
import time
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from jax2d import scene
from jax2d.engine import PhysicsEngine, create_empty_sim
from jax2d.sim_state import SimParams, SimState, StaticSimParams

from benchmarks.timing import best_time

# Kinetix sizes: (polygons incl. the 4 static floor/wall/ceiling slots, circles, joints, thrusters).
SIZES = {"s": (5, 2, 1, 1), "m": (6, 3, 2, 2), "l": (12, 4, 6, 2)}
NUM_STATIC_POLYS = 4

BOX_SIZE_M = (0.4, 0.3)  # width, height
CIRCLE_RADIUS_M = 0.15
DENSITY_KG_PER_M2 = 1.0
FRICTION = 1.0
RESTITUTION = 0.0

CHAIN_START_X_M = 0.75
CHAIN_SPACING_M = 0.5
CHAIN_Y_M = 1.2
JOINT_ANCHOR_OFFSET_M = 0.25  # a anchor at (+offset, 0), b anchor at (-offset, 0)
MOTOR_SPEED = 1.0
MOTOR_POWER = 1.0

GRID_START_X_M = 0.8
GRID_START_Y_M = 2.2
GRID_SPACING_M = 0.7
GRID_COLUMNS = 6
GRID_ROTATION_STEP_RAD = 0.1

JITTER_X_M = 0.05  # uniform in [-JITTER_X_M, JITTER_X_M], one draw per dynamic body

THRUSTER_ROTATION_RAD = np.pi / 2  # pointing up
THRUSTER_POWER = 1.0


def static_params(size: str) -> StaticSimParams:
    """Jax2D static parameters for a Kinetix size."""
    polygons, circles, joints, thrusters = SIZES[size]
    return StaticSimParams(
        num_polygons=polygons,
        num_circles=circles,
        num_joints=joints,
        num_thrusters=thrusters,
        num_static_fixated_polys=NUM_STATIC_POLYS,
    )


def _body_poses(size: str, seed: int) -> np.ndarray:
    """(x, y, rotation) of each dynamic body in D order: chain first, then grid, x jittered."""
    n_polys, n_circles, n_joints, _ = SIZES[size]
    n_bodies = n_polys - NUM_STATIC_POLYS + n_circles
    jitter = np.random.default_rng(seed).uniform(-JITTER_X_M, JITTER_X_M, size=n_bodies)
    poses = np.zeros((n_bodies, 3), dtype=np.float32)
    for i in range(n_bodies):
        if i <= n_joints:
            poses[i] = (CHAIN_START_X_M + CHAIN_SPACING_M * i, CHAIN_Y_M, 0.0)
        else:
            m = i - (n_joints + 1)
            poses[i] = (
                GRID_START_X_M + (m % GRID_COLUMNS) * GRID_SPACING_M,
                GRID_START_Y_M + (m // GRID_COLUMNS) * GRID_SPACING_M,
                GRID_ROTATION_STEP_RAD * m,
            )
    poses[:, 0] += jitter
    return poses


@partial(jax.jit, static_argnums=0)
def _build_state(size: str, poses: jax.Array) -> SimState:
    """Scene for `size` with dynamic bodies at `poses` (one jitted trace instead of many add calls)."""
    n_polys, _, n_joints, n_thrusters = SIZES[size]
    static = static_params(size)
    n_boxes = n_polys - NUM_STATIC_POLYS
    state = create_empty_sim(static, add_floor=True, add_walls_and_ceiling=True)

    global_idx = []  # global shape index of each body of D
    for i, (x, y, rot) in enumerate(poses):
        common = dict(rotation=rot, density=DENSITY_KG_PER_M2, friction=FRICTION, restitution=RESTITUTION)
        if i < n_boxes:
            state, (_, g) = scene.add_rectangle_to_scene(
                state, static, jnp.stack([x, y]), jnp.array(BOX_SIZE_M), **common
            )
        else:
            state, (_, g) = scene.add_circle_to_scene(state, static, jnp.stack([x, y]), CIRCLE_RADIUS_M, **common)
        global_idx.append(g)

    for j in range(n_joints):
        state, _ = scene.add_revolute_joint_to_scene(
            state,
            static,
            global_idx[j],
            global_idx[j + 1],
            jnp.array([JOINT_ANCHOR_OFFSET_M, 0.0]),
            jnp.array([-JOINT_ANCHOR_OFFSET_M, 0.0]),
            motor_on=True,
            motor_speed=MOTOR_SPEED,
            motor_power=MOTOR_POWER,
        )

    for t in range(n_thrusters):
        state, _ = scene.add_thruster_to_scene(
            state, global_idx[t], jnp.zeros(2), THRUSTER_ROTATION_RAD, THRUSTER_POWER
        )
    return state


def _assert_full(state: SimState, size: str) -> None:
    """Fail unless every (possibly batched) scene has exactly the size's active counts."""
    for name, parts, expected in zip(
        ("polygons", "circles", "joints", "thrusters"),
        (state.polygon, state.circle, state.joint, state.thruster),
        SIZES[size],
        strict=True,
    ):
        counts = np.asarray(parts.active.sum(axis=-1))
        assert (counts == expected).all(), f"scene {size}: active {name} {counts} != {expected}"


def build_scene(size: str, seed: int) -> tuple[SimState, StaticSimParams]:
    """Build the fully populated benchmark scene for `size`; `seed` sets the x jitter."""
    state = _build_state(size, jnp.asarray(_body_poses(size, seed)))
    _assert_full(state, size)
    return state, static_params(size)


def build_batch(size: str, batch: int) -> tuple[SimState, StaticSimParams]:
    """Scenes for seeds 0..batch-1 stacked along a leading batch axis (same as stacking build_scene)."""
    poses = jnp.asarray(np.stack([_body_poses(size, seed) for seed in range(batch)]))
    states = jax.vmap(partial(_build_state, size))(poses)
    _assert_full(states, size)
    return states, static_params(size)


def make_rollout(static: StaticSimParams, n_steps: int):
    """Function (states, params, actions) -> states after `n_steps` batched steps in one scan."""
    batched_step = jax.vmap(PhysicsEngine(static).step, in_axes=(0, None, None))

    def rollout(states, params, actions):
        def body(s, _):
            return batched_step(s, params, actions)[0], None

        return jax.lax.scan(body, states, None, length=n_steps)[0]

    return rollout


def compile_rollout(size: str, batch: int, n_steps: int):
    """(call, compile seconds): `call()` runs `n_steps` batched Jax2D steps of the compiled rollout."""
    states, static = build_batch(size, batch)
    params = SimParams()
    actions = jnp.ones(static.num_joints + static.num_thrusters)

    start = time.perf_counter()
    compiled = jax.jit(make_rollout(static, n_steps)).lower(states, params, actions).compile()
    compile_seconds = time.perf_counter() - start
    return (lambda: compiled(states, params, actions)), compile_seconds


def measure(size: str, batch: int, n_steps: int = 50, repeats: int = 3) -> dict:
    """Compile time and best-of-`repeats` throughput of `n_steps` batched Jax2D steps."""
    call, compile_seconds = compile_rollout(size, batch, n_steps)
    best_seconds = best_time(call, repeats)[0]

    return {
        "engine": "jax2d",
        "size": size,
        "batch": batch,
        "steps_per_second": batch * n_steps / best_seconds,
        "compile_seconds": compile_seconds,
        "seconds_per_batched_step": best_seconds / n_steps,
    }


def main() -> None:
    """Command-line entry point: one printed line per (size, batch)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", nargs="+", default=list(SIZES), choices=list(SIZES))
    parser.add_argument("--batches", nargs="+", type=int, default=[1, 256])
    parser.add_argument("--steps", type=int, default=50, help="physics steps per timed run")
    parser.add_argument("--repeats", type=int, default=3, help="timed runs; the best is kept")
    args = parser.parse_args()
    for size in args.sizes:
        for batch in args.batches:
            r = measure(size, batch, args.steps, args.repeats)
            print(
                f"{r['engine']} size={r['size']} batch={r['batch']} "
                f"steps/s={r['steps_per_second']:.0f} compile={r['compile_seconds']:.1f}s "
                f"step={r['seconds_per_batched_step'] * 1e3:.3f}ms",
                flush=True,
            )


if __name__ == "__main__":
    main()
