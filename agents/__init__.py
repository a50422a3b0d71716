"""RL agents that train on env tasks: PPO specialists, one parameter set per level, many levels per program.

Public surface: the config, training of a level batch, evaluation, expert windows for the dataset, training in segments
for adaptive budgets, the learner and its optimiser; for behaviour cloning, its policy networks and objective, and
episodes of any policy given as an actor function.
"""

from kforge.agents.bc_networks import Architecture, NetworkConfig, make_bc_network
from kforge.agents.collect import collect_windows
from kforge.agents.config import PPOConfig
from kforge.agents.evaluate import evaluate, network_actor, run_episode
from kforge.agents.imitation import ImitationTerms, imitation_terms
from kforge.agents.ppo import Batch, initial_params, learn, make_optimizer, train_levels
from kforge.agents.segments import check_segmented, put_slot, start_level, train_segments
from kforge.agents.stages import EVALUATE, START, stage_functions, train_in_stages

__all__ = [
    "EVALUATE",
    "START",
    "Architecture",
    "Batch",
    "ImitationTerms",
    "NetworkConfig",
    "PPOConfig",
    "check_segmented",
    "collect_windows",
    "evaluate",
    "imitation_terms",
    "initial_params",
    "learn",
    "make_bc_network",
    "make_optimizer",
    "network_actor",
    "put_slot",
    "run_episode",
    "stage_functions",
    "start_level",
    "train_levels",
    "train_in_stages",
    "train_segments",
]
