"""The physics part of a dataset's data definition: parameters added to the engine later, at the value that plays
as the engine did before them, leave the fingerprint of existing datasets unchanged; so do keys added later to the
experts section."""

import math

import pytest

from engine import ContactLaw, ContactPoints, LimitLaw, SimParams, StaticSimParams
from pipeline.generation.config import (
    ConfigError,
    data_definition,
    data_fingerprint,
    definition_fingerprint,
    environment,
    load_config,
    physics_definition,
)

FINGERPRINTS_BEFORE_THE_SWITCHES = {"1M/s": "91cabbbb5c0c5e7a", "10M/l": "6b388df577c00203"}
"""`data_fingerprint` of each split's default job, as the code before the limit-law and speculative-margin switches
computed it (commit a0538b2). Its physics is today's engine with `swept_speculative_contacts=False`."""


def test_the_physics_from_before_the_switches_keeps_its_fingerprint(tmp_path):
    """Datasets made before the switches keep their fingerprint under the physics they were made with; today's
    default (circles' contacts followed through the step) plays differently, so its datasets are told apart."""
    for split, fingerprint in FINGERPRINTS_BEFORE_THE_SWITCHES.items():
        job = load_config(None, [f"split.name={split}", f"output_dir={tmp_path}"])
        earlier_sim = environment(job)[0].sim.replace(swept_speculative_contacts=False)
        earlier_physics = physics_definition(earlier_sim)
        assert definition_fingerprint(data_definition(job) | {"physics": earlier_physics}) == fingerprint
        later = {"limit_law", "limit_recovery_rate", "speculative_reach", "push_touch_distance"}
        later |= {"swept_speculative_contacts", "overlap_allowance", "contact_law", "baumgarte_share", "contact_slop"}
        later |= {"baumgarte_depth", "contact_points", "collision_rules"}
        assert not later & set(earlier_physics)
        assert earlier_physics["joint_hertz"] == 75.0  # the older parameters are all there
        assert data_definition(job)["physics"]["swept_speculative_contacts"] is True
        assert data_fingerprint(job) != fingerprint


def test_a_later_parameter_at_another_value_enters_the_definition():
    assert physics_definition(SimParams(limit_law=LimitLaw.BOUNDED_RETURN))["limit_law"] == LimitLaw.BOUNDED_RETURN
    assert physics_definition(SimParams(speculative_reach=0.0))["speculative_reach"] == 0.0
    assert physics_definition(SimParams(overlap_allowance=1.0))["overlap_allowance"] == 1.0
    assert physics_definition(SimParams(contact_law=ContactLaw.BAUMGARTE))["contact_law"] == ContactLaw.BAUMGARTE
    assert physics_definition(SimParams(contact_slop=0.005))["contact_slop"] == 0.005
    assert physics_definition(SimParams(push_touch_distance=0.02))["push_touch_distance"] == 0.02
    assert "push_touch_distance" not in physics_definition(SimParams(push_touch_distance=math.inf))
    assert physics_definition(SimParams(baumgarte_depth=0.05))["baumgarte_depth"] == 0.05
    assert "baumgarte_depth" not in physics_definition(SimParams())
    assert (
        physics_definition(SimParams(contact_points=ContactPoints.KINETIX))["contact_points"] == ContactPoints.KINETIX
    )
    assert "contact_points" not in physics_definition(SimParams())
    assert physics_definition(SimParams())["swept_speculative_contacts"] is True


def test_a_solver_scheme_other_than_the_first_enters_the_definition_and_the_default_stays_out(tmp_path):
    """The solver's counts were not in the definition when the first datasets were made (4 substeps, one pass each
    way): at those counts they stay out, so those datasets keep their fingerprint; Jax2D's scheme (one substep of 10
    passes, none relaxing) is told apart."""
    jax2d_scheme = StaticSimParams(num_substeps=1, num_iterations=10, num_relax_iterations=0)
    physics = physics_definition(SimParams(), jax2d_scheme)
    assert (physics["num_substeps"], physics["num_iterations"], physics["num_relax_iterations"]) == (1, 10, 0)
    assert physics_definition(SimParams(), StaticSimParams(num_iterations=2)) == physics_definition(SimParams()) | {
        "num_iterations": 2
    }
    assert physics_definition(SimParams(), StaticSimParams(block_contacts=True))["block_contacts"] is True
    assert physics_definition(SimParams(), StaticSimParams(relax_contacts=False))["relax_contacts"] is False
    assert physics_definition(SimParams(), StaticSimParams()) == physics_definition(SimParams())
    job = load_config(None, ["split.name=1M/s", f"output_dir={tmp_path}"])
    scheme = {"num_substeps", "num_iterations", "num_relax_iterations", "block_contacts", "relax_contacts"}
    assert not scheme & set(data_definition(job)["physics"])


FINGERPRINTS_BEFORE_THE_WINDOW_CHECK = {"adaptive": "09ceea303481daee", "streamed": "4dbb4cb51ffac5b4"}
"""`data_fingerprint` of split 1M/s's default job in each streaming budget mode, as the code before
`experts.solved_window` computed it (commit 84f6cd3)."""


def test_the_window_check_leaves_streamed_and_earlier_adaptive_datasets_their_fingerprint(tmp_path):
    def fingerprint(*overrides):
        return data_fingerprint(load_config(None, ["split.name=1M/s", f"output_dir={tmp_path}", *overrides]))

    streamed = FINGERPRINTS_BEFORE_THE_WINDOW_CHECK["streamed"]
    assert fingerprint("experts.budget_mode=streamed") == streamed  # the check plays no part there
    assert fingerprint("experts.budget_mode=streamed", "experts.solved_window=false") == streamed
    earlier_adaptive = FINGERPRINTS_BEFORE_THE_WINDOW_CHECK["adaptive"]
    assert fingerprint("experts.budget_mode=adaptive", "experts.solved_window=false") == earlier_adaptive
    assert fingerprint("experts.budget_mode=adaptive") != earlier_adaptive  # the check changes which levels stop


FINGERPRINTS_BEFORE_PHYSICS_SCHEMES = {"1M/s": "196ec675e952d03c", "10M/l": "b4d8d39441477de0"}
"""`data_fingerprint` of each split's default job as the code before `env.physics` computed it (commit 5548280)."""


def test_the_physics_scheme_enters_the_definition_by_its_parameters_and_the_default_keeps_fingerprints(tmp_path):
    """`env.physics` names a scheme; what enters the data definition is what the scheme sets (in `physics`), so
    datasets made before the key keep their fingerprint, whether the default is named or not, and "kinetix" data is
    told apart."""
    for split, fingerprint in FINGERPRINTS_BEFORE_PHYSICS_SCHEMES.items():
        base = [f"split.name={split}", f"output_dir={tmp_path}"]
        assert data_fingerprint(load_config(None, base)) == fingerprint
        assert data_fingerprint(load_config(None, [*base, "env.physics=kforge"])) == fingerprint
        kinetix = load_config(None, [*base, "env.physics=kinetix"])
        assert data_fingerprint(kinetix) != fingerprint
        definition = data_definition(kinetix)
        assert definition["env"] == {"dense_reward_scale": 0.2}
        scheme = {
            "num_substeps": 1,
            "num_iterations": 10,
            "num_relax_iterations": 0,
            "contact_law": 1,
            "force_timing": 1,
            "speculative_distance": 0.0,
            "overlap_allowance": 2.0,
            "contact_points": 1,
            "collision_rules": 1,
            "limit_law": 2,
        }
        assert {key: definition["physics"][key] for key in scheme} == scheme
        params, static = environment(kinetix)
        assert (static.sim.num_substeps, static.sim.num_iterations, static.sim.num_relax_iterations) == (1, 10, 0)
        assert (kinetix.split.size, static.sim.num_polygons, params.dense_reward_scale) == ("s", 5, 0.2)  # kept


def test_an_unknown_physics_scheme_is_refused_in_one_line(tmp_path):
    with pytest.raises(ConfigError, match=r"^env.physics must be one of kforge, kinetix, got 'jax2d'$"):
        load_config(None, ["split.name=1M/s", f"output_dir={tmp_path}", "env.physics=jax2d"])
