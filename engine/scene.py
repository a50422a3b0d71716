"""Host-side scene construction with validation: build a `SimState` shape by shape."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from kforge.engine.collision_filter import joint_collision_matrix
from kforge.engine.geometry import check_convex_polygon, circle_mass_properties, polygon_mass_properties, rotate_host
from kforge.engine.params import MAX_POLYGON_VERTICES, StaticSimParams
from kforge.engine.state import SimState, empty_state

ARENA_SIZE = 5.0
"""[m] side of the Kinetix arena: the floor spans x in [0, 5], the ceiling starts at y = 5."""

FLOOR_TOP = 0.4
"""[m] height of the top of the Kinetix floor."""

BOUNDARY_THICKNESS = 5.0
"""[m] thickness of walls; floor and ceiling are thicker (10.4 m), as in Kinetix."""

DEFAULT_DENSITY = 1.0  # [kg/m^2]
DEFAULT_FRICTION = 1.0  # [-]


@dataclasses.dataclass(frozen=True)
class _Material:
    """Surface and mass parameters of one body, as given to an `add_*` call."""

    density: float
    friction: float
    restitution: float
    collision_mode: int
    static: bool


@dataclasses.dataclass(frozen=True)
class _Placement:
    """Where one body starts, as given to an `add_*` call: position [m], rotation [rad], velocity [m/s] and angular
    velocity [rad/s]."""

    position: np.ndarray
    rotation: float
    velocity: tuple
    angular_velocity: float


def _box_vertices(width: float, height: float) -> np.ndarray:
    half_w, half_h = width / 2, height / 2
    return np.array([[-half_w, -half_h], [half_w, -half_h], [half_w, half_h], [-half_w, half_h]])


@dataclasses.dataclass
class SceneBuilder:
    """Adds shapes, joints and thrusters to an initially empty scene, checking every input.

    Positions and anchors are given in world coordinates at build time; `build()` returns the `SimState`.
    With `boundaries=True`, reserved polygon slots 0-3 hold the Kinetix floor, left wall, right wall and ceiling.
    """

    static: StaticSimParams
    boundaries: bool = True

    def __post_init__(self):
        self._state = jax_to_numpy(empty_state(self.static))
        self._densities = np.zeros(self.static.num_bodies)
        if self.boundaries:
            if self.static.num_reserved_static < 4:
                raise ValueError("boundaries need StaticSimParams.num_reserved_static >= 4")
            half = ARENA_SIZE / 2
            floor_height = 2 * ARENA_SIZE + FLOOR_TOP
            self.add_box(
                (half, FLOOR_TOP - floor_height / 2), (ARENA_SIZE, floor_height), static=True, slot=0, collision_mode=2
            )
            self.add_box(
                (-BOUNDARY_THICKNESS / 2, half), (BOUNDARY_THICKNESS, ARENA_SIZE), static=True, slot=1, collision_mode=2
            )
            self.add_box(
                (ARENA_SIZE + BOUNDARY_THICKNESS / 2, half),
                (BOUNDARY_THICKNESS, ARENA_SIZE),
                static=True,
                slot=2,
                collision_mode=2,
            )
            self.add_box(
                (half, ARENA_SIZE + floor_height / 2), (ARENA_SIZE, floor_height), static=True, slot=3, collision_mode=2
            )

    # ----------------------------------------------------------------- shapes
    def add_polygon(
        self,
        position,
        vertices,
        *,
        rotation: float = 0.0,
        density: float = DEFAULT_DENSITY,
        friction: float = DEFAULT_FRICTION,
        restitution: float = 0.0,
        collision_mode: int = 1,
        static: bool = False,
        velocity=(0.0, 0.0),
        angular_velocity: float = 0.0,
        slot: int | None = None,
    ) -> int:
        """Add a convex polygon whose `vertices` are relative to `position` before `rotation`; returns its body index.

        The stored position is the area centroid; vertices are re-expressed relative to it.
        """
        local = check_convex_polygon(vertices)
        index = self._take_slot("polygon", slot, static)
        material = self._check_material(index, density, friction, restitution, collision_mode, static)
        padded = np.zeros((MAX_POLYGON_VERTICES, 2))
        padded[: len(local)] = local
        mass, centroid, inertia = (
            np.asarray(x, np.float64) for x in polygon_mass_properties(padded, len(local), density)
        )
        centred = padded - centroid
        centred[len(local) :] = 0.0
        b = self._state.bodies
        b.vertices[index] = centred
        b.n_vertices[index] = len(local)
        b.radius[index] = 0.0
        world_centroid = np.asarray(position, np.float64) + rotate_host(rotation, centroid)
        self._set_body(
            index, _Placement(world_centroid, rotation, velocity, angular_velocity), (mass, inertia), material
        )
        return index

    def add_box(self, position, size, **kwargs) -> int:
        """Add a rectangle of `size` = (width, height) [m] centred at `position`; keywords as `add_polygon`."""
        width, height = size
        if not (width > 0 and height > 0):
            raise ValueError(f"box size must be positive, got {size}")
        return self.add_polygon(position, _box_vertices(width, height), **kwargs)

    def add_circle(
        self,
        position,
        radius: float,
        *,
        rotation: float = 0.0,
        density: float = DEFAULT_DENSITY,
        friction: float = DEFAULT_FRICTION,
        restitution: float = 0.0,
        collision_mode: int = 1,
        static: bool = False,
        velocity=(0.0, 0.0),
        angular_velocity: float = 0.0,
        slot: int | None = None,
    ) -> int:
        """Add a disc; returns its body index."""
        if not (np.isfinite(radius) and radius > 0):
            raise ValueError(f"circle radius must be positive and finite, got {radius}")
        index = self._take_slot("circle", slot, static)
        material = self._check_material(index, density, friction, restitution, collision_mode, static)
        mass, inertia = (float(x) for x in circle_mass_properties(radius, density))
        self._state.bodies.radius[index] = radius
        placement = _Placement(np.asarray(position, np.float64), rotation, velocity, angular_velocity)
        self._set_body(index, placement, (mass, inertia), material)
        return index

    # ----------------------------------------------------------------- joints and thrusters
    def add_revolute_joint(
        self,
        body_a: int,
        body_b: int,
        anchor,
        *,
        motor_speed: float = 0.0,
        motor_power: float = 0.0,
        motor_on: bool = False,
        limits: tuple[float, float] | None = None,
    ) -> int:
        """Pin two bodies together at the world point `anchor`; optional motor and angle limits [rad]."""
        index = self._add_joint(body_a, body_b, anchor, is_fixed=False)
        j = self._state.joints
        if limits is not None:
            lower, upper = limits
            if not (lower <= 0.0 <= upper):
                raise ValueError(
                    f"joint limits must satisfy lower <= 0 <= upper (angles relative to now), got {limits}"
                )
            j.has_limits[index], j.lower_angle[index], j.upper_angle[index] = True, lower, upper
        if motor_power < 0:
            raise ValueError(f"motor_power must be >= 0, got {motor_power}")
        j.motor_on[index], j.motor_speed[index], j.motor_power[index] = motor_on, motor_speed, motor_power
        return index

    def add_fixed_joint(self, body_a: int, body_b: int, anchor) -> int:
        """Weld two bodies at the world point `anchor`, keeping their current relative angle."""
        return self._add_joint(body_a, body_b, anchor, is_fixed=True)

    def add_thruster(self, body: int, anchor, angle: float, power: float = 1.0) -> int:
        """Thruster at world point `anchor` pushing along world direction `angle` [rad] (body frame at build time)."""
        self._check_body(body, "thruster body")
        t = self._state.thrusters
        index = _first_free(t.active, "thruster", self.static.num_thrusters)
        if power < 0:
            raise ValueError(f"thruster power must be >= 0, got {power}")
        b = self._state.bodies
        t.body[index] = body
        t.anchor[index] = rotate_host(-b.rotation[body], np.asarray(anchor, np.float64) - b.position[body])
        t.angle[index] = angle - b.rotation[body]
        t.power[index] = power
        t.active[index] = True
        return index

    # ----------------------------------------------------------------- result
    @property
    def densities(self) -> np.ndarray:
        """(N,) [kg/m^2] density of each body slot (0 for empty or static slots)."""
        return self._densities.copy()

    def build(self) -> SimState:
        """The scene as a `SimState` (float32 arrays), with the joint collision matrix filled in."""
        state = jax_from_numpy(self._state)
        return state.replace(collision_matrix=joint_collision_matrix(state.joints, self.static.num_bodies))

    # ----------------------------------------------------------------- helpers
    def _take_slot(self, kind: str, slot: int | None, static: bool) -> int:
        p, n, reserved = self.static.num_polygons, self.static.num_bodies, self.static.num_reserved_static
        first, end = (0, p) if kind == "polygon" else (p, n)
        active = self._state.bodies.active
        if slot is None:
            start = reserved if kind == "polygon" else first
            free = [i for i in range(start, end) if not active[i]]
            if not free:
                raise ValueError(f"no free {kind} slot: all {end - start} are used (StaticSimParams too small)")
            return free[0]
        index = first + slot
        if not first <= index < end:
            raise ValueError(f"{kind} slot {slot} out of range [0, {end - first})")
        if active[index]:
            raise ValueError(f"{kind} slot {slot} is already used")
        if kind == "polygon" and index < reserved and not static:
            raise ValueError(f"polygon slot {slot} is reserved for static bodies (num_reserved_static={reserved})")
        return index

    def _check_material(self, index, density, friction, restitution, collision_mode, static) -> _Material:
        if not static and not (np.isfinite(density) and density > 0):
            raise ValueError(f"body {index}: density must be positive for a movable body, got {density}")
        if static and not (np.isfinite(density) and density >= 0):
            raise ValueError(f"body {index}: density must be >= 0, got {density}")
        if not (np.isfinite(friction) and friction >= 0):
            raise ValueError(f"body {index}: friction must be >= 0, got {friction}")
        if not (0.0 <= restitution <= 1.0):
            raise ValueError(f"body {index}: restitution must be in [0, 1], got {restitution}")
        if collision_mode not in (0, 1, 2):
            raise ValueError(f"body {index}: collision_mode must be 0, 1 or 2, got {collision_mode}")
        return _Material(density, friction, restitution, collision_mode, static)

    def _set_body(self, index, placement: _Placement, mass_properties, material: _Material):
        """Write body `index`: its placement, its (mass [kg], inertia [kg m^2]) and its material."""
        position, rotation = placement.position, placement.rotation
        velocity, angular_velocity = placement.velocity, placement.angular_velocity
        mass, inertia = mass_properties
        values = np.concatenate([np.ravel(position), np.ravel(velocity), [rotation, angular_velocity]])
        if not np.all(np.isfinite(values)) or len(values) != 6:
            raise ValueError(f"body {index}: position, velocity, rotation must be finite 2-vectors/scalars")
        b = self._state.bodies
        b.position[index] = position
        b.rotation[index] = rotation
        b.velocity[index] = velocity
        b.angular_velocity[index] = angular_velocity
        b.inverse_mass[index] = 0.0 if material.static else 1.0 / mass
        b.inverse_inertia[index] = 0.0 if material.static else 1.0 / inertia
        b.friction[index] = material.friction
        b.restitution[index] = material.restitution
        b.collision_mode[index] = material.collision_mode
        b.active[index] = True
        self._densities[index] = 0.0 if material.static else material.density

    def _check_body(self, body: int, what: str):
        n = self.static.num_bodies
        if not (isinstance(body, (int, np.integer)) and 0 <= body < n):
            raise ValueError(f"{what} index {body!r} out of range [0, {n})")
        if not self._state.bodies.active[body]:
            raise ValueError(f"{what} {body} is an empty slot")

    def _add_joint(self, body_a: int, body_b: int, anchor, is_fixed: bool) -> int:
        self._check_body(body_a, "joint body_a")
        self._check_body(body_b, "joint body_b")
        if body_a == body_b:
            raise ValueError(f"a joint needs two different bodies, got {body_a} twice")
        anchor = np.asarray(anchor, np.float64)
        if anchor.shape != (2,) or not np.all(np.isfinite(anchor)):
            raise ValueError(f"joint anchor must be a finite (x, y) point, got {anchor}")
        j = self._state.joints
        index = _first_free(j.active, "joint", self.static.num_joints)
        b = self._state.bodies
        j.body_a[index], j.body_b[index] = body_a, body_b
        j.anchor_a[index] = rotate_host(-b.rotation[body_a], anchor - b.position[body_a])
        j.anchor_b[index] = rotate_host(-b.rotation[body_b], anchor - b.position[body_b])
        j.reference_angle[index] = b.rotation[body_b] - b.rotation[body_a]
        j.is_fixed[index] = is_fixed
        j.active[index] = True
        return index


def _first_free(active: np.ndarray, kind: str, capacity: int) -> int:
    free = np.flatnonzero(~active)
    if free.size == 0:
        raise ValueError(f"no free {kind} slot: all {capacity} are used (StaticSimParams too small)")
    return int(free[0])


def jax_to_numpy(state: SimState) -> SimState:
    """Writable float64/int/bool numpy copy of a state (for host-side editing)."""

    def convert(x):
        array = np.array(x)
        return array.astype(np.float64) if array.dtype == np.float32 else array

    return jax.tree_util.tree_map(convert, state)


def jax_from_numpy(state: SimState) -> SimState:
    """Device copy of a numpy state with float32 floats."""

    def convert(x):
        array = np.asarray(x)
        return jnp.asarray(array.astype(np.float32) if array.dtype == np.float64 else array)

    return jax.tree_util.tree_map(convert, state)
