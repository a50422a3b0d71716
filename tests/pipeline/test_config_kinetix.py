"""Everything that stands for Kinetix plays under the kinetix physics scheme: every release split at every scale, and
the quickstart's job as the command line resolves it."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from kforge import configs
from kforge.pipeline.generation import load_config

pytestmark = pytest.mark.smoke

REPOSITORY = Path(__file__).resolve().parents[2]
QUICKSTART = ["run", "1M/s", "--scale", "tiny"]
"""The README quickstart's `kforge run 1M/s --scale tiny`."""


def test_every_split_at_every_scale_plays_under_the_kinetix_scheme():
    assert len(configs.split_names()) == 5 and len(configs.scale_names()) == 4
    for split in configs.split_names():
        for scale in configs.scale_names():
            assert load_config(split, scale=scale).env.physics == "kinetix", (split, scale)


def test_the_quickstart_job_plays_under_the_kinetix_scheme(tmp_path):
    command = [sys.executable, "-m", "kforge", *QUICKSTART, "--print-config"]
    printed = subprocess.run(command, capture_output=True, text=True, cwd=tmp_path, timeout=120, check=True)
    config = yaml.safe_load(printed.stdout)
    assert config["env"]["physics"] == "kinetix"
    assert (config["split"]["name"], config["scale"], config["output_dir"]) == ("1M/s", "tiny", "outputs/1M-s-tiny")
