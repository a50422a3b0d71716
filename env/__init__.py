"""Kinetix-style tasks on the engine: levels, episodes, rewards, actions, observations, sampler, level files.

Public surface: parameters, level and state types, `reset` / `step` (and the gymnax-style `Environment`),
action spaces and masks, observations, the pixel renderer and GIF export, Kinetix level files and the bundled
hand-designed levels.
"""

from kforge.env.actions import MULTI_DISCRETE_SIZES, ActionType, action_mask, noop_action, random_action
from kforge.env.bundled_levels import BUNDLED_SIZES, bundled_level_path, list_levels
from kforge.env.environment import Environment
from kforge.env.episode import StepResult, advance, reset, step
from kforge.env.gif import GIF_RESOLUTION, write_state_gif
from kforge.env.kinetix_state import KinetixStateError, kinetix_leaf_specs, state_from_kinetix, state_to_kinetix
from kforge.env.level_files import level_to_dict, load_level, save_level
from kforge.env.level_filter import FilterReason, filter_levels
from kforge.env.observations import EntityObservation, ObservationType, observation_shape, observe
from kforge.env.params import NUM_ACTION_SLOTS, EnvParams, StaticEnvParams, under_scheme
from kforge.env.pixels import render_image
from kforge.env.play import record_episode
from kforge.env.rollout import Policy
from kforge.env.sampler import sample_level, sample_levels
from kforge.env.sampler_shapes import DISC_INERTIA_SHARE
from kforge.env.state import EnvState, Level, Role, empty_task, initial_state

__all__ = [
    "BUNDLED_SIZES",
    "DISC_INERTIA_SHARE",
    "GIF_RESOLUTION",
    "MULTI_DISCRETE_SIZES",
    "NUM_ACTION_SLOTS",
    "ActionType",
    "EntityObservation",
    "EnvParams",
    "EnvState",
    "Environment",
    "FilterReason",
    "KinetixStateError",
    "Level",
    "ObservationType",
    "Policy",
    "Role",
    "StaticEnvParams",
    "StepResult",
    "action_mask",
    "advance",
    "bundled_level_path",
    "empty_task",
    "filter_levels",
    "initial_state",
    "kinetix_leaf_specs",
    "level_to_dict",
    "list_levels",
    "load_level",
    "noop_action",
    "observation_shape",
    "observe",
    "random_action",
    "record_episode",
    "render_image",
    "reset",
    "sample_level",
    "sample_levels",
    "save_level",
    "state_from_kinetix",
    "state_to_kinetix",
    "step",
    "under_scheme",
    "write_state_gif",
]
