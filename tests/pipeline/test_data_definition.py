"""The physics part of a dataset's data definition: parameters added to the engine later, at the value that plays
as the engine did before them, leave the fingerprint of existing datasets unchanged."""

import math

from engine import LimitLaw, SimParams
from pipeline.generation.config import data_definition, data_fingerprint, load_config, physics_definition

FINGERPRINTS_BEFORE_THE_SWITCHES = {"1M/s": "91cabbbb5c0c5e7a", "10M/l": "6b388df577c00203"}
"""`data_fingerprint` of each split's default job, as the code before the limit-law and speculative-margin switches
computed it (commit a0538b2)."""


def test_default_jobs_keep_the_fingerprints_they_had_before_the_physics_switches(tmp_path):
    for split, fingerprint in FINGERPRINTS_BEFORE_THE_SWITCHES.items():
        job = load_config(None, [f"split.name={split}", f"output_dir={tmp_path}"])
        assert data_fingerprint(job) == fingerprint
        physics = data_definition(job)["physics"]
        assert not {"limit_law", "limit_recovery_rate", "speculative_reach", "push_touch_distance"} & set(physics)
        assert physics["joint_hertz"] == 75.0  # the older parameters are all there


def test_a_later_parameter_at_another_value_enters_the_definition():
    assert physics_definition(SimParams(limit_law=LimitLaw.BOUNDED_RETURN))["limit_law"] == LimitLaw.BOUNDED_RETURN
    assert physics_definition(SimParams(speculative_reach=0.0))["speculative_reach"] == 0.0
    assert physics_definition(SimParams(push_touch_distance=0.02))["push_touch_distance"] == 0.02
    assert "push_touch_distance" not in physics_definition(SimParams(push_touch_distance=math.inf))
