"""GIF export of a sequence of episode states, drawn with the jittable pixel renderer."""

from __future__ import annotations

import functools
from pathlib import Path

import jax
import numpy as np

from kforge.engine import write_gif
from kforge.env.params import StaticEnvParams
from kforge.env.pixels import render_image
from kforge.env.state import EnvState

GIF_RESOLUTION = 500
"""Default GIF side [px]: Kinetix's full screen, 100 px/m."""

GIF_FPS = 30.0
"""Default GIF frame rate [frames/s]: one frame per env step of 2/60 s plays at about real time."""

FRAMES_PER_RENDER_CALL = 32
"""Frames rendered per compiled call (bounds device memory for long sequences)."""


@functools.partial(jax.jit, static_argnames=("static", "resolution", "supersample"))
def _render_frames(states: EnvState, static: StaticEnvParams, resolution: int, supersample: int) -> jax.Array:
    images = jax.vmap(lambda state: render_image(state, static, resolution, supersample))(states)
    return (images * 255.0 + 0.5).astype(np.uint8)


def write_state_gif(
    states: EnvState,
    static: StaticEnvParams,
    path,
    fps: float = GIF_FPS,
    resolution: int = GIF_RESOLUTION,
    supersample: int = 1,
) -> Path:
    """Write one GIF frame per state of `states` (an `EnvState` stacked over time, leading axis T); returns the path.

    `resolution` is the frame side in pixels; `supersample` antialiases (see `render_image`).
    """
    timesteps = np.asarray(states.timestep)
    if timesteps.ndim != 1 or timesteps.shape[0] == 0:
        raise ValueError(
            f"states must be an EnvState stacked over time (leading axis T >= 1), got timestep shape {timesteps.shape}"
        )
    if not fps > 0:
        raise ValueError(f"fps must be positive, got {fps}")
    num_frames = timesteps.shape[0]
    chunk_size = min(num_frames, FRAMES_PER_RENDER_CALL)
    padded_frames = -(-num_frames // chunk_size) * chunk_size
    # Repeat the last state so every chunk has the same shape (one compilation).
    padded = jax.tree.map(lambda x: np.asarray(x)[np.minimum(np.arange(padded_frames), num_frames - 1)], states)
    chunks = []
    for start in range(0, padded_frames, chunk_size):
        chunk = jax.tree.map(lambda x, s=start: x[s : s + chunk_size], padded)
        chunks.append(np.asarray(_render_frames(chunk, static, resolution, supersample)))
    return write_gif(np.concatenate(chunks)[:num_frames], path, fps)
