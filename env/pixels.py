"""Jittable pixel renderer of an episode state (pure JAX, per-pixel inside tests) and Kinetix's PIXELS observation.

Colours and drawing order follow Kinetix's `renderer_pixels`: white background; shapes in slot order (polygons then
circles) filled with their role colour (static shapes dark grey, or their role colour at half brightness), with a
black outline; circles carry a black radius marker along their body +y axis; then joints (a square, white unless a
revolute motor, which takes its binding's colour) and thrusters (a bar along the thrust direction, in its binding's
colour). Kinetix draws joints and thrusters with small textures at 500 px; here they are plain rectangles of
about the same size, and every size is in metres, so any resolution shows the same picture.

`render_image` returns a display image (row 0 at the top of the arena); the PIXELS observation keeps Kinetix's
layout, which indexes the image [x, y] with y growing upwards (Kinetix flips and transposes it only for display).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from flax import struct

from kforge.engine import ARENA_SIZE
from kforge.env.params import StaticEnvParams
from kforge.env.state import EnvState

PIXEL_OBSERVATION_RESOLUTION = 125
"""Side [px] of the PIXELS observation: Kinetix's 500 px screen downscaled by 4 (25 px/m)."""

GRAVITY_SCALE = 10.0
"""[m/s^2] the gravity feature of every observation is gravity_y / GRAVITY_SCALE."""

# RGB colours, 0-255
BACKGROUND_COLOUR = (255.0, 255.0, 255.0)
ROLE_COLOURS = ((160.0, 160.0, 160.0), (0.0, 204.0, 0.0), (0.0, 102.0, 204.0), (255.0, 102.0, 102.0))
"""Fill colour of a movable shape by `Role`: default grey, green, blue, red."""
STATIC_DEFAULT_COLOUR = (80.0, 80.0, 80.0)
"""Fill colour of a static shape with the DEFAULT role."""
STATIC_ROLE_BRIGHTNESS = 0.5
"""A static shape with a non-default role is drawn in its role colour times this factor."""
OUTLINE_COLOUR = (0.0, 0.0, 0.0)
ACTUATOR_COLOURS = (
    (255.0, 255.0, 255.0),
    (255.0, 255.0, 0.0),
    (255.0, 0.0, 255.0),
    (0.0, 255.0, 255.0),
    (255.0, 153.0, 51.0),
)
"""Index 0: joint without a motor (or fixed); index 1 + b: actuator bound to slot b."""

# Sizes [m] (1 px of the 125 px observation = 0.04 m)
POLYGON_OUTLINE_M = 0.04
CIRCLE_OUTLINE_M = 0.08
CIRCLE_MARKER_HALF_WIDTH_M = 0.04
JOINT_HALF_SIZE_M = 0.03
THRUSTER_HALF_LENGTH_M = 0.08
THRUSTER_HALF_WIDTH_M = 0.04


@struct.dataclass
class PixelObservation:
    """Kinetix's PIXELS observation."""

    image: jnp.ndarray  # (125, 125, 3) f32 in [0, 1], indexed [x, y]: axis 0 left to right, axis 1 bottom to top
    global_info: jnp.ndarray  # (1,) f32 gravity_y / GRAVITY_SCALE


def _pixel_centres(resolution: int) -> tuple[np.ndarray, np.ndarray]:
    """World x and y [m] of the pixel centres (resolution, resolution), row 0 at the top (y = ARENA_SIZE)."""
    centres = (np.arange(resolution) + 0.5) * (ARENA_SIZE / resolution)
    x = np.broadcast_to(centres[None, :], (resolution, resolution))
    y = np.broadcast_to(ARENA_SIZE - centres[:, None], (resolution, resolution))
    return x.astype(np.float32), y.astype(np.float32)


def fill_colours(state: EnvState) -> jnp.ndarray:
    """(N, 3) f32 fill colour (0-255) of every shape from its role and whether it is static."""
    roles = jnp.clip(state.task.roles, 0, len(ROLE_COLOURS) - 1)
    role_colour = jnp.asarray(ROLE_COLOURS)[roles]
    static_colour = jnp.where(
        (roles == 0)[:, None], jnp.asarray(STATIC_DEFAULT_COLOUR), role_colour * STATIC_ROLE_BRIGHTNESS
    )
    return jnp.where((state.sim.bodies.inverse_mass == 0.0)[:, None], static_colour, role_colour)


def _edge_planes(state: EnvState, static: StaticEnvParams) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray]:
    """Coefficients (P, 4) of each polygon edge's inward distance a*x + b*y + c [m] at world point (x, y).

    Unused edges (triangles) get a = b = 0, c = +inf, so they never bound the polygon.
    """
    p = static.sim.num_polygons
    bodies = state.sim.bodies
    cos, sin = jnp.cos(bodies.rotation[:p, None]), jnp.sin(bodies.rotation[:p, None])
    local, count = bodies.vertices[:p], bodies.n_vertices[:p, None]
    world_x = bodies.position[:p, 0, None] + cos * local[..., 0] - sin * local[..., 1]
    world_y = bodies.position[:p, 1, None] + sin * local[..., 0] + cos * local[..., 1]
    corner = jnp.arange(local.shape[1])[None, :]
    following = jnp.where(corner + 1 < count, corner + 1, 0)
    edge_x = jnp.take_along_axis(world_x, following, axis=1) - world_x
    edge_y = jnp.take_along_axis(world_y, following, axis=1) - world_y
    length = jnp.maximum(jnp.sqrt(edge_x**2 + edge_y**2), 1e-12)
    used = corner < count
    a = jnp.where(used, -edge_y / length, 0.0)
    b = jnp.where(used, edge_x / length, 0.0)
    c = jnp.where(used, (edge_y * world_x - edge_x * world_y) / length, jnp.inf)
    return a, b, c


def _polygon_coverage(planes, index: int, x, y) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Pixels inside polygon `index`, and those of them within the outline width of its boundary."""
    a, b, c = (coefficient[index] for coefficient in planes)
    depth = a[0] * x + b[0] * y + c[0]
    for edge in range(1, a.shape[0]):
        depth = jnp.minimum(depth, a[edge] * x + b[edge] * y + c[edge])
    inside = depth >= 0.0
    return inside, depth < POLYGON_OUTLINE_M


def _circle_coverage(state: EnvState, index: int, x, y) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Pixels inside circle `index`, and those on its outline or its radius marker."""
    bodies = state.sim.bodies
    dx, dy = x - bodies.position[index, 0], y - bodies.position[index, 1]
    radius = bodies.radius[index]
    squared = dx**2 + dy**2
    inside = squared <= radius**2
    inner = jnp.maximum(radius - CIRCLE_OUTLINE_M, 0.0)
    marker_x, marker_y = -jnp.sin(bodies.rotation[index]), jnp.cos(bodies.rotation[index])
    along = dx * marker_x + dy * marker_y
    across = jnp.abs(dx * marker_y - dy * marker_x)
    marker = (along >= 0.0) & (across < CIRCLE_MARKER_HALF_WIDTH_M)
    return inside, (squared > inner**2) | marker


def _world_point(state: EnvState, body, local) -> jnp.ndarray:
    """World position [m] of a point given in `body`'s frame relative to its centre of mass."""
    bodies = state.sim.bodies
    cos, sin = jnp.cos(bodies.rotation[body]), jnp.sin(bodies.rotation[body])
    offset = jnp.stack([cos * local[0] - sin * local[1], sin * local[0] + cos * local[1]])
    return bodies.position[body] + offset


def _shapes_layer(state: EnvState, static: StaticEnvParams, x, y) -> jnp.ndarray:
    """(H, W, 3) colours of the background and every active shape, later slots on top."""
    num_polygons, num_bodies = static.sim.num_polygons, static.sim.num_bodies
    active = state.sim.bodies.active
    # Per pixel: 2 * (index of the top shape) + (1 if on its outline), or 2 * num_bodies for the background.
    code = jnp.full(x.shape, 2 * num_bodies, jnp.int32)
    planes = _edge_planes(state, static)
    for index in range(num_bodies):
        if index < num_polygons:
            inside, outline = _polygon_coverage(planes, index, x, y)
        else:
            inside, outline = _circle_coverage(state, index, x, y)
        code = jnp.where(inside & active[index], 2 * index + outline.astype(jnp.int32), code)
    fills = jnp.concatenate([fill_colours(state), jnp.asarray([BACKGROUND_COLOUR])])
    outline = jnp.broadcast_to(jnp.asarray(OUTLINE_COLOUR), fills.shape)
    palette = jnp.stack([fills, outline], axis=1).reshape(-1, 3)
    return palette[code]


def _actuators_layer(state: EnvState, image: jnp.ndarray, x, y, half_pixel: float) -> jnp.ndarray:
    """`image` with every active joint and thruster drawn on top (each covers at least one display pixel)."""
    joints, thrusters, task = state.sim.joints, state.sim.thrusters, state.task
    colours = jnp.asarray(ACTUATOR_COLOURS)
    joint_half = max(JOINT_HALF_SIZE_M, half_pixel)
    for index in range(joints.active.shape[0]):
        centre = _world_point(state, joints.body_a[index], joints.anchor_a[index])
        covered = jnp.maximum(jnp.abs(x - centre[0]), jnp.abs(y - centre[1])) <= joint_half
        motorised = joints.motor_on[index] & ~joints.is_fixed[index]
        colour = colours[jnp.where(motorised, task.motor_bindings[index] + 1, 0)]
        image = jnp.where((covered & joints.active[index])[..., None], colour, image)
    for index in range(thrusters.active.shape[0]):
        body = thrusters.body[index]
        centre = _world_point(state, body, thrusters.anchor[index])
        direction = state.sim.bodies.rotation[body] + thrusters.angle[index]
        dx, dy = x - centre[0], y - centre[1]
        along = jnp.abs(dx * jnp.cos(direction) + dy * jnp.sin(direction))
        across = jnp.abs(-dx * jnp.sin(direction) + dy * jnp.cos(direction))
        covered = (along <= max(THRUSTER_HALF_LENGTH_M, half_pixel)) & (
            across <= max(THRUSTER_HALF_WIDTH_M, half_pixel)
        )
        colour = colours[task.thruster_bindings[index] + 1]
        image = jnp.where((covered & thrusters.active[index])[..., None], colour, image)
    return image


def render_image(
    state: EnvState, static: StaticEnvParams, resolution: int = PIXEL_OBSERVATION_RESOLUTION, supersample: int = 1
) -> jnp.ndarray:
    """(resolution, resolution, 3) f32 RGB in [0, 1] of the arena [0, 5] x [0, 5] m, row 0 at the top (y = 5 m).

    `resolution` and `supersample` are Python ints (static under jit); with `supersample` = k each pixel averages
    k x k samples (antialiasing). Pure, jit- and vmap-able.
    """
    if not (isinstance(resolution, int) and resolution > 0):
        raise ValueError(f"resolution must be a positive int, got {resolution!r}")
    if not (isinstance(supersample, int) and supersample > 0):
        raise ValueError(f"supersample must be a positive int, got {supersample!r}")
    x, y = _pixel_centres(resolution * supersample)
    image = _shapes_layer(state, static, x, y)
    image = _actuators_layer(state, image, x, y, half_pixel=ARENA_SIZE / (2 * resolution))
    if supersample > 1:
        image = image.reshape(resolution, supersample, resolution, supersample, 3).mean(axis=(1, 3))
    return jnp.clip(image / 255.0, 0.0, 1.0)  # averaging can round a hair past 1


def pixel_observation(state: EnvState, static: StaticEnvParams) -> PixelObservation:
    """Kinetix's PIXELS observation: the 125 px image in Kinetix's [x, y] layout and the gravity feature."""
    image = render_image(state, static, PIXEL_OBSERVATION_RESOLUTION)
    return PixelObservation(
        image=jnp.transpose(image[::-1], (1, 0, 2)),
        global_info=(state.sim.gravity[1:] / GRAVITY_SCALE).astype(jnp.float32),
    )
