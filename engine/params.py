"""Physics parameters: traced floats (`SimParams`) and compile-time sizes, laws and execution form
(`StaticSimParams`)."""

from __future__ import annotations

import dataclasses
import enum

from flax import struct

from kforge.engine.batch_last import Batching

MAX_POLYGON_VERTICES = 4
"""Every polygon slot holds up to this many vertices (triangles and quadrilaterals)."""

KINETIX_SIZES: dict[str, tuple[int, int, int, int]] = {
    "s": (5, 2, 1, 1),
    "m": (6, 3, 2, 2),
    "l": (12, 4, 6, 2),
}
"""Kinetix env sizes: (polygons, circles, joints, thrusters), reserved boundary polygons included."""


class ForceTiming(enum.IntEnum):
    """When in a step gravity and thrust change the velocities."""

    SPREAD = 0
    """A share in every substep, before its solve (Box2D v3): positions follow the acceleration to second order."""
    STEP_START = 1
    """Kinetix's (Jax2D's): the whole step's impulse before the first substep, in Jax2D's arithmetic (v + g dt, then
    each thruster's power x base power x action x dt along its direction), so a body in free flight moves dt x
    (v + a dt) per step, dt^2 a x 3/8 further than SPREAD with 4 substeps (6 cm more fall per second of flight)."""


class MotorLaw(enum.IntEnum):
    """How a joint motor drives its joint."""

    SERVO = 0
    """Kinetix's (Jax2D's): once per step, before the solve, an angular impulse pair of at most
    base_motor_power x motor_power x dt x axial inertia, scaled by tanh(motor_decay x speed error) and faded near an
    angle limit; the solve then redistributes it like any other velocity."""
    CONSTRAINT = 1
    """A velocity row solved with the contacts and joints in every substep, driving the joint's speed to the target
    within the same torque bound."""


class ContactLaw(enum.IntEnum):
    """How a contact pushes overlapping shapes apart."""

    SOFT = 0
    """Box2D v3's soft contact: a spring-damper (contact_hertz) pushes at most at max_push_velocity, and each
    substep's relaxing pass takes the push out of the velocity again, so separated shapes do not fly apart."""
    BAUMGARTE = 1
    """Kinetix's (Jax2D's): a rigid row drives the normal speed to baumgarte_share / dt times the overlap beyond
    contact_slop in every pass, relaxing included, so the push-out stays in the bodies' velocity (a deep overlap
    launches them); shapes at rest sink by up to the slop."""


class ContactPoints(enum.IntEnum):
    """Where a contact's points lie and how deep they count."""

    MIDWAY = 0
    """Midway between the two surfaces, each point with its own separation (Box2D v3)."""
    KINETIX = 1
    """Jax2D's: on the polygon's surface (a circle on a polygon), on the first circle's surface (two circles), on
    the incident polygon (two polygons; which points, `CollisionRules`), the overlapping points all at the pair's
    deepest separation; a deep overlap so moves lever arms by up to its depth and pushes a shallow corner as hard as
    the deepest."""


class CollisionRules(enum.IntEnum):
    """Which points two overlapping shapes touch at and which impulses they start from, where Box2D's rules and
    Jax2D's differ."""

    BOX2D = 0
    """Two polygons: the incident edge (the one most opposed to the reference face) clipped to the reference face's
    sides, so a corner past the face's end leaves a point at the end; the second polygon's face becomes the reference
    when it separates more by `engine.collision.REFERENCE_FACE_TOLERANCE`. A circle whose centre is inside a polygon
    overlaps it by its radius plus the centre's depth."""
    JAX2D = 1
    """Two polygons: the incident polygon's two deepest vertices, each moved along the reference face into its extent
    and keeping its depth (a vertex past the face's end and outside it makes no point); the second polygon's face
    becomes the reference when it separates more by `engine.collision.KINETIX_REFERENCE_FACE_TOLERANCE`. A circle
    whose centre is inside a polygon overlaps it by its radius. A point starts from last step's impulses of the
    point in its slot, whatever feature that one touched at (Box2D's: of the point of the same feature)."""


class ContactOrder(enum.IntEnum):
    """In which order one pass solves the contacts."""

    COLOURED = 0
    """Gauss-Seidel over colours of pairs that share no movable body (`engine.pairs`); each pair's normal rows, then
    its friction rows."""
    JAX2D = 1
    """Jax2D's: per kind of pair, batches of pairs at once, point by point, a point's normal row then its friction row
    (`engine.jax2d_contacts`)."""


class JointLaw(enum.IntEnum):
    """How joints hold their anchors together, their fixed angles and their limits."""

    SOFT = 0
    """Box2D v3's soft point constraint (a 2x2 effective-mass solve) and angle rows; angle limits as one-sided
    speculative rows with accumulated impulses: a limit holds under load, within the joint's softness, and a joint
    approaching it is stopped at it."""
    JAX2D = 1
    """Jax2D's: an under-relaxed impulse along the anchors' relative velocity, biased by their gap, and in every
    pass a direct move of the bodies that closes most of the gap (`engine.jax2d_joints`); fixed angles and limits
    by Jax2D's angular impulse."""


@struct.dataclass
class SimParams:
    """Continuous physical constants of a step, every one a float; every field may differ per scene under `vmap`.
    Which law a step follows is static (`StaticSimParams`)."""

    # Time
    dt: float = 1.0 / 60.0  # [s] one physics step

    # Contacts (soft-step solver)
    contact_hertz: float = 30.0  # [Hz] stiffness of the contact position correction
    contact_damping_ratio: float = 10.0  # [-] damping of the contact position correction
    max_push_velocity: float = 3.0  # [m/s] fastest speed at which overlapping shapes are pushed apart
    restitution_threshold: float = 1.0  # [m/s] approach speeds below this never bounce
    speculative_distance: float = 0.02  # [m] contacts are created this far before shapes touch
    speculative_reach: float = 1.0  # [-] share of a step's motion added to the speculative distance
    touch_distance: float = 0.005  # [m] shapes closer than this count as touching
    push_touch_distance: float = float("inf")  # [m] a contact that pushed counts as touching if this close at start
    base_friction: float = 0.4  # [-] friction of a pair = base_friction * sqrt(f_a^2 + f_b^2) (Kinetix's mixing)

    # Joints. A soft joint stretches under load by about load / (effective mass x (2 pi joint_hertz)^2), and the
    # effective mass is about the lighter body's, so the stretch grows with the mass ratio across the joint. 75 Hz
    # with damping ratio 2 holds a 100:1 double pendulum within 1.8 cm (60 Hz / 1: 2.2 cm) and a 30:1 one within
    # 0.6 cm (0.9 cm); with 4 substeps the solve turns unstable from about 85 Hz at 100:1 and 110 Hz at 30:1.
    # Random Kinetix levels have joint mass ratios up to about 34:1 (99th percentile 13:1).
    joint_hertz: float = 75.0  # [Hz] stiffness of joint position correction
    joint_damping_ratio: float = 2.0  # [-]

    # Actuators (Kinetix base values)
    base_motor_speed: float = 6.0  # [rad/s] target relative speed per unit of joint motor_speed and action
    base_motor_power: float = 900.0  # [rad/s^2] torque bound per unit motor_power, per unit of axial inertia
    base_thruster_power: float = 10.0  # [N] force per unit of thruster power and action
    motor_decay: float = 0.1  # [s/rad] servo: the impulse is tanh(motor_decay x speed error) of its bound
    motor_limit_fade: float = 0.1  # [rad] servo: the impulse fades to 0 over this angle before a joint limit

    baumgarte_share: float = 0.2  # [-] BAUMGARTE: share of the overlap beyond contact_slop closed per step (Jax2D's)
    contact_slop: float = 0.01  # [m] BAUMGARTE: overlap left uncorrected (Jax2D's)
    baumgarte_depth: float = float("inf")  # [m] SOFT: a contact point deeper than this at the step's start (a level
    # that starts with shapes inside each other) is pushed out by BAUMGARTE's law, the push kept in the velocity

    # Safety clips applied after every step
    max_position: float = 15.0  # [m] per coordinate
    max_velocity: float = 100.0  # [m/s] per component
    max_angular_velocity: float = 50.0  # [rad/s]


LAW_FIELDS: dict[str, type[enum.IntEnum]] = {
    "force_timing": ForceTiming,
    "motor_law": MotorLaw,
    "contact_law": ContactLaw,
    "contact_points": ContactPoints,
    "collision_rules": CollisionRules,
    "joint_law": JointLaw,
    "contact_order": ContactOrder,
}
"""`StaticSimParams` law field -> its enum."""

SIZE_FIELDS = ("num_polygons", "num_circles", "num_joints", "num_thrusters", "num_reserved_static")
"""`StaticSimParams` fields that size the arrays."""

EXECUTION_FIELDS = ("batching",)
"""`StaticSimParams` fields that choose how a step runs, not how it plays: every value gives the same states to
rounding."""


@dataclasses.dataclass(frozen=True)
class StaticSimParams:
    """Array sizes, the physics laws, iteration counts and the execution form: hashable, static under `jit`; one
    compiled step per value, holding only the kernels of its laws."""

    num_polygons: int = 5  # polygon slots, reserved boundary slots included
    num_circles: int = 2
    num_joints: int = 1
    num_thrusters: int = 1
    num_reserved_static: int = 4  # polygon slots 0.. that are always static (floor, walls, ceiling)
    num_substeps: int = 4  # solver substeps per step
    num_iterations: int = 1  # position-correcting solver passes per substep; positions advance after the last
    num_relax_iterations: int = 1  # passes without position bias per substep, after positions advanced
    block_contacts: bool = False  # a pair's two rigid normal rows are solved together, not one after the other
    relax_contacts: bool = True  # relaxing passes solve contacts and joints; False: joints only (contacts keep their
    # push-out velocity, as under Jax2D's scheme, while joints and their limits let go of theirs)
    force_timing: ForceTiming = ForceTiming.SPREAD  # gravity and thrust spread over substeps or at the step's start
    motor_law: MotorLaw = MotorLaw.SERVO  # Kinetix's servo impulse or a constraint row
    contact_law: ContactLaw = ContactLaw.SOFT  # how overlapping shapes are pushed apart
    contact_points: ContactPoints = ContactPoints.MIDWAY  # where contact points lie, how deep they count
    collision_rules: CollisionRules = CollisionRules.BOX2D  # where shapes touch, which impulses they start from
    joint_law: JointLaw = JointLaw.SOFT  # how joints hold their anchors, angles and limits
    contact_order: ContactOrder = ContactOrder.COLOURED  # in which order a pass solves the contacts
    swept_speculative_contacts: bool = True  # a circle's speculative contact acts only if its free motion meets
    # what it faces within the step (a near miss makes no contact)
    batching: Batching = Batching()  # how a vmapped step batches and the form of the solver's loops (execution only)

    def __post_init__(self):
        for name in SIZE_FIELDS:
            if getattr(self, name) < 0:
                raise ValueError(f"StaticSimParams.{name} must be >= 0, got {getattr(self, name)}")
        if self.num_reserved_static > self.num_polygons:
            raise ValueError(
                f"StaticSimParams.num_reserved_static ({self.num_reserved_static}) exceeds "
                f"num_polygons ({self.num_polygons})"
            )
        for name, least in (("num_substeps", 1), ("num_iterations", 1), ("num_relax_iterations", 0)):
            if getattr(self, name) < least:
                raise ValueError(f"StaticSimParams.{name} must be >= {least}, got {getattr(self, name)}")
        for name, law in LAW_FIELDS.items():
            value = getattr(self, name)
            if isinstance(value, bool) or value not in set(law):
                known = ", ".join(f"{member.name}={member.value}" for member in law)
                raise ValueError(f"StaticSimParams.{name} must be a {law.__name__} ({known}), got {value!r}")
            object.__setattr__(self, name, law(value))
        for name in ("block_contacts", "relax_contacts", "swept_speculative_contacts"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"StaticSimParams.{name} must be a bool, got {getattr(self, name)!r}")
        if not isinstance(self.batching, Batching):
            raise ValueError(f"StaticSimParams.batching must be an engine.Batching, got {self.batching!r}")

    def physics_options(self) -> dict[str, int | bool]:
        """Every setting that changes how a step plays (laws, substeps, passes), the sizes and the execution form
        (`EXECUTION_FIELDS`) left out."""
        left_out = set(SIZE_FIELDS) | set(EXECUTION_FIELDS)
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name not in left_out}

    @property
    def num_bodies(self) -> int:
        """Polygons first (global index 0..P-1), then circles (P..P+C-1)."""
        return self.num_polygons + self.num_circles

    @classmethod
    def for_size(cls, size: str, **overrides) -> StaticSimParams:
        """Static params of a Kinetix env size ('s', 'm' or 'l')."""
        if size not in KINETIX_SIZES:
            raise ValueError(f"unknown size {size!r}; expected one of {sorted(KINETIX_SIZES)}")
        polygons, circles, joints, thrusters = KINETIX_SIZES[size]
        return cls(num_polygons=polygons, num_circles=circles, num_joints=joints, num_thrusters=thrusters, **overrides)
