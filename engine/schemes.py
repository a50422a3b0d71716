"""Named physics schemes: how the engine solves a step, as `StaticSimParams` laws and solver settings and
`SimParams` constants that differ from the engine's defaults. A scheme's laws are static: each scheme compiles to its
own step program, holding only its laws' kernels."""

from __future__ import annotations

import dataclasses

from kforge.engine.params import (
    CollisionRules,
    ContactLaw,
    ContactOrder,
    ContactPoints,
    ForceTiming,
    JointLaw,
    SimParams,
    StaticSimParams,
)


@dataclasses.dataclass(frozen=True)
class PhysicsScheme:
    """A physics setting applied over any `SimParams` (a level's gravity, friction and the like are kept) and any
    `StaticSimParams` (sizes are kept)."""

    sim_fields: tuple[tuple[str, float], ...] = ()  # SimParams field (a continuous constant) -> value
    solver_fields: tuple[tuple[str, int | bool], ...] = ()  # StaticSimParams law or solver setting -> value

    def sim(self, base: SimParams) -> SimParams:
        """`base` with the scheme's physics parameters."""
        return base.replace(**dict(self.sim_fields)) if self.sim_fields else base

    def static(self, base: StaticSimParams) -> StaticSimParams:
        """`base` with the scheme's laws and solver settings (its sizes and execution form kept)."""
        return dataclasses.replace(base, **dict(self.solver_fields)) if self.solver_fields else base


DEFAULT_PHYSICS_SCHEME = "kforge"

PHYSICS_SCHEMES = {
    # The engine's defaults: 4 substeps, soft contacts and joints; every row of the physics test plan holds.
    DEFAULT_PHYSICS_SCHEME: PhysicsScheme(),
    # Jax2D's scheme, the closest to Kinetix's play: one step of 10 passes, Baumgarte's push-out, gravity and thrust
    # at the step's start, no speculative contacts (overlaps are found a step late, and fast thin shapes may pass
    # through each other, as in Jax2D), Jax2D's contact points and geometry, its joints and its order of solving
    # contacts.
    "kinetix": PhysicsScheme(
        sim_fields=(("speculative_distance", 0.0), ("speculative_reach", 0.0)),
        solver_fields=(
            ("num_substeps", 1),
            ("num_iterations", 10),
            ("num_relax_iterations", 0),
            ("contact_law", ContactLaw.BAUMGARTE),
            ("force_timing", ForceTiming.STEP_START),
            ("contact_points", ContactPoints.KINETIX),
            ("collision_rules", CollisionRules.JAX2D),
            ("joint_law", JointLaw.JAX2D),
            ("contact_order", ContactOrder.JAX2D),
        ),
    ),
}
"""Scheme name -> scheme. docs/fidelity.md measures how often each agrees with Kinetix level by level, and which rows
of the physics test plan "kinetix" breaks (stacks, bounces, joints at 1/60 s)."""


def physics_scheme(name: str) -> PhysicsScheme:
    """The scheme called `name`; a ValueError naming the known ones otherwise."""
    if name not in PHYSICS_SCHEMES:
        raise ValueError(f"unknown physics scheme {name!r}; expected one of {', '.join(PHYSICS_SCHEMES)}")
    return PHYSICS_SCHEMES[name]
