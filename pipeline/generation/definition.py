"""The data definition of a job, what makes its dataset's content, and the fingerprint that identifies it."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math

from kforge.env import DISC_INERTIA_SHARE
from kforge.pipeline.generation.resolved import ResolvedJob
from kforge.pipeline.generation.schema import FIXED_BUDGET_MODE

DATA_SECTIONS = ("split", "work", "filter", "env", "ppo", "experts", "collect")
"""Config sections that determine the dataset's content; a resumed job must agree on all of them."""


def data_definition(job: ResolvedJob) -> dict:
    """What defines the dataset's content, as JSON values: the config's data sections (`experts` only where a budget
    mode reads it); the physics the levels play under: the scheme's name, every engine parameter of a step and
    every solver setting; and what the level sampler sets that no config does (a disc's inertia). The last two are
    set by the code, not the config, so that data made by code with other physics or levels is told apart."""
    config = job.config
    sections = [name for name in DATA_SECTIONS if name != "experts" or config.experts.budget_mode != FIXED_BUDGET_MODE]
    data = {section: dataclasses.asdict(getattr(config, section)) for section in sections}
    physics = physics_definition(config.env.physics, job.env_params.sim, job.static.sim)
    return data | {"physics": physics, "levels": {"disc_inertia_share": DISC_INERTIA_SHARE}}


def physics_definition(scheme: str, sim, static_sim) -> dict:
    """The physics entry of the data definition: `{"scheme": scheme, **every field of sim (engine.SimParams),
    **static_sim.physics_options() (engine.StaticSimParams)}`, as JSON values (`json_value`)."""
    fields = {"scheme": scheme, **dataclasses.asdict(sim), **static_sim.physics_options()}
    return {key: json_value(value) for key, value in fields.items()}


NON_FINITE_FLOATS = {math.inf: "inf", -math.inf: "-inf"}
"""How infinite parameters are written in a data definition (JSON has no infinity)."""


def json_value(value):
    """A parameter as a plain JSON value: enums as their ints, infinite floats as "inf" / "-inf"; NaN is refused."""
    if isinstance(value, bool) or isinstance(value, str):
        return value
    if isinstance(value, int):
        return int(value)
    value = float(value)
    if math.isnan(value):
        raise ValueError("a physics parameter is NaN; a data definition holds numbers only")
    return NON_FINITE_FLOATS.get(value, value)


GROWABLE_KEY = ("split", "num_levels")
"""The one data-defining key a dataset may change after it is made: raising it appends levels (level i is the same
level whatever the count), so the data fingerprint leaves it out."""


def data_fingerprint(job: ResolvedJob) -> str:
    """Hash of `data_definition` without `split.num_levels`: equal fingerprints mean that level i's data is the same
    in both datasets, whatever their level counts."""
    return definition_fingerprint(data_definition(job))


def definition_fingerprint(definition: dict) -> str:
    """The data fingerprint of a stored `data_definition` (`data_config` among a dataset's attributes)."""
    section, key = GROWABLE_KEY
    countless = definition | {section: {k: v for k, v in definition.get(section, {}).items() if k != key}}
    return hashlib.sha256(json.dumps(countless, sort_keys=True, allow_nan=False).encode()).hexdigest()[:16]
