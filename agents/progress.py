"""Progress of a training program while it runs, reported to the host.

A `train_levels` call given a progress token reports, each time it starts an evaluation segment of
`PPOConfig.select_every_updates` updates, how many PPO updates every level of its batch has done so far, to the
listener the token was registered for. Reports come from XLA's threads while the program runs; they carry no
training data and never change what is computed (the token is an ordinary traced argument, so one compiled program
serves every listener), and a listener that raises is logged, never propagated into the training.

    with training_progress(lambda done, total: print(f"{done}/{total} updates")) as token:
        trained = jax.block_until_ready(train_levels(levels, keys, config, env_params, static, progress=token))
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import threading
from collections.abc import Callable, Iterator

import jax
import jax.numpy as jnp
import numpy as np

ProgressListener = Callable[[int, int], None]
"""Called with (updates done, updates in total) per level."""

_listeners: dict[int, ProgressListener] = {}
_tokens = itertools.count(1)
_lock = threading.Lock()
_log = logging.getLogger(__name__)


@contextlib.contextmanager
def training_progress(listener: ProgressListener) -> Iterator[jax.Array]:
    """Registers `listener` and yields the token to pass as `train_levels(..., progress=token)`.

    Wait for the program's result inside the block: reports arriving after it ends are dropped.
    """
    with _lock:
        token = next(_tokens)
        _listeners[token] = listener
    try:
        yield jnp.asarray(token, jnp.int32)
    finally:
        with _lock:
            del _listeners[token]


def report_updates(token: jax.Array, updates_done: jax.Array, num_updates: int) -> None:
    """Inside a traced program: tell `token`'s listener that `updates_done` of `num_updates` updates are done.

    `token` and `updates_done` must not be batched under `vmap` (one report per program, not per level).
    """
    jax.debug.callback(_deliver, token, updates_done, num_updates)


def _deliver(token: np.ndarray, updates_done: np.ndarray, num_updates: np.ndarray) -> None:
    with _lock:
        listener = _listeners.get(int(token))
    if listener is None:
        return
    try:
        listener(int(updates_done), int(num_updates))
    except Exception:  # a failing listener must not fail the training it watches
        _log.warning("progress listener failed; training goes on", exc_info=True)
