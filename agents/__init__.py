"""RL agents that train on env tasks: PPO specialists, one parameter set per level, many levels per program.

Public surface: the config, training of a level batch, evaluation and the dataset's expert windows (each with its plan
of how the expert plays), training in segments for adaptive budgets, and PPO fine-tuning from a BC policy
(`PPOConfig.actor`, `with_bc_actor`); for behaviour cloning, its policy networks and objective, and episodes of any
policy given as an actor function.

The PPO hyperparameters' declaration (`PPOHyperparameters`) loads without JAX, so that a job config's schema can
derive from it; every other name imports its module when first used.
"""

import importlib

from kforge.agents.hyperparameters import PPOHyperparameters

_SOURCES = {
    "kforge.agents.bc_networks": "Architecture NetworkConfig make_bc_network",
    "kforge.agents.collect": "WindowPlan collect_windows",
    "kforge.agents.config": "PPOConfig",
    "kforge.agents.episodes": "EpisodePlan evaluate network_actor run_episode",
    "kforge.agents.imitation": "ImitationTerms imitation_terms",
    "kforge.agents.networks": "with_bc_actor",
    "kforge.agents.ppo": "initial_params train_levels",
    "kforge.agents.segments": "check_segmented put_slot start_level train_segments",
}
"""Module -> the public names it defines (separated by spaces), each imported when first used."""

_MODULE_OF = {name: module for module, names in _SOURCES.items() for name in names.split()}

__all__ = [
    "Architecture",
    "EpisodePlan",
    "ImitationTerms",
    "NetworkConfig",
    "PPOConfig",
    "PPOHyperparameters",
    "WindowPlan",
    "check_segmented",
    "collect_windows",
    "evaluate",
    "imitation_terms",
    "initial_params",
    "make_bc_network",
    "network_actor",
    "put_slot",
    "run_episode",
    "start_level",
    "train_levels",
    "train_segments",
    "with_bc_actor",
]


def __getattr__(name: str):
    """A public name, imported from its module on first use (PEP 562)."""
    if name not in _MODULE_OF:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(_MODULE_OF[name]), name)
