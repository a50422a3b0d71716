"""A dataset's data definition: the config's data sections and the physics its levels play under, the scheme named
and every parameter held, as plain JSON; its fingerprint; and the format version that refuses older datasets."""

import dataclasses
import hashlib
import json

import pytest

from kforge.engine import SimParams, StaticSimParams
from kforge.pipeline.generation import ConfigError, load_config, resolve
from kforge.pipeline.generation.definition import (
    data_definition,
    data_fingerprint,
    definition_fingerprint,
    physics_definition,
)
from kforge.pipeline.generation.run import prepare_output
from kforge.pipeline.storage import DatasetError
from kforge.pipeline.storage.shard_store import open_dataset

SPLIT_1M_S = ["split.name=1M/s"]

KINETIX_SCHEME_SETTINGS = {
    "scheme": "kinetix",
    "num_substeps": 1,
    "num_iterations": 10,
    "num_relax_iterations": 0,
    "contact_law": 1,
    "force_timing": 1,
    "speculative_distance": 0.0,
    "speculative_reach": 0.0,
    "contact_points": 1,
    "collision_rules": 1,
    "joint_law": 1,
    "contact_order": 1,
}
"""What `engine.PHYSICS_SCHEMES["kinetix"]` sets (BAUMGARTE, STEP_START, KINETIX, JAX2D, JAX2D, JAX2D as ints)."""

KFORGE_SCHEME_SETTINGS = {
    "scheme": "kforge",
    "num_substeps": 4,
    "num_iterations": 1,
    "num_relax_iterations": 1,
    "contact_law": 0,
    "force_timing": 0,
    "speculative_distance": 0.02,
    "speculative_reach": 1.0,
    "contact_points": 0,
    "collision_rules": 0,
    "joint_law": 0,
    "contact_order": 0,
}
"""The engine's defaults, which the kforge scheme keeps."""


RELEASE_FINGERPRINTS = {
    ("1M/s", None): "ac3e514e015abb10",
    ("1M/s", "tiny"): "96fa6d0255def3cf",
    ("1M/m", None): "aa3d22860a839668",
    ("1M/m", "tiny"): "f79ba473294f5a47",
    ("1M/l", None): "4df1a3b578a4da8b",
    ("1M/l", "tiny"): "6ee9688ce52134d0",
    ("10M/s", None): "b736c1b719429be7",
    ("10M/s", "tiny"): "e58fc44983a10db0",
    ("10M/m", None): "09de0db8038ff3f3",
    ("10M/m", "tiny"): "a99d09d77818d023",
}
"""The data fingerprint of each release split as released and at the tiny scale: a change to the code that moves
one makes other data under the same config (a new format version, not a refactoring)."""

STREAMED_FINGERPRINTS = {"streamed": "961dcd3e9b5e801c", "adaptive": "0e7a8646cff3facf"}
"""1M/s at the tiny scale under the budget modes that read the experts section."""


def job_of(tmp_path, *overrides):
    return resolve(load_config(None, [*SPLIT_1M_S, f"output_dir={tmp_path}", *overrides]))


def test_a_job_plays_under_the_kinetix_scheme_and_its_definition_names_it_with_its_parameters(tmp_path):
    physics = data_definition(job_of(tmp_path))["physics"]
    assert {key: physics[key] for key in KINETIX_SCHEME_SETTINGS} == KINETIX_SCHEME_SETTINGS
    assert (physics["joint_hertz"], physics["base_friction"], physics["dt"]) == (75.0, 0.4, 1 / 60)  # kept


def test_the_definition_names_the_inertia_the_sampler_gives_a_disc(tmp_path):
    """Kinetix's sampler stores a disc's inertia as m r^2 / 4; ours does the same, and says so in the definition."""
    assert data_definition(job_of(tmp_path))["levels"] == {"disc_inertia_share": 0.25}


def test_the_kforge_scheme_stays_available_and_is_its_own_data(tmp_path):
    kforge, kinetix = job_of(tmp_path, "env.physics=kforge"), job_of(tmp_path)
    physics = data_definition(kforge)["physics"]
    assert {key: physics[key] for key in KFORGE_SCHEME_SETTINGS} == KFORGE_SCHEME_SETTINGS
    assert data_fingerprint(kforge) != data_fingerprint(kinetix)
    assert data_definition(kforge)["env"] == {"dense_reward_scale": 0.2, "physics": "kforge"}


def test_the_physics_entry_holds_every_engine_parameter_and_solver_setting_but_the_sizes(tmp_path):
    physics = data_definition(job_of(tmp_path))["physics"]
    sim_fields = {field.name for field in dataclasses.fields(SimParams)}
    solver_fields = {field.name for field in dataclasses.fields(StaticSimParams)}
    sizes = {"num_polygons", "num_circles", "num_joints", "num_thrusters", "num_reserved_static"}
    assert sim_fields <= set(physics) and not sizes & set(physics)
    assert set(StaticSimParams().physics_options()) <= set(physics) <= sim_fields | solver_fields | {"scheme"}


def test_the_definition_is_plain_json_with_infinity_written_as_a_string_and_laws_as_ints(tmp_path):
    definition = data_definition(job_of(tmp_path))
    text = json.dumps(definition, allow_nan=False)  # raises on a float JSON cannot hold
    assert json.loads(text) == definition
    physics = definition["physics"]
    assert physics["baumgarte_depth"] == "inf" and physics["push_touch_distance"] == "inf"
    assert type(physics["contact_law"]) is int and type(physics["block_contacts"]) is bool
    assert "Infinity" not in text and "NaN" not in text


def test_a_physics_parameter_that_is_nan_has_no_definition_and_minus_infinity_is_written_out():
    with pytest.raises(ValueError, match="^a physics parameter is NaN"):
        physics_definition("kforge", SimParams(joint_hertz=float("nan")), StaticSimParams())
    physics = physics_definition("kforge", SimParams(baumgarte_depth=-float("inf")), StaticSimParams())
    assert physics["baumgarte_depth"] == "-inf"


def test_the_fingerprint_is_the_hash_of_the_sorted_json_without_the_level_count():
    definition = {"split": {"seed": 1, "num_levels": 3}, "physics": {"scheme": "kinetix", "dt": 0.5}}
    written_out = b'{"physics": {"dt": 0.5, "scheme": "kinetix"}, "split": {"seed": 1}}'
    assert definition_fingerprint(definition) == hashlib.sha256(written_out).hexdigest()[:16]


def test_every_key_of_the_experts_section_defines_streamed_and_adaptive_data_and_none_fixed(tmp_path):
    def fingerprint(*overrides):
        return data_fingerprint(job_of(tmp_path, *overrides))

    assert "experts" not in data_definition(job_of(tmp_path))
    assert fingerprint("experts.solved_window=false") == fingerprint()  # fixed budgets read no experts key
    for mode in ("streamed", "adaptive"):
        experts = data_definition(job_of(tmp_path, f"experts.budget_mode={mode}"))["experts"]
        assert experts == {
            "budget_mode": mode,
            "solved_evaluations": 2,
            "solved_window": True,
            "give_up_env_steps": 250_000,
        }
    adaptive = "experts.budget_mode=adaptive"
    assert fingerprint(adaptive, "experts.solved_window=false") != fingerprint(adaptive)


@pytest.mark.parametrize(("split", "scale"), sorted(RELEASE_FINGERPRINTS, key=str))
def test_the_fingerprint_of_every_release_split_is_unchanged(split, scale):
    assert data_fingerprint(resolve(load_config(split, scale=scale))) == RELEASE_FINGERPRINTS[split, scale]


def test_the_fingerprints_of_the_streamed_and_adaptive_modes_are_unchanged():
    for mode, fingerprint in STREAMED_FINGERPRINTS.items():
        job = load_config("1M/s", [f"experts.budget_mode={mode}"], scale="tiny")
        assert data_fingerprint(resolve(job)) == fingerprint


def test_an_unknown_physics_scheme_is_refused_in_one_line(tmp_path):
    with pytest.raises(ConfigError, match=r"^env.physics must be one of kforge, kinetix, got 'jax2d'$"):
        job_of(tmp_path, "env.physics=jax2d")


def test_a_dataset_of_an_older_format_version_is_refused_naming_both_versions(tmp_path):
    prepare_output(job_of(tmp_path, "split.num_levels=2", "work.levels_per_shard=2", "work.levels_per_batch=2"))
    group_path = tmp_path / "data" / "zarr.json"
    group = json.loads(group_path.read_text())
    assert group["attributes"]["kforge_dataset"]["format_version"] == 3
    group["attributes"]["kforge_dataset"]["format_version"] = 2
    group_path.write_text(json.dumps(group))
    with pytest.raises(DatasetError, match=r"^\S+: dataset format version 2; this code reads version 3$"):
        open_dataset(tmp_path)
