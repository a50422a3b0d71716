"""Loading, checking and printing a job config import neither JAX nor Ray nor wandb, so a config error is answered
at once; the names the config checks without the engine agree with the engine's."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys

from kforge.engine import KINETIX_SIZES, PHYSICS_SCHEMES
from kforge.pipeline.generation.schema import ENV_SIZES, PHYSICS_SCHEME_NAMES, LeaseConfig
from kforge.pipeline.generation.sources import DATASET_CONFIG_FILE
from kforge.pipeline.storage import CONFIG_FILE
from kforge.pipeline.storage.lease import DEFAULT_HEARTBEAT_S, DEFAULT_STALE_AFTER_S

HEAVY_MODULES = ("jax", "ray", "wandb", "flax", "optax")

CHECK_WITHOUT_HEAVY_MODULES = f"""
import json, sys
from kforge.pipeline.generation import ConfigError, load_config, to_yaml
from kforge.pipeline.generation.loading import read_config
errors = []
for overrides in (["split.size=xl"], ["env.dense_reward_scale=nan"], ["lease.stale_after_s=inf"]):
    try:
        load_config("1M/s", overrides, scale="tiny")
    except ConfigError as error:
        errors.append(str(error))
printed = to_yaml(read_config("1M/s", [], scale="tiny"))
print(json.dumps({{"errors": errors, "printed": "physics: kinetix" in printed,
                  "loaded": [name for name in {HEAVY_MODULES!r} if name in sys.modules]}}))
"""


def test_a_bad_config_is_refused_and_a_good_one_printed_without_importing_jax_ray_or_wandb():
    finished = subprocess.run(
        [sys.executable, "-c", CHECK_WITHOUT_HEAVY_MODULES], capture_output=True, text=True, timeout=60, check=True
    )
    result = json.loads(finished.stdout)
    assert result["loaded"] == []
    assert result["errors"] == [
        "split.size must be one of ['s', 'm', 'l'], got 'xl'",
        "env.dense_reward_scale must be a finite number, got nan",
        "lease.stale_after_s must be a finite number, got inf",
    ]
    assert result["printed"] is True


def test_the_names_checked_without_the_engine_are_the_engines():
    assert PHYSICS_SCHEME_NAMES == tuple(PHYSICS_SCHEMES)
    assert ENV_SIZES == tuple(KINETIX_SIZES)
    assert DATASET_CONFIG_FILE == CONFIG_FILE
    assert dataclasses.asdict(LeaseConfig()) == {
        "stale_after_s": DEFAULT_STALE_AFTER_S,
        "heartbeat_s": DEFAULT_HEARTBEAT_S,
    }
