"""Random levels from Kinetix's level distribution (`sample_kinetix_level`): key -> `Level`, pure and vmappable.

Recipe (docs/kinetix.md, random level distribution): floor role; green and blue shapes (one of them never
fixated); forced control (thruster, motor or both; without a motor a free shape is added instead); the remaining
shape slots each get a connected shape, a free shape or nothing; extra thrusters; a green/blue swap; a permutation
of the slots.
Every shape is the best of several proposals: the one overlapping the fewest existing shapes.
"""

from __future__ import annotations

import enum
import functools

import jax
import jax.numpy as jnp
import numpy as np

from kforge.engine import KINETIX_SIZES, SceneBuilder, joint_collision_matrix
from kforge.env.params import StaticEnvParams
from kforge.env.sampler_shapes import (
    HIDDEN_PENALTY,
    NUM_DRAWS,
    NUM_JOINT_DRAWS,
    NUM_THRUSTER_DRAWS,
    add_thruster,
    categorical,
    free_slots,
    joint_settings,
    overlap_count,
    place_joint,
    place_shape,
    propose_connected_shape,
    propose_free_shape,
)
from kforge.env.state import Level, Role, empty_task

FLOOR_ROLE_WEIGHTS = (0.90, 0.00, 0.02, 0.08)
"""[-] probability of each `Role` for the floor (default, green, blue, red)."""

NUM_PROPOSALS = 8
"""Candidates drawn per added shape; the one with the fewest overlaps is kept."""

NUM_PROPOSALS_SMALL = 1
"""Candidates per shape for size s (as Kinetix, which works around an XLA bug there)."""

FIRST_SHAPE_NO_FIXATE_CHANCE = 0.5
"""[-] probability that the first goal shape (rather than the second) is the one that may not be fixated."""

FORCED_CONTROLS = ((True, False), (False, True), (True, True))
"""(thruster, motor) of the three equally likely forced-control choices."""

ADD_SHAPE_WEIGHTS = (0.35, 0.35, 0.30)
"""[-] probability of a connected shape, a free shape, or nothing, for each remaining shape slot."""

EXTRA_THRUSTER_CHANCE = 0.3
"""[-] probability of each of the num_thrusters - 1 extra thruster tries."""

SWAP_GOALS_CHANCE = 0.5
"""[-] probability of swapping green and blue (only with a default-role floor)."""

FORCED_CONTROL_STEP = 2
"""Index of the shape step that carries the forced motor (or its replacement free shape) and the forced thruster."""


class AddKind(enum.IntEnum):
    """What one shape step adds."""

    CONNECTED = 0
    FREE = 1
    NOTHING = 2


def _is_small(static: StaticEnvParams) -> bool:
    sim = static.sim
    return (sim.num_polygons, sim.num_circles, sim.num_joints, sim.num_thrusters) == KINETIX_SIZES["s"]


def _check_static(static: StaticEnvParams):
    sim = static.sim
    free_shape_slots = static.num_bodies - sim.num_reserved_static
    if free_shape_slots < FORCED_CONTROL_STEP + 1 or sim.num_joints < 1 or sim.num_thrusters < 1:
        raise ValueError(
            f"the level sampler needs >= {FORCED_CONTROL_STEP + 1} free shape slots, >= 1 joint and >= 1 thruster; "
            f"got {free_shape_slots} free shape slots, {sim.num_joints} joints, {sim.num_thrusters} thrusters"
        )


@functools.cache
def _boundary_level(static: StaticEnvParams) -> Level:
    """Host-side constant: the empty arena (floor, walls, ceiling in polygon slots 0-3), every other slot free."""
    with jax.ensure_compile_time_eval():  # may first be called while tracing
        builder = SceneBuilder(static.sim)
        sim = jax.tree.map(np.asarray, builder.build())
        task = empty_task(static.num_bodies, static.sim.num_joints, static.sim.num_thrusters)
        task = task.replace(densities=builder.densities.astype(np.float32))
        return Level(sim=sim, task=jax.tree.map(np.asarray, task))


def _shape_plan(u, static: StaticEnvParams):
    """Per shape step: (kind, force_revolute, no_fixate, add_thruster) arrays of length num_bodies - reserved.

    `u`: `_plan_draws(static)` uniform draws in [0, 1).
    """
    steps = static.num_bodies - static.sim.num_reserved_static
    first_no_fixate = u[0] < FIRST_SHAPE_NO_FIXATE_CHANCE
    force_thruster, force_motor = jnp.asarray(FORCED_CONTROLS)[categorical(u[1], jnp.ones(len(FORCED_CONTROLS)))]
    remaining = jax.vmap(categorical, in_axes=(0, None))(u[3:], jnp.asarray(ADD_SHAPE_WEIGHTS))
    index = jnp.arange(steps)
    kind = jnp.where(index < FORCED_CONTROL_STEP, AddKind.FREE, remaining)
    kind = jnp.where(index == FORCED_CONTROL_STEP, jnp.where(force_motor, AddKind.CONNECTED, AddKind.FREE), kind)
    no_fixate = jnp.where(index == 0, first_no_fixate, (index == 1) & ~first_no_fixate) | _is_small(static)
    force_revolute = index == FORCED_CONTROL_STEP
    add_thruster_now = (index == FORCED_CONTROL_STEP) & force_thruster
    return kind.astype(jnp.int32), force_revolute, no_fixate, add_thruster_now


def _best(proposals, scores):
    return jax.tree.map(lambda x: x[jnp.argmin(scores)], proposals)


def _step_draws(num_proposals: int) -> int:
    """Uniform draws of one shape step: every proposal's shape draws, then the joint's and the thruster's."""
    return num_proposals * NUM_DRAWS + NUM_JOINT_DRAWS + NUM_THRUSTER_DRAWS


def _add_shape_step(level: Level, step, static: StaticEnvParams, num_proposals: int) -> Level:
    """Add the best of `num_proposals` connected or free shapes (per the step's plan), then maybe a thruster."""
    u, kind, force_revolute, no_fixate, add_thruster_now = step
    draws = u[: num_proposals * NUM_DRAWS].reshape(num_proposals, NUM_DRAWS)
    details = u[num_proposals * NUM_DRAWS :]
    free = jax.vmap(propose_free_shape, in_axes=(0, None, None, None))(draws, level, static, no_fixate)
    connected, attachments, hidden = jax.vmap(propose_connected_shape, in_axes=(0, None, None))(draws, level, static)
    score = jax.vmap(overlap_count, in_axes=(0, None, None))
    free = _best(free, score(free, level, static))
    connected_score = score(connected, level, static) + HIDDEN_PENALTY * hidden
    connected, attachment = _best((connected, attachments), connected_score)

    polygon_slot, circle_slot, space_polygon, space_circle = free_slots(level, static)
    shapes_present = jnp.any(level.sim.bodies.active[static.sim.num_reserved_static :])
    joint_free = ~jnp.all(level.sim.joints.active)
    is_connected = kind == AddKind.CONNECTED
    possible = (space_polygon | space_circle) & jnp.where(is_connected, shapes_present & joint_free, True)
    possible = possible & (kind != AddKind.NOTHING)
    shape = jax.tree.map(lambda c, f: jnp.where(is_connected, c, f), connected, free)
    # Out-of-range slots write nothing.
    body_slot = jnp.where(possible, jnp.where(shape.is_polygon, polygon_slot, circle_slot), static.num_bodies)
    joint_slot = jnp.where(possible & is_connected, jnp.argmin(level.sim.joints.active), static.sim.num_joints)
    level = place_shape(level, shape, body_slot)
    settings = joint_settings(details[:NUM_JOINT_DRAWS], level, attachment, force_revolute)
    level = place_joint(level, attachment, settings, joint_slot)
    return add_thruster(details[NUM_JOINT_DRAWS:], level, static, add_thruster_now), None


def _swap_goals(u, level: Level) -> Level:
    roles = level.task.roles
    swap = (u < SWAP_GOALS_CHANCE) & (roles[0] == Role.DEFAULT)
    swapped = jnp.where(roles == Role.GREEN, Role.BLUE, jnp.where(roles == Role.BLUE, Role.GREEN, roles))
    return level.replace(task=level.task.replace(roles=jnp.where(swap, swapped, roles).astype(jnp.int32)))


def _shuffled_groups(static: StaticEnvParams) -> tuple[int, ...]:
    """Sizes of the slot groups `_permute_slots` shuffles: movable polygons, circles, joints, thrusters."""
    sim = static.sim
    return (sim.num_polygons - sim.num_reserved_static, sim.num_circles, sim.num_joints, sim.num_thrusters)


def _permute_slots(u, level: Level, static: StaticEnvParams) -> Level:
    """Shuffle movable polygon slots, circle slots, joints and thrusters, keeping every reference consistent.

    `u`: one uniform draw per shuffled slot. The four shuffles are one sort of (group, draw): each group's slots end
    up in a uniformly random order (up to ties between draws).
    """
    p, reserved = static.sim.num_polygons, static.sim.num_reserved_static
    sizes = _shuffled_groups(static)
    group = np.repeat(np.arange(len(sizes), dtype=np.int32), sizes)
    _, _, shuffled = jax.lax.sort((jnp.asarray(group), u, jnp.arange(group.size, dtype=jnp.int32)), num_keys=2)
    start = np.cumsum((0,) + sizes)
    polygon_shuffle, circle_shuffle, joint_order, thruster_order = (
        shuffled[start[k] : start[k + 1]] - start[k] for k in range(len(sizes))
    )
    polygon_order = jnp.concatenate([jnp.arange(reserved), reserved + polygon_shuffle])
    body_order = jnp.concatenate([polygon_order, p + circle_shuffle])
    new_index = jnp.argsort(body_order)  # new_index[old slot] = new slot

    sim, task = level.sim, level.task
    bodies = jax.tree.map(lambda x: x[body_order], sim.bodies)
    joints = jax.tree.map(lambda x: x[joint_order], sim.joints)
    joints = joints.replace(body_a=new_index[joints.body_a], body_b=new_index[joints.body_b])
    thrusters = jax.tree.map(lambda x: x[thruster_order], sim.thrusters)
    thrusters = thrusters.replace(body=new_index[thrusters.body])
    task = task.replace(
        roles=task.roles[body_order],
        densities=task.densities[body_order],
        motor_bindings=task.motor_bindings[joint_order],
        motor_auto=task.motor_auto[joint_order],
        thruster_bindings=task.thruster_bindings[thruster_order],
    )
    sim = sim.replace(
        bodies=bodies,
        joints=joints,
        thrusters=thrusters,
        collision_matrix=joint_collision_matrix(joints, static.num_bodies),
    )
    return Level(sim=sim, task=task)


def sample_level(key: jax.Array, static: StaticEnvParams) -> Level:
    """One random level of Kinetix's distribution for `static`'s size; the same key always gives the same level.

    Every random number of the level comes from one draw of uniforms (each call of a JAX random function compiles
    to its own loop), split in order among the floor, the plan, the shape steps, the extra thrusters, the goal swap
    and the slot shuffle.
    """
    _check_static(static)
    num_proposals = NUM_PROPOSALS_SMALL if _is_small(static) else NUM_PROPOSALS
    steps = static.num_bodies - static.sim.num_reserved_static
    extra_thrusters = static.sim.num_thrusters - 1
    sizes = (
        1,
        3 + steps,
        steps * _step_draws(num_proposals),
        extra_thrusters * (1 + NUM_THRUSTER_DRAWS),
        1,
        sum(_shuffled_groups(static)),
    )
    u = jax.random.uniform(key, (sum(sizes),))
    floor_u, plan_u, step_u, extra_u, swap_u, permute_u = (
        u[start : start + size] for start, size in zip(np.cumsum((0,) + sizes[:-1]), sizes, strict=True)
    )
    level = jax.tree.map(jnp.asarray, _boundary_level(static))
    floor_role = categorical(floor_u[0], jnp.asarray(FLOOR_ROLE_WEIGHTS))
    level = level.replace(task=level.task.replace(roles=level.task.roles.at[0].set(floor_role)))

    plan = _shape_plan(plan_u, static)
    level, _ = jax.lax.scan(
        functools.partial(_add_shape_step, static=static, num_proposals=num_proposals),
        level,
        (step_u.reshape(steps, -1),) + plan,
    )

    for draws in extra_u.reshape(extra_thrusters, 1 + NUM_THRUSTER_DRAWS):
        level = add_thruster(draws[1:], level, static, draws[0] < EXTRA_THRUSTER_CHANCE)

    level = _swap_goals(swap_u[0], level)
    return _permute_slots(permute_u, level, static)


@functools.partial(jax.jit, static_argnames="static")
def sample_levels(keys: jax.Array, static: StaticEnvParams) -> Level:
    """`sample_level` over a batch of keys (B, ...) -> levels with a leading batch axis."""
    return jax.vmap(sample_level, in_axes=(0, None))(keys, static)
