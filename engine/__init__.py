"""Rigid-body 2D physics in JAX: fixed-shape scenes of convex polygons and circles, joints and thrusters.

Public surface: state and parameter types, the scene builder, `step`, how batched steps and the solver's loops run
(`Batching`, a static option of each step: `StaticSimParams.batching`), named physics schemes (`physics_scheme`),
bitwise-repeatable GPU execution (`use_deterministic_ops`), and the demo scene written as a GIF (`write_demo`); for the
env layer, the geometry, mass properties, contact manifolds and collision filter its levels are built and checked with.
"""

from kforge.engine.batch_last import Batching
from kforge.engine.collision import manifolds, world_geometry
from kforge.engine.collision_filter import joint_collision_matrix, modes_collide
from kforge.engine.demo import write_demo
from kforge.engine.determinism import use_deterministic_ops
from kforge.engine.geometry import (
    CONVEXITY_TOLERANCE,
    MIN_POLYGON_AREA,
    circle_mass_properties,
    cross2,
    polygon_mass_properties,
    rotate,
    rotate_host,
)
from kforge.engine.pairs import pair_layout
from kforge.engine.params import (
    KINETIX_SIZES,
    MAX_POLYGON_VERTICES,
    CollisionRules,
    ContactLaw,
    ContactPoints,
    ForceTiming,
    MotorLaw,
    SimParams,
    StaticSimParams,
)
from kforge.engine.physics_step import StepInfo, step
from kforge.engine.render import write_gif
from kforge.engine.scene import ARENA_SIZE, FLOOR_TOP, SceneBuilder
from kforge.engine.schemes import PHYSICS_SCHEMES, PhysicsScheme, physics_scheme
from kforge.engine.state import NO_FEATURE, SimState, empty_state

__all__ = [
    "ARENA_SIZE",
    "Batching",
    "CONVEXITY_TOLERANCE",
    "FLOOR_TOP",
    "KINETIX_SIZES",
    "MAX_POLYGON_VERTICES",
    "MIN_POLYGON_AREA",
    "NO_FEATURE",
    "PHYSICS_SCHEMES",
    "CollisionRules",
    "ContactLaw",
    "ContactPoints",
    "ForceTiming",
    "MotorLaw",
    "PhysicsScheme",
    "SceneBuilder",
    "SimParams",
    "SimState",
    "StaticSimParams",
    "StepInfo",
    "circle_mass_properties",
    "cross2",
    "empty_state",
    "joint_collision_matrix",
    "manifolds",
    "modes_collide",
    "pair_layout",
    "physics_scheme",
    "polygon_mass_properties",
    "rotate",
    "rotate_host",
    "step",
    "use_deterministic_ops",
    "write_demo",
    "world_geometry",
    "write_gif",
]
