"""The proof-of-use report's budget rule and its machine-free paths."""

import argparse
import json
from pathlib import Path

from benchmarks.bc import budget, without_machine_paths


def test_the_budget_rule_validates_every_five_passes_and_caps_the_passes():
    # 512 levels: 52 held out (10 %, rounded up), 460 trained on in batches of 32 -> 14.375 steps per pass
    assert budget(512, epochs=200, batch_size=32) == {"batch_size": 32, "num_steps": 2875, "validate_every_steps": 72}
    # 16 levels: 2 held out, 14 trajectories -> one batch of 14 per pass
    assert budget(16, epochs=200, batch_size=32) == {"batch_size": 14, "num_steps": 200, "validate_every_steps": 5}


def test_report_paths_of_this_machine_become_names(tmp_path):
    work_dir, dataset = tmp_path / "work", tmp_path / "data" / "1M-s"
    args = argparse.Namespace(work_dir=work_dir, dataset=str(dataset))
    text = json.dumps({"run_dir": str(work_dir / "bc-16-levels"), "dataset": str(dataset), "other": "/elsewhere"})
    scrubbed = json.loads(without_machine_paths(text, args))
    assert scrubbed == {"run_dir": "WORK_DIR/bc-16-levels", "dataset": "DATASET", "other": "/elsewhere"}
    assert str(tmp_path) not in without_machine_paths(text, args)
    assert Path(scrubbed["run_dir"]).parts[0] == "WORK_DIR"
