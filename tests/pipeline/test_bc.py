"""Behaviour cloning on a dataset and the evaluation of its policy: config, resume to the same parameters, the
command line end to end, known outcomes in evaluation, data parallelism over two devices and a real interruption."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from pipeline_test_helpers import PARAMS, STATIC, as_a_terminal_job

from kforge import configs
from kforge.engine import physics_scheme
from kforge.env import EnvParams, StaticEnvParams, action_mask, list_levels, load_level, reset, under_scheme
from kforge.pipeline.cli import main
from kforge.pipeline.generation import ConfigError
from kforge.pipeline.learning import load_bc_config, load_policy, train_bc
from kforge.pipeline.learning.checkpoints import checkpoint_steps
from kforge.pipeline.learning.config import BCConfig
from kforge.pipeline.learning.evaluation import Baseline, Episodes, play
from kforge.pipeline.learning.evaluation_sets import StartSet, hand_starts
from kforge.pipeline.storage import DatasetError

SMALL = [
    "train.batch_size=2",
    "model.architecture=mlp",
    "model.hidden_size=32",
    "model.num_hidden_layers=1",
    "validation.every_steps=2",
    "checkpoint.every_steps=2",
    "tracking.wandb=disabled",
]
"""A model and schedule small enough for tests; every test uses these shapes, so programs compile once."""

REPO = Path(__file__).resolve().parents[2]


def small_config(dataset, output_dir, *extra) -> BCConfig:
    return load_bc_config(str(dataset), [f"output_dir={output_dir}", *SMALL, *extra])


@pytest.mark.smoke
def test_bc_yaml_holds_the_schema_defaults():
    from omegaconf import OmegaConf

    stored = OmegaConf.to_container(OmegaConf.load(configs.BC))
    defaults = OmegaConf.to_container(OmegaConf.structured(BCConfig))
    assert stored == {key: value for key, value in defaults.items() if key not in ("dataset", "output_dir")}


@pytest.mark.smoke
def test_config_errors_name_the_key(dataset_dir):
    with pytest.raises(ConfigError, match=r"unknown key train\.num_step \(did you mean train\.num_steps\?\)"):
        load_bc_config(str(dataset_dir), ["train.num_step=3"])
    with pytest.raises(ConfigError, match="model.architecture must be one of mlp, transformer"):
        load_bc_config(str(dataset_dir), ["model.architecture=cnn"])
    with pytest.raises(ConfigError, match=r"validation.fraction must be in \[0, 1\)"):
        load_bc_config(str(dataset_dir), ["validation.fraction=1.5"])
    with pytest.raises(ConfigError, match="num_heads"):
        load_bc_config(str(dataset_dir), ["model.attention_size=30", "model.num_heads=4"])
    assert load_bc_config(str(dataset_dir)).output_dir == f"outputs/bc/{Path(dataset_dir).name}-transformer"


def _final_params(run_dir):
    return jax.tree.leaves(load_policy(run_dir).params)


def test_an_interrupted_run_resumes_to_the_parameters_of_an_uninterrupted_one(dataset_dir, tmp_path):
    whole = train_bc(small_config(dataset_dir, tmp_path / "whole", "train.num_steps=5"), show_progress=False)
    assert whole.steps == 5 and whole.resumed_from == 0
    assert whole.train_levels == 7 and whole.validation_levels == 1  # 8 kept levels, 10 % held out (at least one)
    parts_dir = tmp_path / "parts"
    first = train_bc(small_config(dataset_dir, parts_dir, "train.num_steps=5"), show_progress=False, stop_after_steps=3)
    assert first.steps == 3 and checkpoint_steps(parts_dir)[-1] == 3
    second = train_bc(small_config(dataset_dir, parts_dir, "train.num_steps=5"), show_progress=False)
    assert second.resumed_from == 3 and second.steps == 5
    for resumed, uninterrupted in zip(_final_params(parts_dir), _final_params(tmp_path / "whole"), strict=True):
        np.testing.assert_array_equal(resumed, uninterrupted)
    lines = [json.loads(line) for line in (parts_dir / "metrics.jsonl").read_text().splitlines()]
    assert [line["step"] for line in lines] == [2, 4, 5]
    assert lines[-1]["validation"]["loss"] == pytest.approx(whole.validation_loss, rel=1e-6)


def test_a_resumed_run_refuses_a_changed_key(dataset_dir, tmp_path):
    train_bc(small_config(dataset_dir, tmp_path, "train.num_steps=1"), show_progress=False)
    with pytest.raises(ConfigError, match="trained with other train.learning_rate"):
        train_bc(small_config(dataset_dir, tmp_path, "train.num_steps=2", "train.learning_rate=0.1"))
    raised = train_bc(small_config(dataset_dir, tmp_path, "train.num_steps=2"), show_progress=False)
    assert raised.resumed_from == 1 and raised.steps == 2  # more steps may be asked for


def test_a_small_dataset_fits_the_default_batch_and_a_refused_run_blocks_no_retry(dataset_dir, tmp_path):
    """The dataset holds 8 kept trajectories of 8 levels, one held out: 7 training trajectories, fewer than 32."""
    small = [key for key in SMALL if not key.startswith("train.batch_size")]
    run_dir = tmp_path / "run"
    with pytest.raises(
        ConfigError,
        match=r"^train.batch_size=16 exceeds the 7 training trajectories .*"
        r"use train.batch_size=7 \(or leave it null\)$",
    ):
        train_bc(load_bc_config(str(dataset_dir), [f"output_dir={run_dir}", *small, "train.batch_size=16"]))
    assert not run_dir.exists()  # refused before anything was written
    (run_dir).mkdir()
    (run_dir / "config.yaml").write_text("train:\n  batch_size: 3\n")  # left by a run that never checkpointed
    lines = []
    config = load_bc_config(str(dataset_dir), [f"output_dir={run_dir}", *small, "train.num_steps=1"])
    assert config.train.batch_size is None
    summary = train_bc(config, show_progress=False, report=lines.append)
    assert summary.steps == 1 and summary.resumed_from == 0
    assert lines == [f"train.batch_size=7 (not 32): {dataset_dir} holds 7 training trajectories"]
    stored = load_bc_config(None, [], run_dir / "config.yaml")
    assert stored.train.batch_size == 7  # the run directory records the batch size it trained with
    chosen = tmp_path / "chosen"  # trained with a batch size of its own: a re-run with the default keeps it
    train_bc(
        load_bc_config(str(dataset_dir), [f"output_dir={chosen}", *small, "train.num_steps=1", "train.batch_size=3"])
    )
    resumed = train_bc(load_bc_config(str(dataset_dir), [f"output_dir={chosen}", *small, "train.num_steps=2"]))
    assert resumed.resumed_from == 1 and load_bc_config(None, [], chosen / "config.yaml").train.batch_size == 3


def test_evaluation_counts_the_outcomes_the_levels_force(levels):
    """Drop levels 0 and 1 end in success and level 2 in failure whatever the actions, within a few steps."""
    starts = StartSet(
        jax.vmap(reset)(levels),
        jax.vmap(action_mask)(levels),
        jax.tree.map(lambda x: jnp.broadcast_to(jnp.asarray(x), (3,) + jnp.shape(x)), PARAMS),
        [0, 1, 2],
    )
    for baseline in Baseline:
        success, failure = play(baseline, starts, STATIC, Episodes(count=2, seed=0))
        np.testing.assert_array_equal(success, [[True, True], [True, True], [False, False]])
        np.testing.assert_array_equal(failure, [[False, False], [False, False], [True, True]])


def test_bc_train_and_evaluate_run_end_to_end_on_the_command_line(dataset_dir, tmp_path, capsys):
    run_dir = tmp_path / "run"
    main(
        [
            "bc",
            "train",
            str(dataset_dir),
            f"output_dir={run_dir}",
            *SMALL,
            "train.num_steps=2",
            "--no-progress",
            "--json",
        ]
    )
    summary = json.loads(capsys.readouterr().out)
    assert summary["steps"] == 2 and 0 <= summary["loader_wait_share"] <= 1
    assert summary["validation_loss"] > 0 and (run_dir / "config.yaml").is_file()
    main(["evaluate", str(run_dir), "--on", "train", "--episodes", "1", "--max-levels", "2", "--json"])
    report = json.loads(capsys.readouterr().out)
    train = report["sets"]["train"]
    assert train["levels"] == 2 and train["stored_starts"] > 0
    # Every stored level drops green onto blue: it succeeds whatever any policy does, and so do stored states
    # taken before the landing (after it the trajectory restarted: timestep 0 states are not drawn).
    assert train["from_start"]["noop"]["success"] == 1.0 and train["from_start"]["bc"]["success"] == 1.0
    assert train["from_start"]["expert_recorded"]["success"] == pytest.approx(np.mean([1.0, 0.75]))
    assert json.loads((run_dir / "evaluation.json").read_text()) == report
    with pytest.raises(SystemExit) as stopped:
        main(["evaluate", str(run_dir), "--on", "unseen"])
    assert stopped.value.code == 1
    assert "not made by kforge run" in capsys.readouterr().err


def _train_command(dataset, run_dir, *extra):
    return [sys.executable, "-m", "kforge", "bc", "train", str(dataset), f"output_dir={run_dir}", *SMALL, *extra]


@pytest.mark.slow
def test_two_devices_give_the_loss_of_one_to_rounding(dataset_dir, tmp_path):
    losses = {}
    for devices in (1, 2):
        env = os.environ | {"XLA_FLAGS": f"--xla_force_host_platform_device_count={devices}", "JAX_PLATFORMS": "cpu"}
        run_dir = tmp_path / f"devices-{devices}"
        command = _train_command(dataset_dir, run_dir, "train.num_steps=4", "--no-progress", "--json")
        result = subprocess.run(command, env=env, capture_output=True, text=True, cwd=REPO, check=True)
        summary = json.loads(result.stdout)
        assert summary["devices"] == devices
        losses[devices] = (summary["train_loss"], summary["validation_loss"])
    np.testing.assert_allclose(losses[2], losses[1], rtol=1e-5)


@pytest.mark.slow
def test_sigint_checkpoints_and_the_resumed_run_ends_as_an_uninterrupted_one(dataset_dir, tmp_path):
    steps = ["train.num_steps=60", "checkpoint.every_steps=5", "validation.every_steps=1000", "--no-progress"]
    whole = tmp_path / "whole"
    subprocess.run(_train_command(dataset_dir, whole, *steps), cwd=REPO, check=True, capture_output=True)
    parts = tmp_path / "parts"
    process = subprocess.Popen(
        _train_command(dataset_dir, parts, *steps),
        cwd=REPO,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=as_a_terminal_job,
    )
    while not checkpoint_steps(parts):  # the first checkpoint: training runs
        assert process.poll() is None, "the run ended before it could be interrupted"
        time.sleep(0.05)
    process.send_signal(signal.SIGINT)
    _, err = process.communicate(timeout=120)
    assert process.returncode == 130
    assert "interrupted at step" in err and "resume with: kforge bc train" in err
    interrupted_at = checkpoint_steps(parts)[-1]
    assert 5 <= interrupted_at < 60
    subprocess.run(_train_command(dataset_dir, parts, *steps), cwd=REPO, check=True, capture_output=True)
    for resumed, uninterrupted in zip(_final_params(parts), _final_params(whole), strict=True):
        np.testing.assert_array_equal(resumed, uninterrupted)


def test_hand_levels_are_played_under_the_datasets_physics_scheme():
    """A dataset made with env.physics=kinetix is evaluated on the hand-designed levels with that scheme's parameters
    (its laws live in the static parameters), each level keeping its own constants; the engine's own scheme's static
    parameters are none of Kinetix's sizes under it."""
    kinetix = physics_scheme("kinetix")
    _, static = under_scheme(kinetix, EnvParams(), StaticEnvParams.for_size("s"))
    starts = hand_starts(static, kinetix)
    names = list_levels("s")
    assert starts.level_ids == names and len(names) > 1
    assert np.all(np.asarray(starts.params.sim.speculative_distance) == 0.0)
    own = np.array([load_level(name).params.sim.base_friction for name in names], np.float32)
    assert np.array_equal(np.asarray(starts.params.sim.base_friction), own)
    with pytest.raises(DatasetError, match="none of Kinetix's s, m and l"):
        hand_starts(StaticEnvParams.for_size("s"))  # the engine's own scheme's size s (4 substeps) under kinetix


def _learner_and_batches(dataset_dir, tmp_path, count, *extra):
    from kforge.pipeline.learning.train import Learner
    from kforge.pipeline.reading import TrajectoryDatasetManager
    from kforge.pipeline.storage import open_dataset

    config = small_config(dataset_dir, tmp_path, *extra)
    layout = open_dataset(str(dataset_dir)).layout
    learner = Learner(config, layout.static, layout.num_steps)
    loader = TrajectoryDatasetManager(str(dataset_dir), batch_size=config.train.batch_size, seed=0)
    return learner, [loader.load_next_batch() for _ in range(count)]


def _train_batch(batch):
    from kforge.pipeline.learning.train import TrainBatch

    return TrainBatch(batch.env_state, batch.action, batch.action_mask)


def test_the_compiled_loop_takes_the_steps_one_by_one_steps_take(dataset_dir, tmp_path):
    """Four steps per call (the validation and checkpoint intervals allow it); three batches leave the fourth step
    inactive."""
    learner, batches = _learner_and_batches(
        dataset_dir, tmp_path, 3, "validation.every_steps=4", "checkpoint.every_steps=4"
    )
    assert learner.steps_per_dispatch == 4
    looped, metrics = learner.steps(learner.init(0), batches)
    single = jax.jit(learner.train_step)
    state = learner.init(0)
    losses = []
    for batch in batches:
        state, step_metrics = single(state, _train_batch(batch))
        losses.append(float(step_metrics["loss"]))
    assert int(looped.step) == int(state.step) == 3
    for got, expected in zip(jax.tree.leaves(looped), jax.tree.leaves(state), strict=True):
        np.testing.assert_allclose(got, expected, rtol=0, atol=1e-6)
    np.testing.assert_allclose([float(m["loss"]) for m in metrics], losses, rtol=1e-6)


def test_the_gradient_in_time_slices_is_the_whole_batchs(dataset_dir, tmp_path):
    from kforge.agents import imitation_terms

    learner, (batch,) = _learner_and_batches(dataset_dir, tmp_path, 1, "model.architecture=transformer")
    assert learner.chunk_steps < batch.action.shape[1]  # the batch is taken in several slices
    params = learner.init(0).params

    def whole_loss(p):
        logits = learner.network.apply(p, learner.observations(batch.env_state))
        return imitation_terms(logits, batch.action, batch.action_mask).loss

    expected = jax.grad(whole_loss)(params)
    sliced, (loss, _) = jax.jit(learner.gradient)(params, _train_batch(batch))
    np.testing.assert_allclose(float(loss), float(whole_loss(params)), rtol=1e-5)
    for got, want in zip(jax.tree.leaves(sliced), jax.tree.leaves(expected), strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-7)


@pytest.mark.smoke
def test_the_patience_rule_stops_at_the_patience_th_validation_without_an_improvement():
    from kforge.pipeline.learning.stopping import loss_curve, plateau

    losses = [1.0, 0.8, 0.7995, 0.79, 0.85, 0.6, 0.61]
    # 0.7995 and 0.79 are not 0.01 below the best (0.8); 0.85 is the third validation in a row without an improvement
    stopped = plateau(losses, patience=3, min_improvement=0.01)
    assert (stopped.best_index, stopped.stop_index) == (1, 4)
    assert plateau(losses, patience=4, min_improvement=0.01).stop_index is None  # 0.6 improves on 0.8 in time
    assert plateau(losses, patience=4, min_improvement=0.01).best_index == 5
    assert plateau(losses, patience=0, min_improvement=0.01).stop_index is None
    lines = [
        {"step": 10 * (i + 1), "train": {"loss": 2.0}, "validation": {"loss": loss}} for i, loss in enumerate(losses)
    ]
    curve = loss_curve(lines, patience=3, min_improvement=0.01)
    assert (curve["plateau_step"], curve["best_step"], curve["best_validation_loss"]) == (50, 20, 0.8)
    assert curve["gradient_steps"] == 70 and curve["validation_loss"] == losses and curve["steps"][0] == 10


@pytest.mark.smoke
def test_the_validation_split_is_disjoint_complete_and_fixed_by_its_seed():
    from kforge.pipeline.learning.data import validation_split

    ids = list(range(100, 140))
    train, validation = validation_split(ids, fraction=0.1, seed=3)
    assert len(validation) == 4 and not set(train) & set(validation) and sorted(train + validation) == ids
    assert validation_split(list(reversed(ids)), fraction=0.1, seed=3) == (train, validation)
    assert validation_split(ids, fraction=0.1, seed=4)[1] != validation


def test_a_run_stops_at_a_validation_plateau_and_records_its_curve(dataset_dir, tmp_path):
    """No validation loss can improve by 100 nats on the first: the run stops at its second validation."""
    stop = ["train.num_steps=20", "validation.patience=1", "validation.min_improvement=100"]
    summary = train_bc(small_config(dataset_dir, tmp_path, *stop), show_progress=False)
    assert (summary.steps, summary.stopped, summary.best_step) == (4, "plateau", 2)
    curve = json.loads((tmp_path / "curve.json").read_text())
    assert curve["gradient_steps"] == 4 and curve["steps"] == [2, 4] and curve["plateau_step"] == 4
    assert all(loss > 0 for loss in curve["train_loss"] + curve["validation_loss"])
    again = train_bc(small_config(dataset_dir, tmp_path, *stop), show_progress=False)
    assert (again.resumed_from, again.steps, again.stopped) == (4, 4, "plateau")
