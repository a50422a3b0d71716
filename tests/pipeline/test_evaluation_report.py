"""benchmarks/bc.py's stages: a stage done is read back instead of run again (so an interrupted report resumes),
unless its settings changed; the budget rule gives every training-level count the same passes over its data."""

from benchmarks.bc import budget, stage


def test_a_done_stage_is_read_back_and_run_again_only_when_its_settings_change(tmp_path):
    runs, lines = [], []

    def compute():
        runs.append(len(runs))
        return {"run": len(runs)}

    assert stage(tmp_path, "train-16", {"epochs": 100}, compute, lines.append) == {"run": 1}
    assert stage(tmp_path, "train-16", {"epochs": 100}, compute, lines.append) == {"run": 1}  # read, not run
    assert len(runs) == 1 and (tmp_path / "stages" / "train-16.json").is_file()
    assert stage(tmp_path, "train-16", {"epochs": 200}, compute, lines.append) == {"run": 2}
    assert lines[1] == f"train-16: done before, read from {tmp_path / 'stages' / 'train-16.json'}"
    assert not list((tmp_path / "stages").glob("*.tmp"))


def test_the_budget_rule_is_passes_over_the_training_trajectories_validated_every_five():
    # 16 levels: 2 held out (10 %, rounded up), 14 trajectories in one batch of 14: 100 passes, 100 steps, a
    # validation every 5 passes (5 steps)
    assert budget(16, epochs=100, batch_size=32) == {"batch_size": 14, "num_steps": 100, "validate_every_steps": 5}
    # 512 levels: 52 held out, 460 trajectories in batches of 32: ceil(100 * 460 / 32) steps, a validation every
    # ceil(5 * 460 / 32) steps
    assert budget(512, epochs=100, batch_size=32) == {
        "batch_size": 32,
        "num_steps": 1438,
        "validate_every_steps": 72,
    }
