"""Fully populated benchmark scenes for our engine, laid out exactly like `jax2d_baseline.build_scene`."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from kforge.engine import SceneBuilder, SimState, StaticSimParams

BOX_SIZE_M = (0.4, 0.3)
CIRCLE_RADIUS_M = 0.15
CHAIN_START_X_M, CHAIN_SPACING_M, CHAIN_Y_M = 0.75, 0.5, 1.2
GRID_START_X_M, GRID_SPACING_X_M, GRID_START_Y_M, GRID_SPACING_Y_M, GRID_COLUMNS = 0.8, 0.7, 2.2, 0.7, 6
GRID_ROTATION_STEP_RAD = 0.1
JITTER_M = 0.05
THRUSTER_ANGLE_RAD = np.pi / 2
DISTINCT_SCENES = 16
"""Scenes with different jitter seeds, tiled to fill a batch (building thousands on the host is slow)."""


def build_scene(size: str, seed: int) -> tuple[SimState, StaticSimParams]:
    """Every slot of the size used: a motorised joint chain, free bodies above it, thrusters pointing up."""
    static = StaticSimParams.for_size(size)
    builder = SceneBuilder(static)
    jitter = np.random.default_rng(seed).uniform(-JITTER_M, JITTER_M, static.num_bodies)
    num_boxes = static.num_polygons - static.num_reserved_static
    kinds = ["box"] * num_boxes + ["circle"] * static.num_circles
    bodies, centres = [], []
    for i, kind in enumerate(kinds):
        if i <= static.num_joints:
            x, y, rotation = CHAIN_START_X_M + CHAIN_SPACING_M * i, CHAIN_Y_M, 0.0
        else:
            m = i - static.num_joints - 1
            x = GRID_START_X_M + (m % GRID_COLUMNS) * GRID_SPACING_X_M
            y = GRID_START_Y_M + (m // GRID_COLUMNS) * GRID_SPACING_Y_M
            rotation = GRID_ROTATION_STEP_RAD * m
        centre = np.array([x + jitter[i], y])
        if kind == "box":
            bodies.append(builder.add_box(centre, BOX_SIZE_M, rotation=rotation))
        else:
            bodies.append(builder.add_circle(centre, CIRCLE_RADIUS_M, rotation=rotation))
        centres.append(centre)
    for j in range(static.num_joints):
        anchor = (centres[j] + centres[j + 1]) / 2
        builder.add_revolute_joint(bodies[j], bodies[j + 1], anchor, motor_on=True, motor_speed=1.0, motor_power=1.0)
    for t in range(static.num_thrusters):
        builder.add_thruster(bodies[t], centres[t], THRUSTER_ANGLE_RAD)
    return builder.build(), static


def batched_scenes(size: str, batch: int) -> SimState:
    """`batch` scenes: the first `DISTINCT_SCENES` jitter seeds, repeated in order, tiled on the host (one
    concatenation of thousands of operands per field would compile for minutes at 65,536 scenes)."""
    scenes = [build_scene(size, seed)[0] for seed in range(min(batch, DISTINCT_SCENES))]
    stacked = jax.tree_util.tree_map(lambda *x: np.stack(x), *scenes)
    in_order = np.arange(batch) % len(scenes)
    return jax.tree_util.tree_map(lambda x: jnp.asarray(x[in_order]), stacked)
