"""Named physics schemes: what each sets, what it keeps of the parameters it is applied to, and that "kinetix" plays
Jax2D's push-out of a deep overlap."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from engine_test_helpers import SIZE_M, SIZE_S, zero_gravity

from kforge.engine import (
    FLOOR_TOP,
    PHYSICS_SCHEMES,
    Batching,
    CollisionRules,
    ContactLaw,
    ContactPoints,
    ForceTiming,
    MotorLaw,
    SceneBuilder,
    SimParams,
    StaticSimParams,
    physics_scheme,
    step,
)
from kforge.engine.params import ContactOrder, JointLaw
from kforge.engine.schemes import DEFAULT_PHYSICS_SCHEME
from tests.rollouts import run_scene

KINETIX = physics_scheme("kinetix")


def test_the_default_scheme_changes_nothing():
    assert DEFAULT_PHYSICS_SCHEME == "kforge"
    default = physics_scheme(DEFAULT_PHYSICS_SCHEME)
    assert default.sim(SimParams()) == SimParams()
    assert default.static(SIZE_M) == SIZE_M


def test_the_kinetix_scheme_is_jax2ds_solver_and_contact_geometry_and_keeps_sizes_and_level_constants():
    sim = KINETIX.sim(SimParams(base_friction=0.7, dt=1.0 / 30.0))
    assert (sim.speculative_distance, sim.speculative_reach) == (0.0, 0.0)  # no speculative contacts
    assert (sim.base_friction, sim.dt) == (0.7, 1.0 / 30.0)  # what it does not set is the level's own
    batching = Batching("whole", 8, "unrolled")
    static = KINETIX.static(dataclasses.replace(SIZE_M, batching=batching))
    assert (static.contact_law, static.force_timing) == (ContactLaw.BAUMGARTE, ForceTiming.STEP_START)
    assert (static.joint_law, static.contact_order) == (JointLaw.JAX2D, ContactOrder.JAX2D)
    assert (static.contact_points, static.collision_rules) == (ContactPoints.KINETIX, CollisionRules.JAX2D)
    assert (static.num_substeps, static.num_iterations, static.num_relax_iterations) == (1, 10, 0)
    assert (static.num_polygons, static.num_circles, static.num_joints, static.num_thrusters) == (6, 3, 2, 2)
    assert static.batching == batching  # the execution form is the caller's


def test_a_scheme_sets_only_continuous_constants_in_sim_params_and_its_laws_statically():
    for name, scheme in PHYSICS_SCHEMES.items():
        for field, value in scheme.sim_fields:
            assert isinstance(value, float) and isinstance(getattr(SimParams(), field), float), (name, field)
        assert {field for field, _ in scheme.solver_fields} <= set(StaticSimParams().physics_options()), name


def test_physics_options_are_the_laws_and_solver_settings_without_the_sizes_or_the_execution_form():
    options = KINETIX.static(SIZE_M).physics_options()
    assert options["num_substeps"] == 1 and options["num_iterations"] == 10 and options["num_relax_iterations"] == 0
    assert options["contact_law"] == ContactLaw.BAUMGARTE and options["joint_law"] == JointLaw.JAX2D
    assert options["swept_speculative_contacts"] is True and options["block_contacts"] is False
    assert not {"num_polygons", "num_circles", "num_joints", "num_thrusters", "num_reserved_static"} & set(options)
    assert "batching" not in options


def test_a_law_must_be_one_of_its_enum():
    assert StaticSimParams(contact_law=1).contact_law is ContactLaw.BAUMGARTE
    with pytest.raises(ValueError, match=r"StaticSimParams.joint_law must be a JointLaw \(SOFT=0, JAX2D=1\), got 3"):
        StaticSimParams(joint_law=3)
    with pytest.raises(ValueError, match="StaticSimParams.swept_speculative_contacts must be a bool, got 1"):
        StaticSimParams(swept_speculative_contacts=1)


def test_an_unknown_scheme_is_refused_with_the_known_ones():
    with pytest.raises(ValueError, match=r"unknown physics scheme 'jax2d'; expected one of kforge, kinetix"):
        physics_scheme("jax2d")
    assert set(PHYSICS_SCHEMES) == {"kforge", "kinetix"}


def _disc_in_the_floor_first_step_speed(scheme_name: str, depth: float) -> float:
    """[m/s] upward speed after one step of a 0.25 m disc started `depth` inside the floor, at rest, in zero gravity,
    under the named scheme."""
    scheme = physics_scheme(scheme_name)
    builder = SceneBuilder(SIZE_S)
    radius = 0.25
    disc = builder.add_circle((2.5, FLOOR_TOP + radius - depth), radius)
    _, traj = run_scene(zero_gravity(builder.build()), scheme.static(SIZE_S), 1, params=scheme.sim(SimParams()))
    return float(np.asarray(traj.velocity)[1, disc, 1])


def test_under_the_kinetix_scheme_a_deep_disc_leaves_at_jax2ds_push_out_speed():
    """Jax2D pushes an overlap out at baumgarte_share / dt times its depth beyond the slop, all of it within one step
    of 10 passes: a disc 10 cm in the floor leaves at 0.2 x 60/s x 9 cm = 1.08 m/s. The default's substeps shrink the
    overlap within the step and its soft contacts push at most max_push_velocity."""
    depth, share, slop, dt = 0.1, SimParams().baumgarte_share, SimParams().contact_slop, SimParams().dt
    assert _disc_in_the_floor_first_step_speed("kinetix", depth) == pytest.approx(share / dt * (depth - slop), rel=1e-5)
    assert _disc_in_the_floor_first_step_speed("kforge", depth) < 0.95 * share / dt * (depth - slop)


def _step_jaxpr(static: StaticSimParams, params: SimParams) -> str:
    """The traced program of one step of an empty scene of `static`'s size."""
    state = SceneBuilder(static).build()
    motors, thrusters = jnp.zeros(static.num_joints), jnp.zeros(static.num_thrusters)
    return str(jax.make_jaxpr(lambda s, p: step(s, p, motors, thrusters, static=static))(state, params))


def test_each_scheme_traces_its_own_program_holding_only_its_laws():
    """The laws are static: the two schemes' steps are different programs, and a law's kernels are only in the
    programs that follow it (the servo motor's tanh is in a SERVO step, and nowhere in a CONSTRAINT one)."""
    programs = {
        name: _step_jaxpr(scheme.static(SIZE_S), scheme.sim(SimParams())) for name, scheme in PHYSICS_SCHEMES.items()
    }
    assert programs["kforge"] != programs["kinetix"]
    assert "tanh" in programs["kforge"]
    constraint = dataclasses.replace(SIZE_S, motor_law=MotorLaw.CONSTRAINT)
    assert "tanh" not in _step_jaxpr(constraint, SimParams())
