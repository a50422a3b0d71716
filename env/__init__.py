"""Kinetix-style tasks on the engine: levels, episodes, rewards, actions, observations, sampler, level files.

Public surface: parameters, level and state types, `reset` / `step` (and the gymnax-style `Environment`),
action spaces and masks, observations, the pixel renderer and GIF export, Kinetix level files and the bundled
hand-designed levels.
"""

from kforge.env.actions import (
    MULTI_DISCRETE_SIZES,
    NUM_DISCRETE_ACTIONS,
    ActionType,
    action_mask,
    actuator_actions,
    noop_action,
    random_action,
)
from kforge.env.bundled_levels import BUNDLED_SIZES, bundled_level_path, list_levels
from kforge.env.environment import Environment
from kforge.env.episode import StepResult, advance, reset, step
from kforge.env.gif import GIF_RESOLUTION, write_state_gif
from kforge.env.kinetix_state import KinetixStateError, kinetix_leaf_specs, state_from_kinetix, state_to_kinetix
from kforge.env.level_builder import build_level
from kforge.env.level_files import LevelFileError, LoadedLevel, level_to_dict, load_level, save_level
from kforge.env.level_filter import FilterReason, FilterResult, filter_levels
from kforge.env.observations import EntityObservation, ObservationType, observation_shape, observe
from kforge.env.params import (
    NUM_ACTION_SLOTS,
    NUM_MOTOR_BINDINGS,
    NUM_THRUSTER_BINDINGS,
    EnvParams,
    StaticEnvParams,
    under_scheme,
)
from kforge.env.pixels import PIXEL_OBSERVATION_RESOLUTION, PixelObservation, pixel_observation, render_image
from kforge.env.play import GIF_FPS, record_episode
from kforge.env.rewards import goal_reward, green_blue_distance
from kforge.env.rollout import Outcome, Policy, RolloutResult, first_episode_outcomes
from kforge.env.sampler import sample_level, sample_levels
from kforge.env.state import NO_DISTANCE, NUM_ROLES, EnvState, Level, Role, Task, empty_task, initial_state

__all__ = [
    "BUNDLED_SIZES",
    "GIF_FPS",
    "GIF_RESOLUTION",
    "MULTI_DISCRETE_SIZES",
    "NO_DISTANCE",
    "NUM_ACTION_SLOTS",
    "NUM_DISCRETE_ACTIONS",
    "NUM_MOTOR_BINDINGS",
    "NUM_ROLES",
    "NUM_THRUSTER_BINDINGS",
    "PIXEL_OBSERVATION_RESOLUTION",
    "ActionType",
    "EntityObservation",
    "EnvParams",
    "EnvState",
    "Environment",
    "FilterReason",
    "FilterResult",
    "KinetixStateError",
    "Level",
    "LevelFileError",
    "LoadedLevel",
    "ObservationType",
    "Outcome",
    "PixelObservation",
    "Policy",
    "Role",
    "RolloutResult",
    "StaticEnvParams",
    "StepResult",
    "Task",
    "action_mask",
    "actuator_actions",
    "advance",
    "build_level",
    "bundled_level_path",
    "empty_task",
    "filter_levels",
    "first_episode_outcomes",
    "goal_reward",
    "green_blue_distance",
    "initial_state",
    "kinetix_leaf_specs",
    "level_to_dict",
    "list_levels",
    "load_level",
    "noop_action",
    "observation_shape",
    "observe",
    "pixel_observation",
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
