"""RL agents that train on env tasks: PPO specialists, one parameter set per level, many levels per program.

Public surface: the config, training of a level batch, evaluation, expert windows for the dataset, training in segments
for adaptive budgets, and the pieces they are made of (GAE, loss, the learner and its optimiser, policy); for behaviour
cloning, its policy networks and objective, and episodes of any policy given as an actor function.
"""

from kforge.agents.bc_networks import Architecture, EntityTransformerPolicy, MLPPolicy, NetworkConfig, make_bc_network
from kforge.agents.collect import WINDOW_STEPS, Window, collect_windows
from kforge.agents.config import PPOConfig
from kforge.agents.evaluate import Actor, Episode, EvalOutput, evaluate, level_episodes, network_actor, run_episode
from kforge.agents.imitation import ImitationTerms, imitation_terms
from kforge.agents.networks import ActorCritic, make_network
from kforge.agents.ppo import (
    Batch,
    LossTerms,
    Selection,
    TrainOutput,
    UpdateMetrics,
    gae,
    initial_params,
    learn,
    make_optimizer,
    ppo_loss,
    train_from,
    train_level,
    train_levels,
)
from kforge.agents.segments import LevelTraining, SegmentOutput, check_segmented, put_slot, start_level, train_segments

__all__ = [
    "WINDOW_STEPS",
    "Actor",
    "ActorCritic",
    "Architecture",
    "Batch",
    "EntityTransformerPolicy",
    "Episode",
    "EvalOutput",
    "ImitationTerms",
    "LevelTraining",
    "LossTerms",
    "MLPPolicy",
    "NetworkConfig",
    "PPOConfig",
    "SegmentOutput",
    "Selection",
    "TrainOutput",
    "UpdateMetrics",
    "Window",
    "check_segmented",
    "collect_windows",
    "evaluate",
    "gae",
    "imitation_terms",
    "initial_params",
    "learn",
    "level_episodes",
    "make_bc_network",
    "make_network",
    "make_optimizer",
    "network_actor",
    "ppo_loss",
    "put_slot",
    "run_episode",
    "start_level",
    "train_from",
    "train_level",
    "train_levels",
    "train_segments",
]
