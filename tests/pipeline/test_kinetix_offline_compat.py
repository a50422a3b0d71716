"""Slow: Kinetix's own code (kinetix-env 3.0.2 from PyPI, in its own virtualenv) reads a `kforge export`, renders it,
and writes a shard our importer reads back.

The virtualenv is the one `benchmarks/kinetix_venv.py` builds (`.venv-kinetix`, built on first use: a few minutes
and network access to PyPI); set KFORGE_KINETIX_VENV to an existing one to skip that, e.g.

    KFORGE_KINETIX_VENV=path/to/kinetix-venv python -m pytest tests/pipeline/test_kinetix_offline_compat.py -m slow -q

The checks themselves run in `kinetix_offline_check.py` (see its docstring); our dataset's values reach it as an npz
file in our field names.
"""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import jax
import numpy as np
import pytest

from benchmarks.kinetix_venv import DEFAULT_KINETIX_VENV, kinetix_python
from kforge.env import bundled_level_path, initial_state, list_levels, load_level
from kforge.pipeline.kinetix.export import export_kinetix, kept_trajectories
from kforge.pipeline.kinetix.importer import load_kinetix_levels
from kforge.pipeline.reading.loader import TrajectoryDatasetManager
from kforge.pipeline.storage.layout import ACTION, ACTION_MASK, DONE, STATE_PREFIX, flatten_state

KINETIX_VENV_VARIABLE = "KFORGE_KINETIX_VENV"
"""Environment variable naming an existing virtualenv with kinetix-env 3.0.2 (default: build `.venv-kinetix`)."""

SCRIPT = Path(__file__).with_name("kinetix_offline_check.py")
SCRIPT_TIMEOUT = 1800  # [s] Kinetix compiles its renderer and env step on a 2-core CPU: a few minutes
SIZE_S_LEVELS = [bundled_level_path(name) for name in list_levels("s")]
"""Kinetix's hand-designed size-s level files, bundled with `env`."""

ROLLOUT_SLOTS = (0, 1)  # dataset slots 0 and 1 hold rollout levels 0 and 1 (conftest)
EXPECTED_FIELDS = 85  # action, action_mask, done and the 82 EnvState leaves (docs/kinetix.md, offline dataset format)
NUM_RENDERS = 3


def _expected_file(dataset_dir, path: Path) -> None:
    """Our trajectories of rollout levels 0 and 1 in our field names, and each kept level id's rollout level."""
    batch = TrajectoryDatasetManager(dataset_dir, batch_size=1).load_slots(np.asarray(ROLLOUT_SLOTS))
    state_prefix = f"{STATE_PREFIX}/"
    arrays = {
        name.removeprefix(state_prefix).removeprefix("sim/"): np.asarray(value)
        for name, value in flatten_state(batch.env_state).items()
    }
    arrays |= {
        ACTION: np.asarray(batch.action),
        ACTION_MASK: np.asarray(batch.action_mask),
        DONE: np.asarray(batch.done),
    }
    ids = [trajectory.level_id for trajectory in kept_trajectories(dataset_dir)]
    np.savez(path, level_ids=np.asarray(ids), level_index=np.asarray(ids) % 10, **arrays)


@pytest.mark.slow
def test_kinetix_reads_our_export_and_we_read_kinetix_shards(dataset_dir, tmp_path):
    python = kinetix_python(Path(os.environ.get(KINETIX_VENV_VARIABLE, DEFAULT_KINETIX_VENV)), print)
    summary = export_kinetix(dataset_dir, tmp_path / "export", seed=0, trajectories_per_shard=3, show_progress=False)
    _expected_file(dataset_dir, tmp_path / "expected.npz")
    level_files = SIZE_S_LEVELS
    environment = {name: value for name, value in os.environ.items() if name != "PYTHONPATH"}
    command = [str(python), str(SCRIPT), "--export", str(summary.group), "--expected", str(tmp_path / "expected.npz")]
    command += ["--images", str(tmp_path / "images"), "--write-shard", str(tmp_path / "kinetix")]
    command += ["--levels", *map(str, level_files)]
    result = subprocess.run(command, capture_output=True, text=True, timeout=SCRIPT_TIMEOUT, env=environment)
    assert result.returncode == 0, f"{result.stdout[-3000:]}\n{result.stderr[-3000:]}"
    report = json.loads(result.stdout.strip().splitlines()[-1])
    assert report["fields"] == EXPECTED_FIELDS
    assert report["rows"] == report["loaded"] == summary.num_trajectories
    assert len(report["renders"]) == NUM_RENDERS and all(r["distinct_colours"] >= 4 for r in report["renders"])
    assert len(list((tmp_path / "images").glob("*.png"))) == NUM_RENDERS

    imported = load_kinetix_levels(tmp_path / "kinetix")
    assert imported.static.sim.num_polygons == 5 and imported.static.frame_skip == 2
    for row, path in enumerate(level_files):
        level = load_level(path).level
        for got_tree, want_tree in ((imported.levels, level), (imported.initial_states, initial_state(level))):
            got = jax.tree.map(lambda x, r=row: np.asarray(x[r]), got_tree)
            for (key, a), b in zip(
                jax.tree_util.tree_flatten_with_path(got)[0], jax.tree.leaves(want_tree), strict=True
            ):
                np.testing.assert_array_equal(a, np.asarray(b), err_msg=f"{path.stem}{jax.tree_util.keystr(key)}")
