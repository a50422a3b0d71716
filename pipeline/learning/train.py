"""Behaviour cloning on a dataset: a policy trained on the stored expert actions, validated on held-out levels until
its validation loss reaches a plateau, checkpointed and resumable, data parallel over the local devices.

Each gradient step reads `train.batch_size` trajectories with the dataset loader (in a background thread with
`prefetch`), renders their observations from the stored states inside the compiled step, and minimises the masked
per-slot NLL (`agents.imitation_terms`) with AdamW after global-norm clipping; one compiled call takes several steps
(`Learner`). The batch is split over all local devices along the trajectory axis (a `jax.sharding` mesh), the
parameters replicated. Every `validation.every_steps` steps the run scores its validation levels, appends the figures
to <run>/metrics.jsonl and rewrites <run>/curve.json (`stopping`); it stops at `train.num_steps` or at the plateau.
A run is a pure function of its config: an interrupted run resumes from its latest checkpoint at the same point of
the same batch sequence, so it ends with the parameters an uninterrupted run ends with.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from omegaconf import OmegaConf
from tqdm import tqdm

from kforge.agents import ImitationTerms, NetworkConfig, imitation_terms, make_bc_network
from kforge.env import EnvState, StaticEnvParams, observation_shape, observe
from kforge.pipeline.generation import ConfigError, seconds_left, to_schema_object, to_yaml, tracking_mode
from kforge.pipeline.learning.checkpoints import checkpoint_steps, restore_checkpoint, save_checkpoint
from kforge.pipeline.learning.config import (
    DEFAULT_BATCH_SIZE,
    RUN_CONFIG_FILE,
    BCConfig,
    changed_keys,
    fit_batch_size,
    network_config,
)
from kforge.pipeline.learning.data import kept_levels, validation_split
from kforge.pipeline.learning.stopping import loss_curve, write_curve
from kforge.pipeline.reading import TrajectoryDatasetManager
from kforge.pipeline.storage import DatasetError, open_dataset

LEVELS_FILE = "levels.json"
"""The run's training and validation level ids."""
METRICS_FILE = "metrics.jsonl"
"""One JSON line of training and validation metrics per validation."""
SUMMARY_FILE = "summary.json"
"""The finished run's closing figures."""
DATA_AXIS = "data"
"""Mesh axis over which a batch's trajectories are split."""
CHUNK_TRANSITIONS = 128
"""[transitions] per device, the time slice of a batch whose gradient is taken at once. Slices of 64 to 512
transitions keep a block's activations (10 tokens x 128 floats each) within the CPU's second-level cache; the whole
batch's (8192 transitions) would stream through memory in every layer. About 1.7x the transitions per CPU second of
whole batches, measured on the 2-core CPU."""
STEPS_PER_DISPATCH = 4
"""Gradient steps the compiled training loop takes per call (fewer where a validation or checkpoint interval is not a
multiple of it): the host reads the next batches while the device trains."""
BYTES_PER_GIB = 1 << 30
BAR_FORMAT = "{desc}: {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt} [{elapsed}, {postfix}]"
"""The progress bar: time left comes from the pace since the first step (which compiles), in the postfix."""


class TrainBatch(NamedTuple):
    """What a gradient step reads of a loader batch: stored states, expert actions and the levels' action masks."""

    env_state: EnvState  # leaves (B, T, ...)
    action: jnp.ndarray  # (B, T, 6)
    action_mask: jnp.ndarray  # (B, T, 6) bool


@struct.dataclass
class LearnerState:
    """What a checkpoint holds: the parameters, the optimiser state and the gradient steps taken."""

    params: Any
    opt_state: Any
    step: jnp.ndarray  # () i32


def chunk_steps(trajectories_per_device: int, window_steps: int) -> int:
    """[env steps] the time slice of a batch whose gradient is taken at once: the longest divisor of `window_steps` that
    keeps a device's slice within `CHUNK_TRANSITIONS` (at least one step)."""
    fitting = max(1, CHUNK_TRANSITIONS // max(trajectories_per_device, 1))
    return max(length for length in range(1, window_steps + 1) if window_steps % length == 0 and length <= fitting)


def steps_per_dispatch(config: BCConfig) -> int:
    """Gradient steps per call of the compiled training loop: `STEPS_PER_DISPATCH` or fewer, dividing the validation
    and checkpoint intervals so that a call never crosses one."""
    return math.gcd(STEPS_PER_DISPATCH, config.validation.every_steps, config.checkpoint.every_steps)


class Learner:
    """The compiled programs of a BC run: initialisation, `steps_per_dispatch` gradient steps per call and validation
    scores, sharded over the local devices.

    A gradient step renders the observations of its (B, T) batch and takes the gradient of the batch's mean loss in
    time slices of `chunk_steps` (a scan that sums the slices' gradients): a slice's activations stay in the CPU's
    caches, where the whole batch's would not. The steps of a call are a scan over stacked batches; a step marked
    inactive leaves the state as it is (a call that ends a run early), so every step runs the same compiled body.
    """

    def __init__(self, config: BCConfig, static: StaticEnvParams, window_steps: int, devices: list | None = None):
        self.network_config: NetworkConfig = network_config(config)
        self.network = make_bc_network(self.network_config)
        self.observation_type = self.network_config.architecture.observation_type
        self.static = static
        self.config = config
        devices = jax.local_devices() if devices is None else devices
        self.num_devices = len(devices)
        self.window_steps = window_steps
        """Env steps per stored trajectory."""
        if config.train.batch_size % len(devices):
            raise ConfigError(
                f"train.batch_size ({config.train.batch_size}) must be a multiple of the {len(devices)} local devices"
            )
        self.chunk_steps = chunk_steps(config.train.batch_size // len(devices), window_steps)
        self.steps_per_dispatch = steps_per_dispatch(config)
        mesh = Mesh(np.asarray(devices), (DATA_AXIS,))
        self.data_sharding = NamedSharding(mesh, PartitionSpec(DATA_AXIS))
        self.stacked_sharding = NamedSharding(mesh, PartitionSpec(None, DATA_AXIS))
        self.replicated = NamedSharding(mesh, PartitionSpec())
        train = config.train
        schedule = (
            optax.linear_schedule(train.learning_rate, 0.0, train.num_steps) if train.anneal else train.learning_rate
        )
        self.optimizer = optax.chain(
            optax.clip_by_global_norm(train.max_grad_norm),
            optax.adamw(schedule, weight_decay=train.weight_decay),
        )
        self._steps = jax.jit(
            self._train_steps,
            in_shardings=(self.replicated, self.stacked_sharding, self.replicated),
            out_shardings=(self.replicated, self.replicated),
        )
        self._score = jax.jit(
            self._terms,
            in_shardings=(self.replicated,) + (self.data_sharding,) * 4,
            out_shardings=self.replicated,
        )

    def init(self, seed: int) -> LearnerState:
        """Fresh parameters from `seed` and a fresh optimiser."""
        shapes = observation_shape(self.static, self.observation_type)
        example = jax.tree.map(lambda leaf: jnp.zeros(leaf.shape, leaf.dtype), shapes)
        params = self.network.init(jax.random.key(seed), example)
        state = LearnerState(params=params, opt_state=self.optimizer.init(params), step=jnp.zeros((), jnp.int32))
        return jax.device_put(state, self.replicated)

    def observations(self, env_state: EnvState):
        """Observations of a (B, T) batch of states."""
        return jax.vmap(jax.vmap(lambda state: observe(state, self.static, self.observation_type)))(env_state)

    def _terms(self, params, env_state, action, action_mask, weight=None) -> ImitationTerms:
        logits = self.network.apply(params, self.observations(env_state))
        return imitation_terms(logits, action, action_mask, weight)

    def gradient(self, params, batch: TrainBatch):
        """(gradient of the batch's mean loss, (loss, valid-slot accuracy)), summed over time slices."""
        counted = jnp.sum(jnp.any(batch.action_mask, axis=-1)).astype(jnp.float32)
        valid_slots = jnp.sum(batch.action_mask).astype(jnp.float32)
        slices = batch.action.shape[1] // self.chunk_steps

        def time_slices(leaf):  # (B, T, ...) -> (slices, B, chunk, ...), the trajectory axis still split over devices
            leaf = leaf.reshape((leaf.shape[0], slices, self.chunk_steps) + leaf.shape[2:])
            return jnp.moveaxis(leaf, 1, 0)

        def add_slice(total, part: TrainBatch):
            def weighted_loss(p):
                terms = self._terms(p, part.env_state, part.action, part.action_mask)
                return terms.loss * terms.transition_count / jnp.maximum(counted, 1.0), terms

            (_, terms), grads = jax.value_and_grad(weighted_loss, has_aux=True)(params)
            correct = terms.accuracy * jnp.sum(part.action_mask)
            loss_sum = terms.loss * terms.transition_count
            return jax.tree.map(jnp.add, total, (grads, loss_sum, correct)), None

        zero = (jax.tree.map(jnp.zeros_like, params), jnp.zeros(()), jnp.zeros(()))
        (grads, loss_sum, correct), _ = jax.lax.scan(add_slice, zero, jax.tree.map(time_slices, batch))
        return grads, (loss_sum / jnp.maximum(counted, 1.0), correct / jnp.maximum(valid_slots, 1.0))

    def train_step(self, state: LearnerState, batch: TrainBatch):
        """One gradient step (pure: the compiled loop scans it)."""
        grads, (loss, accuracy) = self.gradient(state.params, batch)
        updates, opt_state = self.optimizer.update(grads, state.opt_state, state.params)
        following = LearnerState(optax.apply_updates(state.params, updates), opt_state, state.step + 1)
        return following, {"loss": loss, "accuracy": accuracy, "grad_norm": optax.tree.norm(grads)}

    def _train_steps(self, state: LearnerState, batches: TrainBatch, active: jnp.ndarray):
        def one(state, inputs):
            batch, take = inputs
            return jax.lax.cond(take, self.train_step, self._skip_step, state, batch)

        return jax.lax.scan(one, state, (batches, active))

    def _skip_step(self, state: LearnerState, batch: TrainBatch):
        zero = jnp.zeros((), jnp.float32)
        return state, {"loss": zero, "accuracy": zero, "grad_norm": zero}

    def steps(self, state: LearnerState, batches: list) -> tuple[LearnerState, list[dict]]:
        """`len(batches)` gradient steps (at most `steps_per_dispatch`) on loader batches in one call; the metrics of
        each step, on the device until read."""
        count = len(batches)
        if not 1 <= count <= self.steps_per_dispatch:
            raise ValueError(f"expected 1 to {self.steps_per_dispatch} batches, got {count}")
        padded = batches + [batches[-1]] * (self.steps_per_dispatch - count)
        stacked = jax.tree.map(
            lambda *leaves: np.stack([np.asarray(leaf) for leaf in leaves]),
            *[TrainBatch(b.env_state, b.action, b.action_mask) for b in padded],
        )
        active = np.arange(self.steps_per_dispatch) < count
        state, metrics = self._steps(state, stacked, active)
        return state, [jax.tree.map(lambda value, i=i: value[i], metrics) for i in range(count)]

    def score(self, params, batch, weight) -> ImitationTerms:
        """BC terms of a batch, each trajectory weighted (0 leaves a padding trajectory out)."""
        steps = batch.action.shape[1]
        weights = jnp.repeat(jnp.asarray(weight, jnp.float32)[:, None], steps, axis=1)
        return self._score(params, batch.env_state, batch.action, batch.action_mask, weights)


class TrainingInterrupted(Exception):
    """A BC run stopped by SIGINT or SIGTERM after checkpointing its last completed step; re-running resumes."""

    def __init__(self, run_dir: str, step: int, num_steps: int):
        super().__init__(f"{run_dir}: interrupted at step {step} of {num_steps}, checkpointed")
        self.step = step


@dataclasses.dataclass
class TrainSummary:
    """A finished run's closing figures (also <run>/summary.json)."""

    run_dir: str
    steps: int
    resumed_from: int  # [steps] 0 for a fresh run
    devices: int  # local devices the batches were split over
    train_levels: int
    validation_levels: int
    train_loss: float  # [nats] mean over the steps since the last validation
    train_accuracy: float  # [-] valid-slot accuracy, mean over the same steps
    validation_loss: float | None  # [nats] None without validation levels
    validation_accuracy: float | None
    validation_slot_accuracy: list[float | None] | None  # per action slot; None where no level uses the slot
    seconds: float  # [s] wall time of this invocation's steps
    loader_wait_seconds: float  # [s] of which the device waited for the loader's next batch
    cached: bool  # the training trajectories were held in host memory
    loader_wait_share: float  # [-] loader_wait_seconds / seconds
    transitions_per_s: float  # trained transitions per second of wall time
    stopped: str = "num_steps"  # plateau (validation loss), num_steps, or paused (stop_after_steps; re-run to go on)
    best_step: int | None = None  # [steps] the validation with the lowest loss (the last improvement)
    best_validation_loss: float | None = None  # [nats] its loss


def _start_wandb(config: BCConfig, run_dir: Path, verbose: bool):
    """A wandb run of the BC run (None when disabled); its files under <run>/logs, its banner and closing summary on
    the terminal only if `verbose`."""
    mode = tracking_mode(config)
    if mode == "disabled":
        return None
    import wandb

    logs = run_dir / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("WANDB_DISABLE_WEAVE", "true")
    return wandb.init(
        mode=mode,
        project=config.tracking.project,
        name=config.tracking.name,
        dir=str(logs),
        job_type="bc",
        config=dataclasses.asdict(config),
        settings=wandb.Settings(console="off", save_code=False, disable_git=True, silent=not verbose),
    )


def _trained_config(run_dir: Path) -> BCConfig | None:
    """The config a run directory was trained with: None until it holds a checkpoint (a run that stopped before its
    first binds nothing)."""
    stored_file = run_dir / RUN_CONFIG_FILE
    if not (stored_file.exists() and checkpoint_steps(run_dir)):
        return None
    return to_schema_object(OmegaConf.merge(OmegaConf.structured(BCConfig), OmegaConf.load(stored_file)), BCConfig)


def _prepare_run_dir(config: BCConfig) -> Path:
    """The run directory with the config written; a re-run of a trained run must agree with its config
    (`changed_keys`)."""
    run_dir = Path(config.output_dir)
    stored = _trained_config(run_dir)
    changed = [] if stored is None else changed_keys(stored, config)
    if changed:
        raise ConfigError(
            f"{run_dir}: this run directory was trained with other {', '.join(changed)}; resume with the same "
            f"values or choose another output_dir"
        )
    run_dir.mkdir(parents=True, exist_ok=True)
    stored_file = run_dir / RUN_CONFIG_FILE
    partial = stored_file.with_suffix(".partial")
    partial.write_text(to_yaml(config))
    os.replace(partial, stored_file)
    return run_dir


def _validation_batches(loader: TrajectoryDatasetManager, slots: list[int], batch_size: int):
    """(batch, weight) pairs covering `slots`; the last batch is padded with its first slot at weight 0."""
    for start in range(0, len(slots), batch_size):
        chunk = slots[start : start + batch_size]
        padded = chunk + [chunk[0]] * (batch_size - len(chunk))
        weight = np.array([1.0] * len(chunk) + [0.0] * (batch_size - len(chunk)), np.float32)
        yield loader.load_slots(np.asarray(padded)), weight


def _combine(scores: list[ImitationTerms]) -> dict:
    """Validation figures of several batches' terms, each weighted by what it counted."""
    scores = jax.device_get(scores)
    transitions = sum(float(s.transition_count) for s in scores)
    slot_count = np.sum([s.slot_count for s in scores], axis=0)
    slot_correct = np.sum([s.slot_accuracy * s.slot_count for s in scores], axis=0)
    return {
        "loss": sum(float(s.loss) * float(s.transition_count) for s in scores) / max(transitions, 1.0),
        "accuracy": float(slot_correct.sum() / max(slot_count.sum(), 1.0)),
        "slot_accuracy": [float(c / n) if n else None for c, n in zip(slot_correct, slot_count, strict=True)],
    }


def _mean_metrics(pending: list[dict]) -> dict:
    values = jax.device_get(pending)
    return {key: float(np.mean([v[key] for v in values])) for key in values[0]}


def _read_metrics(run_dir: Path) -> list[dict]:
    path = run_dir / METRICS_FILE
    return [json.loads(line) for line in path.read_text().splitlines() if line] if path.exists() else []


def _stop_reason(curve: dict, step: int, num_steps: int) -> str:
    if curve["plateau_step"] is not None:
        return "plateau"
    return "num_steps" if step >= num_steps else "paused"


def _truncate_metrics(run_dir: Path, step: int) -> None:
    """Drop metric lines written after `step` (by a run interrupted after its last checkpoint)."""
    path = run_dir / METRICS_FILE
    if path.exists():
        lines = [line for line in path.read_text().splitlines() if line and json.loads(line)["step"] <= step]
        path.write_text("".join(line + "\n" for line in lines))


def train_bc(
    config: BCConfig,
    show_progress: bool = True,
    report=print,
    stop_after_steps: int | None = None,
    verbose: bool = False,
) -> TrainSummary:
    """Train (or resume) the BC run of `config`; returns its summary. `stop_after_steps` ends this invocation after
    that many steps, checkpointed, as an interruption would (tests and time-boxed jobs). wandb's files go to
    <run>/logs, its terminal output only if `verbose`."""
    levels, train_ids, validation_ids = _chosen_levels(config)
    config = _settled_batch_size(config, sum(len(levels[level]) for level in train_ids), report)
    layout = open_dataset(config.dataset).layout
    learner = Learner(config, layout.static, layout.num_steps)
    run_dir = _prepare_run_dir(config)  # after every check that can refuse the run: a refused run leaves nothing
    (run_dir / LEVELS_FILE).write_text(json.dumps({"train": train_ids, "validation": validation_ids}))
    state = _restored_state(learner, run_dir, config.train.seed)
    start = int(state.step)
    _truncate_metrics(run_dir, start)
    if start:
        report(f"resuming {run_dir} from its checkpoint at step {start} of {config.train.num_steps}")
    run = _Run(
        config,
        learner,
        run_dir,
        validation_slots=sorted(slot for level in validation_ids for slot in levels[level]),
        loader=_training_loader(config, train_ids, start),
        tracking=_start_wandb(config, run_dir, verbose),
    )
    loop = _TrainingLoop(run, state, stop_after_steps, show_progress)
    loop.train()
    return _finish(run, loop, (train_ids, validation_ids))


def _chosen_levels(config: BCConfig) -> tuple[dict, list, list]:
    """(the dataset's kept levels -> their trajectory slots, training level ids, validation level ids)."""
    levels = kept_levels(config.dataset)
    if not levels:
        raise DatasetError(f"{config.dataset}: no committed, kept trajectories to learn from")
    chosen = sorted(levels)[: config.train.levels]
    if config.train.levels is not None and len(chosen) < config.train.levels:
        raise DatasetError(
            f"{config.dataset}: train.levels={config.train.levels}, but the dataset holds {len(chosen)} kept levels"
        )
    train_ids, validation_ids = validation_split(chosen, config.validation.fraction, config.train.seed)
    return levels, train_ids, validation_ids


def _settled_batch_size(config: BCConfig, train_trajectories: int, report) -> BCConfig:
    """`config` with the batch size the run trains with: the one asked for or, when none is, the one a resumed run
    chose, resolved for the training trajectories and the local devices (`fit_batch_size`)."""
    requested_batch_size = config.train.batch_size
    trained = _trained_config(Path(config.output_dir))
    if requested_batch_size is None and trained is not None:  # a resumed run keeps the batch size it chose
        config = dataclasses.replace(
            config, train=dataclasses.replace(config.train, batch_size=trained.train.batch_size)
        )
    config = fit_batch_size(config, train_trajectories, len(jax.local_devices()))
    if requested_batch_size is None and trained is None and config.train.batch_size < DEFAULT_BATCH_SIZE:
        report(
            f"train.batch_size={config.train.batch_size} (not {DEFAULT_BATCH_SIZE}): {config.dataset} holds "
            f"{train_trajectories} training trajectories"
        )
    return config


def _restored_state(learner: Learner, run_dir: Path, seed: int) -> LearnerState:
    """The learner state at the run's latest checkpoint, or a fresh one from `seed`."""
    state = learner.init(seed)
    steps = checkpoint_steps(run_dir)
    if steps:
        state = jax.device_put(restore_checkpoint(run_dir, steps[-1], state), learner.replicated)
    return state


def _training_loader(config: BCConfig, train_ids: list, start: int) -> TrajectoryDatasetManager:
    """The loader of the training levels' batches, from the batch of step `start` on."""
    train = config.train
    return TrajectoryDatasetManager(
        config.dataset,
        batch_size=train.batch_size,
        seed=train.seed,
        prefetch=train.prefetch,
        level_ids=train_ids,
        start_batch=start,
        cache_bytes=int(train.cache_gb * BYTES_PER_GIB),
    )


def _loss_curve(lines: list[dict], config: BCConfig) -> dict:
    """The validation loss curve of the metric lines under the run's plateau rule."""
    return loss_curve(lines, config.validation.patience, config.validation.min_improvement)


@dataclasses.dataclass
class _Run:
    """What a BC run's training loop works with."""

    config: BCConfig
    learner: Learner
    run_dir: Path
    validation_slots: list[int]
    loader: TrajectoryDatasetManager
    tracking: Any  # the wandb run, None when tracking is disabled


class _TrainingLoop:
    """One invocation's gradient steps, from the run's latest checkpoint to `train.num_steps`, the plateau or
    `stop_after_steps`: validated, logged, checkpointed and shown on the progress bar on the way."""

    def __init__(self, run: _Run, state: LearnerState, stop_after_steps: int | None, show_progress: bool):
        self.run = run
        self.state = state
        self.start = self.step = self.saved = int(state.step)
        self.lines = _read_metrics(run.run_dir)
        num_steps = run.config.train.num_steps
        stopped_early = _loss_curve(self.lines, run.config)["plateau_step"] is not None  # a re-run of a finished run
        end = num_steps if stop_after_steps is None else min(num_steps, self.start + stop_after_steps)
        self.end = self.start if stopped_early else end
        self.bar = tqdm(
            total=num_steps,
            initial=self.start,
            disable=not show_progress,
            unit="step",
            dynamic_ncols=True,
            bar_format=BAR_FORMAT,
            desc="compiling",
        )
        self.since = None  # (time, step) once the first call, the one that compiles, is done
        self.wait = 0.0  # [s] spent waiting for the loader's batches
        self.seconds = 0.0  # [s] wall time of the steps, once trained
        self.began = time.perf_counter()
        self.pending: list[dict] = []  # metrics of the steps since the last validation, on the device until read
        last = self.lines[-1] if self.lines else {"train": None, "validation": None}
        self.latest = {"train": last["train"], "validation": last["validation"], "step_loss": None}

    def train(self) -> None:
        """Take the steps; an interruption checkpoints the last completed step and raises `TrainingInterrupted`."""
        config = self.run.config
        try:
            with self.run.loader:
                while self.step < self.end:
                    self._take_steps()
                    if self.step % config.validation.every_steps == 0 or self.step == config.train.num_steps:
                        self._validate()
                    if self.step % config.checkpoint.every_steps == 0 or self.step == self.end:
                        self._checkpoint()
        except KeyboardInterrupt:
            if self.saved != self.step:
                self._checkpoint()
            self.bar.close()
            if self.run.tracking is not None:
                self.run.tracking.finish(exit_code=1)
            raise TrainingInterrupted(str(self.run.run_dir), self.step, config.train.num_steps) from None
        finally:
            self.bar.close()
        self.seconds = time.perf_counter() - self.began
        if self.pending:
            self.latest["train"] = _mean_metrics(self.pending)

    def _take_steps(self) -> None:
        """One call of the compiled steps, never past a validation or checkpoint step."""
        per_call = self.run.learner.steps_per_dispatch
        count = min(per_call - self.step % per_call, self.end - self.step)
        asked = time.perf_counter()
        batches = [self.run.loader.load_next_batch() for _ in range(count)]
        self.wait += time.perf_counter() - asked
        if self.pending:  # wait for the previous call; its loss shows on the bar
            self.latest["step_loss"] = float(self.pending[-1]["loss"])
            now = time.perf_counter()
            self.since = self.since or (now, self.step)
            self.bar.desc = "steps"
            self.bar.set_postfix_str(_postfix(self.latest, self._seconds_left(now)), refresh=False)
        self.state, metrics = self.run.learner.steps(self.state, batches)
        self.pending.extend(metrics)
        self.step += count
        self.bar.update(count)

    def _validate(self) -> None:
        """Score the validation levels, append the metric line, rewrite the curve and end the run at its plateau."""
        run, config = self.run, self.run.config
        self.latest["train"] = _mean_metrics(self.pending)
        self.pending = []
        if run.validation_slots:
            batches = _validation_batches(run.loader, run.validation_slots, config.validation.batch_size)
            self.latest["validation"] = _combine(
                [run.learner.score(self.state.params, batch, weight) for batch, weight in batches]
            )
        line = {"step": self.step, "train": self.latest["train"], "validation": self.latest["validation"]}
        with open(run.run_dir / METRICS_FILE, "a") as metrics_file:
            metrics_file.write(json.dumps(line) + "\n")
        self.lines.append(line)
        curve = _loss_curve(self.lines, config)
        write_curve(run.run_dir, curve)
        if curve["plateau_step"] is not None:
            self.end = self.step
        if run.tracking is not None:
            run.tracking.log(_flat_metrics(line), step=self.step)
        self.bar.set_postfix_str(_postfix(self.latest, self._seconds_left(time.perf_counter())))

    def _checkpoint(self) -> None:
        save_checkpoint(self.run.run_dir, self.step, jax.device_get(self.state), self.run.config.checkpoint.keep)
        self.saved = self.step

    def _seconds_left(self, now: float) -> float | None:
        return seconds_left(self.since, now, self.step, self.run.config.train.num_steps)


def _finish(run: _Run, loop: _TrainingLoop, level_ids: tuple[list, list]) -> TrainSummary:
    """Write the final curve and <run>/summary.json, close the wandb run; the summary."""
    curve = _loss_curve(loop.lines, run.config)
    write_curve(run.run_dir, curve)
    summary = _summary(run, loop, level_ids, curve)
    (run.run_dir / SUMMARY_FILE).write_text(json.dumps(dataclasses.asdict(summary), indent=1))
    if run.tracking is not None:
        run.tracking.summary.update({"loader_wait_share": summary.loader_wait_share})
        run.tracking.finish()
    return summary


def _flat_metrics(line: dict) -> dict:
    flat = {f"train/{key}": value for key, value in (line["train"] or {}).items()}
    validation = line["validation"] or {}
    flat |= {f"validation/{key}": value for key, value in validation.items() if key != "slot_accuracy"}
    flat |= {
        f"validation/slot_accuracy_{slot}": value
        for slot, value in enumerate(validation.get("slot_accuracy") or [])
        if value is not None
    }
    return flat


def _postfix(latest: dict, left: float | None) -> str:
    """The bar's text: time left, the last step's loss, the latest training and validation means."""
    parts = [f"left {'?' if left is None else tqdm.format_interval(left)}"]
    if latest["step_loss"] is not None:
        parts.append(f"step loss {latest['step_loss']:.3f}")
    if latest["train"]:
        parts.append(f"loss {latest['train']['loss']:.3f} acc {latest['train']['accuracy']:.2f}")
    if latest["validation"]:
        parts.append(f"val loss {latest['validation']['loss']:.3f} acc {latest['validation']['accuracy']:.2f}")
    return ", ".join(parts)


def _summary(run: _Run, loop: _TrainingLoop, level_ids: tuple[list, list], curve: dict) -> TrainSummary:
    """The closing figures of the run after `loop`."""
    (train_ids, validation_ids), seconds, wait = level_ids, loop.seconds, loop.wait
    validation = loop.latest["validation"]
    train = loop.latest["train"] or {"loss": float("nan"), "accuracy": float("nan")}
    transitions = (loop.step - loop.start) * run.config.train.batch_size * run.learner.window_steps
    return TrainSummary(
        run_dir=str(run.run_dir),
        steps=loop.step,
        resumed_from=loop.start,
        devices=run.learner.num_devices,
        train_levels=len(train_ids),
        validation_levels=len(validation_ids),
        train_loss=train["loss"],
        train_accuracy=train["accuracy"],
        validation_loss=None if validation is None else validation["loss"],
        validation_accuracy=None if validation is None else validation["accuracy"],
        validation_slot_accuracy=None if validation is None else validation["slot_accuracy"],
        seconds=seconds,
        loader_wait_seconds=wait,
        cached=run.loader.cached,
        loader_wait_share=wait / seconds if seconds > 0 else 0.0,
        transitions_per_s=transitions / seconds if seconds > 0 else 0.0,
        stopped=_stop_reason(curve, loop.step, run.config.train.num_steps),
        best_step=curve["best_step"],
        best_validation_loss=curve["best_validation_loss"],
    )
