"""RL agents that train on env tasks: PPO specialists, one parameter set per level, many levels per program.

Public surface: the config, training of a level batch, evaluation, expert windows for the dataset, training in
segments for adaptive budgets, the pieces they are made of (GAE, loss, policy), and progress reports from a training
program while it runs.
"""

from agents.collect import WINDOW_STEPS, Window, collect_windows
from agents.config import PPOConfig
from agents.evaluate import Episode, EvalOutput, evaluate, level_episodes
from agents.networks import ActorCritic, make_network
from agents.ppo import (
    Batch,
    LossTerms,
    Selection,
    TrainOutput,
    UpdateMetrics,
    gae,
    initial_params,
    ppo_loss,
    train_from,
    train_level,
    train_levels,
)
from agents.progress import ProgressListener, training_progress
from agents.segments import LevelTraining, SegmentOutput, check_segmented, put_slot, start_level, train_segments

__all__ = [
    "WINDOW_STEPS",
    "ActorCritic",
    "Batch",
    "Episode",
    "EvalOutput",
    "LevelTraining",
    "LossTerms",
    "PPOConfig",
    "ProgressListener",
    "SegmentOutput",
    "Selection",
    "TrainOutput",
    "UpdateMetrics",
    "Window",
    "check_segmented",
    "collect_windows",
    "evaluate",
    "gae",
    "initial_params",
    "level_episodes",
    "make_network",
    "ppo_loss",
    "put_slot",
    "start_level",
    "train_from",
    "train_level",
    "train_levels",
    "train_segments",
    "training_progress",
]
