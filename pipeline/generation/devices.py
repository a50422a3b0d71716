"""A level batch spread over the local devices: each device trains and rolls out its own share of the levels.

Levels never interact, so each device runs the same program on L / D levels with no communication between
devices (`jax.shard_map` over a 1-D mesh of the local devices). With one device, or a batch that the device count
does not divide, a function runs unchanged. Results equal the one-device run to rounding: each device's program
has a smaller batch, and XLA may vectorise its arithmetic differently.
"""

from __future__ import annotations

import jax
import numpy as np
from jax.sharding import Mesh, PartitionSpec

LEVEL_AXIS = "levels"


def level_devices(num_levels: int) -> int:
    """Local devices a batch of `num_levels` levels is spread over (1: not spread)."""
    count = len(jax.local_devices())
    return count if count > 1 and num_levels % count == 0 else 1


def over_local_devices(function, num_levels: int, level_args: int, shared_args: int):
    """`function(*level_args, *shared_args)` with its first `level_args` arguments (leading level axis, every leaf)
    split over the local devices, the others copied to each, and every output split along its leading level axis.
    """
    if level_devices(num_levels) == 1:
        return function
    mesh = Mesh(np.array(jax.local_devices()), (LEVEL_AXIS,))
    in_specs = (PartitionSpec(LEVEL_AXIS),) * level_args + (PartitionSpec(),) * shared_args
    sharded = jax.shard_map(
        function, mesh=mesh, in_specs=in_specs, out_specs=PartitionSpec(LEVEL_AXIS), check_vma=False
    )
    return jax.jit(sharded)
