"""Named physics schemes: what each sets, what it keeps of the parameters it is applied to, and that "kinetix" plays
Jax2D's push-out of a deep overlap."""

from __future__ import annotations

import numpy as np
import pytest
from engine_test_helpers import SIZE_M, SIZE_S, run, zero_gravity

from engine import (
    DEFAULT_PHYSICS_SCHEME,
    FLOOR_TOP,
    PHYSICS_SCHEMES,
    CollisionRules,
    ContactLaw,
    ContactPoints,
    ForceTiming,
    LimitLaw,
    SceneBuilder,
    SimParams,
    physics_scheme,
)

KINETIX = physics_scheme("kinetix")


def test_the_default_scheme_changes_nothing():
    assert DEFAULT_PHYSICS_SCHEME == "kforge"
    default = physics_scheme(DEFAULT_PHYSICS_SCHEME)
    assert default.sim(SimParams()) == SimParams()
    assert default.static(SIZE_M) == SIZE_M


def test_the_kinetix_scheme_is_jax2ds_solver_and_contact_geometry_and_keeps_sizes_and_level_constants():
    sim = KINETIX.sim(SimParams(base_friction=0.7, dt=1.0 / 30.0))
    assert (sim.contact_law, sim.force_timing, sim.limit_law) == (
        ContactLaw.BAUMGARTE,
        ForceTiming.STEP_START,
        LimitLaw.BOUNDED_RETURN,
    )
    assert (sim.speculative_distance, sim.overlap_allowance, sim.contact_points) == (0.0, 2.0, ContactPoints.KINETIX)
    assert sim.collision_rules == CollisionRules.JAX2D
    assert (sim.base_friction, sim.dt) == (0.7, 1.0 / 30.0)  # what it does not set is the level's own
    static = KINETIX.static(SIZE_M)
    assert (static.num_substeps, static.num_iterations, static.num_relax_iterations) == (1, 10, 0)
    assert (static.num_polygons, static.num_circles, static.num_joints, static.num_thrusters) == (6, 3, 2, 2)


def test_physics_options_are_the_solver_settings_without_the_sizes():
    options = KINETIX.static(SIZE_M).physics_options()
    assert options["num_substeps"] == 1 and options["num_iterations"] == 10 and options["num_relax_iterations"] == 0
    assert not {"num_polygons", "num_circles", "num_joints", "num_thrusters", "num_reserved_static"} & set(options)


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
    _, traj = run(zero_gravity(builder.build()), scheme.static(SIZE_S), 1, params=scheme.sim(SimParams()))
    return float(np.asarray(traj.velocity)[1, disc, 1])


def test_under_the_kinetix_scheme_a_deep_disc_leaves_at_jax2ds_push_out_speed():
    """Jax2D pushes an overlap out at baumgarte_share / dt times its depth beyond the slop, all of it within one step
    of 10 passes: a disc 10 cm in the floor leaves at 0.2 x 60/s x 9 cm = 1.08 m/s. The default's substeps shrink the
    overlap within the step and its soft contacts push at most max_push_velocity."""
    depth, share, slop, dt = 0.1, SimParams().baumgarte_share, SimParams().contact_slop, SimParams().dt
    assert _disc_in_the_floor_first_step_speed("kinetix", depth) == pytest.approx(share / dt * (depth - slop), rel=1e-5)
    assert _disc_in_the_floor_first_step_speed("kforge", depth) < 0.95 * share / dt * (depth - slop)
