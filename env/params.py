"""Environment parameters: traced (`EnvParams`) and compile-time (`StaticEnvParams`), as in Kinetix."""

from __future__ import annotations

import dataclasses

from flax import struct

from kforge.engine import PhysicsScheme, SimParams, StaticSimParams

NUM_MOTOR_BINDINGS = 4
"""Motor colours: the first four slots of the unified action."""

NUM_THRUSTER_BINDINGS = 2
"""Thruster colours: the last two slots of the unified action."""

NUM_ACTION_SLOTS = NUM_MOTOR_BINDINGS + NUM_THRUSTER_BINDINGS


@struct.dataclass
class EnvParams:
    """Per-level constants that may be vmapped: physics and reward shaping."""

    sim: SimParams = SimParams()
    dense_reward_scale: float = 0.1  # [1/m] shaping reward per metre the green-blue distance shrinks (Kinetix default)


@dataclasses.dataclass(frozen=True)
class StaticEnvParams:
    """Sizes and episode constants: hashable, static under `jit`."""

    sim: StaticSimParams = StaticSimParams()
    frame_skip: int = 2  # physics steps per env step
    max_timesteps: int = 256  # env steps per episode

    def __post_init__(self):
        if self.frame_skip < 1:
            raise ValueError(f"StaticEnvParams.frame_skip must be >= 1, got {self.frame_skip}")
        if self.max_timesteps < 1:
            raise ValueError(f"StaticEnvParams.max_timesteps must be >= 1, got {self.max_timesteps}")
        if self.sim.num_reserved_static != 4:
            raise ValueError("Kinetix levels reserve polygon slots 0-3 for the boundaries (num_reserved_static=4)")

    @classmethod
    def for_size(cls, size: str, **overrides) -> StaticEnvParams:
        """Kinetix's static parameters for size 's', 'm' or 'l' (frame_skip 2, 256 steps)."""
        return cls(sim=StaticSimParams.for_size(size), **overrides)

    @property
    def num_bodies(self) -> int:
        return self.sim.num_bodies


def under_scheme(
    scheme: PhysicsScheme, params: EnvParams, static: StaticEnvParams
) -> tuple[EnvParams, StaticEnvParams]:
    """`params` and `static` with `scheme`'s physics; the level's own constants (gravity, ...) and the sizes kept."""
    return params.replace(sim=scheme.sim(params.sim)), dataclasses.replace(static, sim=scheme.static(static.sim))
