"""Host-side rendering of a `SimState` to RGB images (numpy + Pillow) and GIF writing (imageio)."""

from __future__ import annotations

from pathlib import Path

import imageio.v3 as iio
import jax
import numpy as np
from PIL import Image, ImageDraw

from kforge.engine.geometry import rotate_host
from kforge.engine.scene import ARENA_SIZE
from kforge.engine.state import Bodies, SimState

DEFAULT_PIXELS_PER_METRE = 100
"""[px/m] image scale; the arena (ARENA_SIZE m square) becomes a 500 x 500 px image."""

# RGB colours
BACKGROUND = (250, 250, 247)
STATIC_COLOUR = (70, 70, 70)
OUTLINE_COLOUR = (40, 40, 40)
JOINT_COLOUR = (200, 30, 30)
THRUSTER_COLOUR = (230, 120, 0)
LIGHT_PALETTE = np.array(
    [(140, 190, 230), (245, 170, 140), (160, 215, 160), (230, 200, 120), (200, 170, 225), (240, 160, 190)], np.uint8
)
"""Default colours of movable bodies, cycled by body index."""

JOINT_RADIUS_M = 0.03
"""[m] radius of the dot drawn at a joint."""

THRUSTER_LENGTH_M = 0.15
"""[m] length of a thruster triangle, from its base at the anchor to its tip along the thrust direction."""

THRUSTER_HALF_WIDTH_M = 0.06
"""[m] half width of a thruster triangle's base."""


def _to_pixels(points: np.ndarray, pixels_per_metre: float) -> list[tuple[float, float]]:
    """World points (n, 2) [m], y up, to image (column, row) pixel tuples, row 0 at the top (y = ARENA_SIZE)."""
    return [_to_pixel(point, pixels_per_metre) for point in points]


def _to_pixel(point: np.ndarray, pixels_per_metre: float) -> tuple[float, float]:
    """One world point (2,) [m] to an image (column, row) pixel position."""
    return (float(point[0]) * pixels_per_metre, (ARENA_SIZE - float(point[1])) * pixels_per_metre)


def body_colours(num_bodies: int) -> np.ndarray:
    """(N, 3) uint8 default colours: `LIGHT_PALETTE` cycled by body index."""
    return LIGHT_PALETTE[np.arange(num_bodies) % len(LIGHT_PALETTE)]


def render_frame(state: SimState, *, colours=None, pixels_per_metre: float = DEFAULT_PIXELS_PER_METRE) -> np.ndarray:
    """RGB image (H, W, 3) uint8 of one unbatched state; the arena [0, 5] x [0, 5] m, y up.

    `colours` (N, 3) uint8-compatible colours of movable bodies (default `body_colours`); static bodies are drawn
    `STATIC_COLOUR`. Circles carry a radius line at their rotation; joints are dots, thrusters triangles pointing
    along their thrust direction. Inactive slots are skipped.
    """
    state = jax.tree.map(np.asarray, state)
    num_bodies = len(state.bodies.active)
    fills = body_colours(num_bodies) if colours is None else np.asarray(colours, np.uint8).reshape(num_bodies, 3)
    size = round(ARENA_SIZE * pixels_per_metre)
    image = Image.new("RGB", (size, size), BACKGROUND)
    draw = ImageDraw.Draw(image)
    _draw_bodies(draw, state.bodies, fills, pixels_per_metre)
    _draw_joints(draw, state, pixels_per_metre)
    _draw_thrusters(draw, state, pixels_per_metre)
    return np.asarray(image)


def _world(bodies: Bodies, body, local: np.ndarray) -> np.ndarray:
    """World position [m] of a point given in `body`'s frame relative to its centre of mass."""
    return bodies.position[body] + rotate_host(bodies.rotation[body], local)


def _disc(draw: ImageDraw.ImageDraw, centre: tuple[float, float], radius_px: float, **style) -> None:
    x, y = centre
    draw.ellipse([x - radius_px, y - radius_px, x + radius_px, y + radius_px], **style)


def _draw_bodies(draw: ImageDraw.ImageDraw, bodies: Bodies, fills: np.ndarray, pixels_per_metre: float) -> None:
    """Active bodies, static ones first so that movable bodies are drawn on top."""
    is_static = bodies.inverse_mass == 0.0
    for index in sorted(np.flatnonzero(bodies.active), key=lambda i: not is_static[i]):
        fill = STATIC_COLOUR if is_static[index] else tuple(int(c) for c in fills[index])
        n_vertices = int(bodies.n_vertices[index])
        if n_vertices > 0:
            corners = _world(bodies, index, bodies.vertices[index, :n_vertices])
            draw.polygon(_to_pixels(corners, pixels_per_metre), fill=fill, outline=OUTLINE_COLOUR)
        else:
            radius = float(bodies.radius[index])
            centre = _to_pixel(bodies.position[index], pixels_per_metre)
            _disc(draw, centre, radius * pixels_per_metre, fill=fill, outline=OUTLINE_COLOUR)
            rim = _to_pixel(_world(bodies, index, np.array([radius, 0.0])), pixels_per_metre)
            draw.line([centre, rim], fill=OUTLINE_COLOUR, width=2)


def _draw_joints(draw: ImageDraw.ImageDraw, state: SimState, pixels_per_metre: float) -> None:
    """A dot at each active joint's anchor (as seen from body a)."""
    joints = state.joints
    for index in np.flatnonzero(joints.active):
        anchor = _world(state.bodies, joints.body_a[index], joints.anchor_a[index])
        _disc(draw, _to_pixel(anchor, pixels_per_metre), JOINT_RADIUS_M * pixels_per_metre, fill=JOINT_COLOUR)


def _draw_thrusters(draw: ImageDraw.ImageDraw, state: SimState, pixels_per_metre: float) -> None:
    """A triangle at each active thruster's anchor, its tip along the thrust direction."""
    thrusters, bodies = state.thrusters, state.bodies
    for index in np.flatnonzero(thrusters.active):
        body = thrusters.body[index]
        direction = rotate_host(bodies.rotation[body] + thrusters.angle[index], np.array([1.0, 0.0]))
        side = THRUSTER_HALF_WIDTH_M * np.array([-direction[1], direction[0]])
        base = _world(bodies, body, thrusters.anchor[index])
        triangle = np.stack([base + THRUSTER_LENGTH_M * direction, base + side, base - side])
        draw.polygon(_to_pixels(triangle, pixels_per_metre), fill=THRUSTER_COLOUR, outline=OUTLINE_COLOUR)


def write_gif(frames, path, fps: float) -> Path:
    """Write RGB frames (T, H, W, 3) uint8 as a looping GIF at `fps` frames per second; returns the path.

    GIF stores frame durations in 1/100 s, so the played rate is rounded (30 fps plays at about 33 fps).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(path, np.asarray(frames, np.uint8), duration=1000.0 / fps, loop=0)
    return path
