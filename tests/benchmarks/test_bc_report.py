"""The proof-of-use report names the dataset and the work directory, not their paths on the machine that made it."""

import argparse
import json
from pathlib import Path

from benchmarks.bc import without_machine_paths
from benchmarks.kinetix_venv import REPOSITORY


def test_report_paths_of_this_machine_become_names(tmp_path):
    work_dir, dataset = tmp_path / "work", tmp_path / "data" / "1M-s"
    args = argparse.Namespace(work_dir=work_dir, dataset=str(dataset))
    level = str(REPOSITORY / "env" / "levels" / "s" / "h0_weak_thrust.json")
    text = json.dumps(
        {"run_dir": str(work_dir / "bc-16-levels"), "dataset": str(dataset), "other": "/elsewhere", level: 1}
    )
    scrubbed = json.loads(without_machine_paths(text, args))
    assert scrubbed == {
        "run_dir": "WORK_DIR/bc-16-levels",
        "dataset": "DATASET",
        "other": "/elsewhere",
        "env/levels/s/h0_weak_thrust.json": 1,
    }
    assert str(tmp_path) not in without_machine_paths(text, args)
    assert Path(scrubbed["run_dir"]).parts[0] == "WORK_DIR"
