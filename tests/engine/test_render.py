"""The renderer draws the scene where it is (y up, 100 px per metre) and the demo writes a readable GIF."""

from __future__ import annotations

import imageio.v3 as iio
import numpy as np

from kforge.engine import SceneBuilder, StaticSimParams, write_demo
from kforge.engine.render import BACKGROUND, STATIC_COLOUR, render_frame

PIXELS_PER_METRE = 100
ARENA_PIXELS = 500


def _pixel(image, x_m, y_m):
    """RGB at world point (x, y) [m]; image row 0 is the top of the arena (y = 5 m)."""
    return tuple(int(c) for c in image[int(ARENA_PIXELS - y_m * PIXELS_PER_METRE), int(x_m * PIXELS_PER_METRE)])


def test_render_frame_places_floor_box_and_background():
    static = StaticSimParams.for_size("s")
    builder = SceneBuilder(static)
    builder.add_box((1.0, 3.0), (0.6, 0.6))
    colours = np.zeros((static.num_bodies, 3), np.uint8)
    colours[4] = (10, 200, 30)
    image = render_frame(builder.build(), colours=colours, pixels_per_metre=PIXELS_PER_METRE)
    assert image.shape == (ARENA_PIXELS, ARENA_PIXELS, 3) and image.dtype == np.uint8
    assert _pixel(image, 2.5, 0.2) == STATIC_COLOUR  # floor top is at y = 0.4 m
    assert _pixel(image, 1.0, 3.0) == (10, 200, 30)  # box centre
    assert _pixel(image, 4.0, 3.0) == BACKGROUND
    assert _pixel(image, 1.0, 1.5) == BACKGROUND  # below the box: y points up


def test_demo_writes_a_gif(tmp_path):
    out = tmp_path / "demo.gif"
    path, summary = write_demo(str(out), 8)
    assert path == str(out) and summary.startswith("8 steps") and "positions finite: True" in summary
    frames = iio.imread(out, index=None)
    assert frames.shape[0] == 4 and frames.shape[1:3] == (ARENA_PIXELS, ARENA_PIXELS)
    assert frames.std() > 0  # not a blank image
