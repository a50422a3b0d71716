"""Rigid-body 2D physics in JAX: fixed-shape scenes of convex polygons and circles, joints and thrusters.

Public surface: state and parameter types, the scene builder, and `step`.
"""

from engine.pairs import PairLayout, pair_layout
from engine.params import KINETIX_SIZES, MAX_POLYGON_VERTICES, SimParams, StaticSimParams
from engine.physics_step import StepInfo, step
from engine.scene import SceneBuilder
from engine.state import Bodies, ContactCache, Joints, SimState, Thrusters, empty_state

__all__ = [
    "KINETIX_SIZES",
    "MAX_POLYGON_VERTICES",
    "Bodies",
    "ContactCache",
    "Joints",
    "PairLayout",
    "SceneBuilder",
    "SimParams",
    "SimState",
    "StaticSimParams",
    "StepInfo",
    "Thrusters",
    "empty_state",
    "pair_layout",
    "step",
]
