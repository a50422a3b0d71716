"""Pixel renderer: role colours at known places, orientation, Kinetix's observation layout, batching, GIF export."""

import imageio.v3 as iio
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from kforge.engine import SceneBuilder
from kforge.env import Role, StaticEnvParams, reset
from kforge.env.gif import write_state_gif
from kforge.env.observations import ObservationType, observe
from kforge.env.pixels import render_image
from kforge.env.state import EnvState, Level, Task

STATIC = StaticEnvParams.for_size("s")
RESOLUTION = 125
METRES_PER_PIXEL = 5.0 / RESOLUTION  # 0.04 m

WHITE = (1.0, 1.0, 1.0)
GREEN = (0.0, 204 / 255, 0.0)
BLUE = (0.0, 102 / 255, 204 / 255)
RED = (1.0, 102 / 255, 102 / 255)
GREY = (160 / 255, 160 / 255, 160 / 255)
STATIC_GREY = (80 / 255, 80 / 255, 80 / 255)
YELLOW = (1.0, 1.0, 0.0)
CYAN = (0.0, 1.0, 1.0)

render = jax.jit(render_image, static_argnums=(1, 2, 3))


def pixel_of(x: float, y: float, resolution: int = RESOLUTION) -> tuple[int, int]:
    """(row, column) of the display pixel containing world point (x, y); row 0 is the top (y = 5 m)."""
    size = 5.0 / resolution
    return int((5.0 - y) / size), int(x / size)


def make_state(builder: SceneBuilder, roles: dict, motor_binding: int = 0, thruster_binding: int = 0) -> EnvState:
    n = STATIC.num_bodies
    role_array = np.zeros(n, np.int32)
    for body, role in roles.items():
        role_array[body] = role
    task = Task(
        roles=jnp.asarray(role_array),
        densities=jnp.asarray(builder.densities, jnp.float32),
        motor_bindings=jnp.full((1,), motor_binding, jnp.int32),
        thruster_bindings=jnp.full((1,), thruster_binding, jnp.int32),
        motor_auto=jnp.zeros((1,), bool),
    )
    return reset(Level(builder.build(), task))


def disc_state(position, radius=0.5, role=Role.GREEN, static=False) -> EnvState:
    builder = SceneBuilder(STATIC.sim)
    disc = builder.add_circle(position, radius, static=static)
    return make_state(builder, {disc: role})


def test_circle_has_its_role_colour_inside_and_background_outside():
    image = np.asarray(render(disc_state((2.5, 2.5)), STATIC, RESOLUTION, 1))
    assert image.shape == (RESOLUTION, RESOLUTION, 3) and image.dtype == np.float32
    below_centre = pixel_of(2.5, 2.5 - 0.15)  # the black radius marker points up (body +y) from the centre
    np.testing.assert_allclose(image[below_centre], GREEN, atol=1e-6)
    np.testing.assert_allclose(image[pixel_of(2.5, 2.5 + 0.2)], (0, 0, 0))  # on the radius marker
    np.testing.assert_allclose(image[pixel_of(2.5 + 0.7, 2.5)], WHITE)
    np.testing.assert_allclose(image[pixel_of(2.5, 2.5 + 0.7)], WHITE)
    np.testing.assert_allclose(image[pixel_of(2.5, 0.2)], STATIC_GREY, atol=1e-6)  # the floor


@pytest.mark.parametrize(
    ("role", "static", "colour"),
    [
        (Role.DEFAULT, False, GREY),
        (Role.BLUE, False, BLUE),
        (Role.RED, False, RED),
        (Role.DEFAULT, True, STATIC_GREY),
        (Role.RED, True, tuple(0.5 * c for c in RED)),
    ],
)
def test_fill_colour_by_role_and_static(role, static, colour):
    image = np.asarray(render(disc_state((2.5, 2.5), role=role, static=static), STATIC, RESOLUTION, 1))
    np.testing.assert_allclose(image[pixel_of(2.5, 2.35)], colour, atol=1e-6)


def green_pixels(image: np.ndarray) -> np.ndarray:
    return np.argwhere(np.all(np.abs(image - np.asarray(GREEN)) < 1e-6, axis=-1))


def test_high_objects_are_in_the_top_rows_and_left_objects_in_the_left_columns():
    high_left = green_pixels(np.asarray(render(disc_state((1.0, 4.0), radius=0.3), STATIC, RESOLUTION, 1)))
    low_right = green_pixels(np.asarray(render(disc_state((4.0, 1.0), radius=0.3), STATIC, RESOLUTION, 1)))
    assert len(high_left) > 0 and len(low_right) > 0
    assert high_left[:, 0].max() < RESOLUTION // 2 < low_right[:, 0].min()
    assert high_left[:, 1].max() < RESOLUTION // 2 < low_right[:, 1].min()


def test_pixel_observation_uses_kinetix_x_y_layout():
    obs = observe(disc_state((1.0, 4.0), radius=0.3), STATIC, ObservationType.PIXELS)
    image = np.asarray(obs.image)
    greens = green_pixels(image)  # obs.image[i, j]: i grows with world x, j with world y
    assert greens[:, 0].max() < RESOLUTION // 2 < greens[:, 1].min()
    centre_x, centre_y = int(1.0 / METRES_PER_PIXEL), int(4.0 / METRES_PER_PIXEL)
    np.testing.assert_allclose(image[centre_x, centre_y - 3], GREEN, atol=1e-6)
    np.testing.assert_allclose(np.asarray(obs.global_info), [-0.981], rtol=1e-6)


def test_rotated_box_covers_its_diamond_not_its_unrotated_square():
    builder = SceneBuilder(STATIC.sim)
    box = builder.add_box((2.5, 2.5), (1.0, 1.0), rotation=np.pi / 4)
    image = np.asarray(render(make_state(builder, {box: Role.BLUE}), STATIC, RESOLUTION, 1))
    np.testing.assert_allclose(image[pixel_of(2.5, 2.5)], BLUE, atol=1e-6)
    np.testing.assert_allclose(image[pixel_of(2.5 + 0.6, 2.5)], BLUE, atol=1e-6)  # inside the diamond's right tip
    np.testing.assert_allclose(image[pixel_of(2.5 + 0.45, 2.5 + 0.45)], WHITE)  # a corner of the unrotated square


def test_joint_and_thruster_take_their_binding_colours():
    builder = SceneBuilder(STATIC.sim)
    body = builder.add_box((2.0, 2.5), (1.2, 0.6))
    wheel = builder.add_circle((1.6, 2.5), 0.2)
    builder.add_revolute_joint(body, wheel, (1.6, 2.5), motor_on=True, motor_speed=1.0, motor_power=1.0)
    builder.add_thruster(body, (2.4, 2.5), 0.0)
    state = make_state(builder, {}, motor_binding=2, thruster_binding=0)
    image = np.asarray(render(state, STATIC, RESOLUTION, 1))
    np.testing.assert_allclose(image[pixel_of(1.6, 2.5)], CYAN)  # motor binding 2
    np.testing.assert_allclose(image[pixel_of(2.4, 2.5)], YELLOW)  # thruster binding 0
    np.testing.assert_allclose(image[pixel_of(2.0, 2.5)], GREY, atol=1e-6)


def test_inactive_shapes_are_not_drawn():
    state = disc_state((2.5, 2.5))
    bodies = state.sim.bodies
    hidden = state.replace(
        sim=state.sim.replace(bodies=bodies.replace(active=bodies.active.at[STATIC.sim.num_polygons].set(False)))
    )
    image = np.asarray(render(hidden, STATIC, RESOLUTION, 1))
    np.testing.assert_allclose(image[pixel_of(2.5, 2.35)], WHITE)


def test_values_in_unit_range_at_any_resolution_and_supersampling():
    builder = SceneBuilder(STATIC.sim)
    body = builder.add_box((2.0, 2.0), (1.0, 0.5), rotation=0.4)
    wheel = builder.add_circle((1.6, 1.8), 0.3)
    builder.add_revolute_joint(body, wheel, (1.6, 1.8), motor_on=True)
    builder.add_thruster(body, (2.3, 2.1), 1.0)
    state = make_state(builder, {body: Role.GREEN, wheel: Role.RED})
    for resolution, supersample in ((RESOLUTION, 1), (100, 3)):
        image = np.asarray(render(state, STATIC, resolution, supersample))
        assert image.shape == (resolution, resolution, 3)
        assert image.min() >= 0.0 and image.max() <= 1.0
    sharp, smooth = (np.asarray(render(state, STATIC, 100, supersample)) for supersample in (1, 3))
    assert len(np.unique(smooth.reshape(-1, 3), axis=0)) > len(np.unique(sharp.reshape(-1, 3), axis=0))
    np.testing.assert_allclose(smooth[pixel_of(2.0, 2.0, 100)], GREEN, atol=1e-6)


def test_bad_resolution_is_rejected():
    with pytest.raises(ValueError, match="resolution"):
        render_image(disc_state((2.5, 2.5)), STATIC, 0)
    with pytest.raises(ValueError, match="supersample"):
        render_image(disc_state((2.5, 2.5)), STATIC, 10, 1.5)


def stacked_states(xs) -> EnvState:
    return jax.tree.map(lambda *leaves: np.stack(leaves), *[disc_state((x, 2.5), radius=0.3) for x in xs])


def test_gif_has_one_frame_per_state(tmp_path):
    xs = (1.0, 2.0, 3.0, 4.0)
    path = write_state_gif(stacked_states(xs), STATIC, tmp_path / "episode.gif", fps=10, resolution=50)
    frames = iio.imread(path, index=None)
    assert frames.shape[:3] == (len(xs), 50, 50)
    for frame, x in zip(frames, xs, strict=True):
        row, column = pixel_of(x, 2.35, 50)
        np.testing.assert_allclose(frame[row, column, :3], (0, 204, 0), atol=2)


def test_gif_rejects_an_unstacked_state(tmp_path):
    with pytest.raises(ValueError, match="stacked over time"):
        write_state_gif(disc_state((2.5, 2.5)), STATIC, tmp_path / "x.gif")
