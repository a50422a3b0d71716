"""Kinetix-style tasks on the engine: levels, episodes, rewards, actions, observations, sampler, level files.

Public surface: parameters, level and state types, `reset` / `step`, action spaces and masks.
"""

from env.actions import (
    MULTI_DISCRETE_SIZES,
    NUM_DISCRETE_ACTIONS,
    ActionType,
    action_mask,
    actuator_actions,
    noop_action,
    random_action,
)
from env.episode import StepResult, advance, reset, step
from env.params import NUM_ACTION_SLOTS, NUM_MOTOR_BINDINGS, NUM_THRUSTER_BINDINGS, EnvParams, StaticEnvParams
from env.rewards import goal_reward, green_blue_distance
from env.state import NO_DISTANCE, NUM_ROLES, EnvState, Level, Role, Task, empty_task, initial_state

__all__ = [
    "MULTI_DISCRETE_SIZES",
    "NO_DISTANCE",
    "NUM_ACTION_SLOTS",
    "NUM_DISCRETE_ACTIONS",
    "NUM_MOTOR_BINDINGS",
    "NUM_ROLES",
    "NUM_THRUSTER_BINDINGS",
    "ActionType",
    "EnvParams",
    "EnvState",
    "Level",
    "Role",
    "StaticEnvParams",
    "StepResult",
    "Task",
    "action_mask",
    "actuator_actions",
    "advance",
    "empty_task",
    "goal_reward",
    "green_blue_distance",
    "initial_state",
    "noop_action",
    "random_action",
    "reset",
    "step",
]
