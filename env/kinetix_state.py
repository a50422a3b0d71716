"""Kinetix's `EnvState` as flat named leaves (the Kinetix-Offline record fields) <-> our `EnvState`, any leading axes.

Leaf names are Kinetix's `flatten_dict(to_state_dict(state), sep="/")` paths, in its declaration order: `polygon/*`,
`circle/*`, `joint/*`, `thruster/*`, `collision_matrix`, `acc_{rr,cr,cc}_manifolds/*`, `gravity`, then the task
leaves (`thruster_bindings` ... `circle_densities`), `timestep` and `last_distance`: 82 leaves. Shapes, dtypes and
the entity mapping come from the level-file code (`env.level_files` schemas, `env.kinetix_convert`).

Leaves our state does not keep are filled as Kinetix fills them when it expands a state
(`kinetix/data/expanding_utils.py`): every contact manifold field zero (inactive), joint warm-start impulses zero,
`highlighted` False, circle vertices and polygon radii zero; the joint and thruster `global_position` caches are
computed from the bodies' current pose. On import those leaves are dropped (our contact cache starts empty, joint
impulses at zero) and the collision matrix is recomputed from the joints, as Kinetix's level loader does.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import jax.numpy as jnp
import numpy as np

from kforge.env.kinetix_convert import (
    NUM_BOUNDARY_POLYGONS,
    KinetixLevel,
    entities_to_kinetix,
    level_from_kinetix,
    static_from_counts,
)
from kforge.env.level_files import BODY_SCHEMA, JOINT_SCHEMA, MANIFOLD_FIELDS, THRUSTER_SCHEMA, manifold_counts
from kforge.env.params import StaticEnvParams
from kforge.env.state import EnvState, Level

KINETIX_FRAME_SKIP = 2
"""Physics steps per env step in every Kinetix size (s, m, l); a Kinetix state does not store it."""

KIND_DTYPES = {"float": np.dtype(np.float32), "int": np.dtype(np.int32), "bool": np.dtype(bool)}
"""Dtype of a Kinetix leaf of each level-file schema kind (jax without x64)."""

ENTITY_SCHEMAS = {"polygon": BODY_SCHEMA, "circle": BODY_SCHEMA, "joint": JOINT_SCHEMA, "thruster": THRUSTER_SCHEMA}
"""Kinetix entity -> its level-file record schema (the entity's leaves plus the SLOT_LEAVES fields)."""

SLOT_LEAVES: dict[str, tuple[str, str]] = {
    "thruster_bindings": ("thruster", "thruster_binding"),
    "motor_bindings": ("joint", "motor_binding"),
    "polygon_shape_roles": ("polygon", "role"),
    "circle_shape_roles": ("circle", "role"),
    "polygon_highlighted": ("polygon", "highlighted"),
    "circle_highlighted": ("circle", "highlighted"),
    "polygon_densities": ("polygon", "density"),
    "circle_densities": ("circle", "density"),
}
"""Kinetix `EnvState` leaves that level files keep inside the per-slot records: leaf -> (entity, record field)."""

ENV_LEAVES = (
    "thruster_bindings",
    "motor_bindings",
    "motor_auto",
    "polygon_shape_roles",
    "circle_shape_roles",
    "polygon_highlighted",
    "circle_highlighted",
    "polygon_densities",
    "circle_densities",
    "timestep",
    "last_distance",
)
"""Kinetix `EnvState` fields beyond Jax2D's `SimState`, in declaration order."""

MANIFOLD_POINTS = {"acc_rr_manifolds": 2, "acc_cr_manifolds": 1, "acc_cc_manifolds": 1}
"""Contact points per shape pair in each Kinetix manifold leaf; only polygon pairs have a point axis."""


class KinetixStateError(ValueError):
    """Kinetix state leaves are missing or do not fit the size their slot counts imply; the message names the leaf."""


@dataclasses.dataclass(frozen=True)
class LeafSpec:
    """Shape (of one state, without leading axes) and dtype of a Kinetix `EnvState` leaf."""

    shape: tuple[int, ...]
    dtype: np.dtype


def kinetix_leaf_specs(static: StaticEnvParams) -> dict[str, LeafSpec]:
    """Every Kinetix `EnvState` leaf at `static`'s size, in Kinetix's flattening order."""
    sim = static.sim
    counts = {
        "polygon": sim.num_polygons,
        "circle": sim.num_circles,
        "joint": sim.num_joints,
        "thruster": sim.num_thrusters,
    }
    in_records = set(SLOT_LEAVES.values())
    specs = {
        f"{entity}/{field}": LeafSpec((counts[entity], *shape), KIND_DTYPES[kind])
        for entity, schema in ENTITY_SCHEMAS.items()
        for field, (kind, shape) in schema.items()
        if (entity, field) not in in_records
    }
    specs["collision_matrix"] = LeafSpec((sim.num_bodies, sim.num_bodies), KIND_DTYPES["bool"])
    for name, records in manifold_counts(sim.num_polygons, sim.num_circles).items():
        points = MANIFOLD_POINTS[name]
        pair_shape = (records // points,) + ((points,) if points > 1 else ())
        for field, (kind, shape) in MANIFOLD_FIELDS.items():
            specs[f"{name}/{field}"] = LeafSpec(pair_shape + shape, KIND_DTYPES[kind])
    specs["gravity"] = LeafSpec((2,), KIND_DTYPES["float"])
    own = {
        "motor_auto": LeafSpec((sim.num_joints,), KIND_DTYPES["bool"]),
        "timestep": LeafSpec((), KIND_DTYPES["int"]),
        "last_distance": LeafSpec((), KIND_DTYPES["float"]),
    }
    for name in ENV_LEAVES:
        if name in SLOT_LEAVES:
            entity, field = SLOT_LEAVES[name]
            specs[name] = LeafSpec((counts[entity],), KIND_DTYPES[ENTITY_SCHEMAS[entity][field][0]])
        else:
            specs[name] = own[name]
    return specs


def state_to_kinetix(state: EnvState, static: StaticEnvParams) -> dict[str, np.ndarray]:
    """Kinetix leaf name -> host array (leading axes of `state` kept, Kinetix's dtype) of every leaf of `state`."""
    batch = np.shape(state.timestep)
    entities = entities_to_kinetix(Level(sim=state.sim, task=state.task), static)
    ours = {"motor_auto": state.task.motor_auto, "timestep": state.timestep, "last_distance": state.last_distance}
    leaves = {}
    for name, spec in kinetix_leaf_specs(static).items():
        head, _, field = name.partition("/")
        if name in SLOT_LEAVES:
            entity, record_field = SLOT_LEAVES[name]
            value = entities[entity][record_field]
        elif head in MANIFOLD_POINTS:
            value = np.zeros(batch + spec.shape)
        elif field:
            value = entities[head][field]
        else:
            value = entities[name] if name in entities else ours[name]
        value = np.asarray(value)
        if value.shape != batch + spec.shape:
            raise KinetixStateError(f"leaf {name}: mapped to shape {value.shape}, expected {batch + spec.shape}")
        leaves[name] = value.astype(spec.dtype)
    return leaves


def _check_leaf(name: str, value: np.ndarray, spec: LeafSpec, batch: tuple[int, ...]) -> None:
    if value.shape != batch + spec.shape:
        raise KinetixStateError(f"leaf {name}: shape {value.shape}, expected {batch + spec.shape} for this size")
    if value.dtype.kind not in {"f": "f", "i": "iu", "b": "b"}[spec.dtype.kind]:
        raise KinetixStateError(f"leaf {name}: dtype {value.dtype}, expected {spec.dtype}")


def state_from_kinetix(leaves: Mapping[str, np.ndarray]) -> tuple[EnvState, StaticEnvParams]:
    """Our `EnvState` (same leading axes) and static params of Kinetix state leaves; the size is read from the slot
    counts. Raises `KinetixStateError` naming a missing or misshapen leaf."""
    counts = {}
    for entity in ENTITY_SCHEMAS:
        active = f"{entity}/active"
        if active not in leaves:
            raise KinetixStateError(f"leaf {active} is missing")
        if np.ndim(leaves[active]) < 1:
            raise KinetixStateError(f"leaf {active}: expected a slot axis, got shape {np.shape(leaves[active])}")
        counts[f"num_{entity}s"] = int(np.shape(leaves[active])[-1])
    if counts["num_polygons"] < NUM_BOUNDARY_POLYGONS:
        raise KinetixStateError(
            f"leaf polygon/active: {counts['num_polygons']} polygon slots, Kinetix needs at least "
            f"{NUM_BOUNDARY_POLYGONS} (the boundaries)"
        )
    static = static_from_counts(counts | {"frame_skip": KINETIX_FRAME_SKIP})
    batch = np.shape(leaves["polygon/active"])[:-1]
    entities: dict[str, dict[str, np.ndarray]] = {entity: {} for entity in ENTITY_SCHEMAS}
    values = {}
    for name, spec in kinetix_leaf_specs(static).items():
        if name not in leaves:
            raise KinetixStateError(f"leaf {name} is missing")
        value = np.asarray(leaves[name])
        _check_leaf(name, value, spec, batch)
        head, _, field = name.partition("/")
        if name in SLOT_LEAVES:
            entity, record_field = SLOT_LEAVES[name]
            entities[entity][record_field] = value
        elif head in entities:
            entities[head][field] = value
        else:
            values[name] = value
    kinetix = KinetixLevel(
        **entities,
        collision_matrix=values["collision_matrix"],
        gravity=values["gravity"],
        env_params={},
        static_env_params=counts | {"frame_skip": KINETIX_FRAME_SKIP},
    )
    level = level_from_kinetix(kinetix, static)
    state = EnvState(
        sim=level.sim,
        task=level.task.replace(motor_auto=jnp.asarray(values["motor_auto"], bool)),
        timestep=jnp.asarray(values["timestep"], jnp.int32),
        last_distance=jnp.asarray(values["last_distance"], jnp.float32),
    )
    return state, static
