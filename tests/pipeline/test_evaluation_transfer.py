"""The transfer adapter: Kinetix's entity observation of a level, recorded from kinetix-env 3.0.2 into a fixture,
mapped to the BC network's input, equals kforge's observation of the same level field by field.

The fixture is made in the Kinetix virtualenv by
`python -m benchmarks.kinetix_transfer_player --record-observation s/h3_point_the_thruster m/h1_car_left
--out tests/pipeline/data/kinetix_entity_observations.json` (benchmarks/kinetix_transfer.py builds that virtualenv).
"""

import json
from pathlib import Path
from types import SimpleNamespace

import jax
import numpy as np
import pytest

from benchmarks.kinetix_transfer_player import ENTITY_FIELDS, from_kinetix_observation
from kforge.engine import physics_scheme
from kforge.env import EnvParams, ObservationType, StaticEnvParams, load_level, observe, reset, under_scheme

FIXTURE = Path(__file__).parent / "data" / "kinetix_entity_observations.json"
LEVELS = ("s/h3_point_the_thruster", "m/h1_car_left")
"""A thruster on a jointed arm (every slot of size s active); a car of size m (two joints; no thruster active)."""
TOLERANCE = 1e-5
"""Features compared to float32 rounding: both engines load the same level file into float32 states."""


def recorded(name: str) -> tuple[str, SimpleNamespace]:
    entry = json.loads(FIXTURE.read_text())["levels"][name]
    return entry["size"], SimpleNamespace(**{field: np.asarray(v) for field, v in entry["observation"].items()})


def ours(name: str, size: str):
    static = under_scheme(physics_scheme("kinetix"), EnvParams(), StaticEnvParams.for_size(size))[1]
    return observe(reset(load_level(name).level), static, ObservationType.SYMBOLIC_ENTITY)


@pytest.mark.parametrize("name", LEVELS)
def test_kinetix_entity_observation_maps_to_ours_field_by_field(name):
    size, kinetix = recorded(name)
    mapped, expected = from_kinetix_observation(kinetix), ours(name, size)
    assert set(ENTITY_FIELDS) == set(vars(kinetix))
    for field in ENTITY_FIELDS:
        got, want = np.asarray(getattr(mapped, field)), np.asarray(getattr(expected, field))
        assert got.shape == want.shape and got.dtype == want.dtype, field
        np.testing.assert_allclose(got, want, atol=TOLERANCE, rtol=0, err_msg=field)


def test_inactive_entities_read_as_kforge_zeroes_them():
    """Kinetix leaves inactive rows raw behind its masks; mapped, they are zero as in kforge's observation."""
    _, kinetix = recorded("m/h1_car_left")
    mapped = from_kinetix_observation(kinetix)
    inactive = ~kinetix.thruster_mask.astype(bool)  # the car has no thruster
    assert inactive.all() and np.abs(kinetix.thrusters[inactive]).sum() > 0
    assert np.all(np.asarray(mapped.thrusters) == 0)
    assert jax.tree.structure(mapped) == jax.tree.structure(ours("m/h1_car_left", "m"))
