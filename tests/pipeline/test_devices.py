"""A worker with several local devices spreads its level batch over them and trains the same experts."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from pipeline_test_helpers import TINY_JOB

from kforge.pipeline.generation import load_config, resolve
from kforge.pipeline.generation.level_batch import run_level_batch

REPO_ROOT = Path(__file__).resolve().parents[2]
DEVICES = 2

RUN_ON_DEVICES = """
import json, sys
import jax, numpy as np
from kforge.pipeline.generation import load_config, resolve
from kforge.pipeline.generation.devices import level_devices
from kforge.pipeline.generation.level_batch import run_level_batch

overrides, out = json.loads(sys.argv[1]), sys.argv[2]
job = load_config(None, overrides)
result = run_level_batch(resolve(job), 0, 0)
np.savez(out, devices=len(jax.local_devices()), spread=level_devices(job.work.levels_per_batch),
         action=result.action, success_rate=result.curves.success_rate, mean_return=result.curves.mean_return,
         expert_success_rate=result.expert_success_rate, position=np.asarray(result.states.sim.bodies.position))
"""


def _figures(result):
    return {
        "action": result.action,
        "success_rate": result.curves.success_rate,
        "mean_return": result.curves.mean_return,
        "expert_success_rate": result.expert_success_rate,
        "position": np.asarray(result.states.sim.bodies.position),
    }


@pytest.mark.slow  # two compiles of training (one per device count): minutes on 2 cores
def test_two_devices_train_the_same_experts_as_one(tmp_path):
    overrides = [f"output_dir={tmp_path / 'unused'}", *TINY_JOB]
    out = tmp_path / "two_devices.npz"
    env = dict(os.environ, XLA_FLAGS=f"--xla_force_host_platform_device_count={DEVICES}", JAX_PLATFORMS="cpu")
    subprocess.run(
        [sys.executable, "-c", RUN_ON_DEVICES, json.dumps(overrides), str(out)], cwd=REPO_ROOT, env=env, check=True
    )
    spread = np.load(out)
    assert int(spread["devices"]) == DEVICES and int(spread["spread"]) == DEVICES
    alone = _figures(run_level_batch(resolve(load_config(None, overrides)), 0, 0))
    np.testing.assert_array_equal(spread["action"], alone["action"])
    for name in ("success_rate", "mean_return", "expert_success_rate", "position"):
        np.testing.assert_allclose(spread[name], alone[name], rtol=1e-4, atol=1e-5, err_msg=name)
