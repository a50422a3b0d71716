"""XLA's deterministic GPU ops: the flag joins XLA_FLAGS without disturbing other flags, and the pinned XLA accepts
it (an unknown flag aborts the process at the first computation)."""

import os
import subprocess
import sys

from kforge.engine import use_deterministic_ops
from kforge.engine.determinism import DETERMINISTIC_GPU_OPS_FLAG, XLA_FLAGS_ENV, with_deterministic_ops

HOST_DEVICES_FLAG = "--xla_force_host_platform_device_count=2"


def test_the_flag_joins_empty_and_existing_flags_once():
    assert with_deterministic_ops("") == "--xla_gpu_deterministic_ops=true"
    both = with_deterministic_ops(HOST_DEVICES_FLAG)
    assert both.split() == [HOST_DEVICES_FLAG, "--xla_gpu_deterministic_ops=true"]
    assert with_deterministic_ops(both) == both


def test_a_users_own_setting_of_the_flag_stands():
    own = f"{HOST_DEVICES_FLAG} --xla_gpu_deterministic_ops=false"
    assert with_deterministic_ops(own) == own


def test_use_sets_the_process_environment(monkeypatch):
    monkeypatch.setenv(XLA_FLAGS_ENV, HOST_DEVICES_FLAG)
    use_deterministic_ops()
    assert os.environ[XLA_FLAGS_ENV].split() == [HOST_DEVICES_FLAG, DETERMINISTIC_GPU_OPS_FLAG]


def test_xla_accepts_the_flag_and_keeps_the_others():
    program = (
        "from engine import use_deterministic_ops\n"
        "use_deterministic_ops()\n"
        "import jax, jax.numpy as jnp\n"
        "print(jax.device_count(), float(jnp.arange(4.0).sum()))\n"
    )
    environment = {**os.environ, XLA_FLAGS_ENV: HOST_DEVICES_FLAG, "JAX_PLATFORMS": "cpu"}
    finished = subprocess.run(
        [sys.executable, "-c", program], env=environment, capture_output=True, text=True, timeout=120
    )
    assert finished.returncode == 0, finished.stderr[-2000:]
    assert finished.stdout.split() == ["2", "6.0"]
