"""The PPO hyperparameters of a specialist, declared once and importable without JAX: `PPOConfig` extends them, and a
job config's `ppo` section is generated from them."""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass(frozen=True)
class PPOHyperparameters:
    """Hyperparameters of PPO on one level; each field's default and meaning is on its line (evidence for the values:
    docs/experts.md).

    The budget is given in env steps per level; the number of updates derives from it:
    `env_steps_per_level = num_envs * num_steps * num_updates`. The policy is evaluated every
    `select_every_updates` updates and after the last (`selection_updates`); training returns the parameters of the
    best evaluation, so a policy that unlearns late keeps what it had learnt.
    """

    env_steps_per_level: int = 1_000_000  # budget: env steps collected per level over the whole training
    num_envs: int = 16  # parallel episodes per level
    num_steps: int = 125  # env steps per env between two updates (rollout length)
    update_epochs: int = 4  # passes over each rollout
    num_minibatches: int = 4  # minibatches per epoch; must divide num_envs * num_steps
    learning_rate: float = 3e-4  # Adam step size, constant
    adam_eps: float = 1e-5  # Adam epsilon (Kinetix)
    max_grad_norm: float = 1.0  # global-norm gradient clipping before Adam (Kinetix)
    gamma: float = 0.995  # discount per env step (Kinetix)
    gae_lambda: float = 0.9  # GAE lambda (Kinetix)
    clip_eps: float = 0.2  # PPO ratio clip, also the value-clipping range (Kinetix)
    ent_coef: float = 0.01  # entropy bonus weight (Kinetix)
    vf_coef: float = 0.5  # value loss weight (Kinetix)
    hidden_size: int = 64  # units per hidden layer, actor and critic (Kinetix: 128)
    num_hidden_layers: int = 2  # tanh hidden layers of each MLP (Kinetix: 5)
    bootstrap_truncation: bool = False  # time-limit ends bootstrap from the last value
    select_every_updates: int = 50  # evaluate every this many updates and after the last; 0: after the last only
    select_episodes: int = 16  # episodes from the level's start per evaluation
    select_greedy: bool = False  # evaluation episodes act with the most probable choice per slot instead of sampling

    def __post_init__(self):
        name = type(self).__name__
        positive = (
            "env_steps_per_level num_envs num_steps update_epochs num_minibatches hidden_size num_hidden_layers "
            "select_episodes"
        ).split()
        for key in positive:
            value = getattr(self, key)
            if not (isinstance(value, int) and value > 0):
                raise ValueError(f"{name}.{key} must be a positive int, got {value!r}")
        if not (isinstance(self.select_every_updates, int) and self.select_every_updates >= 0):
            raise ValueError(f"{name}.select_every_updates must be an int >= 0, got {self.select_every_updates!r}")
        for key in ("learning_rate", "adam_eps", "max_grad_norm", "clip_eps"):
            if not getattr(self, key) > 0:
                raise ValueError(f"{name}.{key} must be > 0, got {getattr(self, key)!r}")
        for key in ("gamma", "gae_lambda"):
            if not 0.0 <= getattr(self, key) <= 1.0:
                raise ValueError(f"{name}.{key} must lie in [0, 1], got {getattr(self, key)!r}")
        for key in ("ent_coef", "vf_coef"):
            if not getattr(self, key) >= 0:
                raise ValueError(f"{name}.{key} must be >= 0, got {getattr(self, key)!r}")
        self._check_budget(name)

    def _check_budget(self, name: str) -> None:
        steps = f"num_envs * num_steps = {self.num_envs} * {self.num_steps} = {self.steps_per_update}"
        if self.env_steps_per_level < self.steps_per_update:
            raise ValueError(
                f"{name}.env_steps_per_level ({self.env_steps_per_level}) is smaller than one update's {steps}"
            )
        if self.env_steps_per_level % self.steps_per_update:
            raise ValueError(f"{name}.env_steps_per_level ({self.env_steps_per_level}) is not a multiple of {steps}")
        if self.steps_per_update % self.num_minibatches:
            raise ValueError(
                f"{name}.num_minibatches ({self.num_minibatches}) does not divide "
                f"num_envs * num_steps = {self.steps_per_update}"
            )

    @property
    def steps_per_update(self) -> int:
        """Env steps collected per level between two updates."""
        return self.num_envs * self.num_steps

    @property
    def num_updates(self) -> int:
        """PPO updates per level: the budget divided by the steps per update."""
        return self.env_steps_per_level // self.steps_per_update

    @property
    def selection_updates(self) -> tuple[int, ...]:
        """Updates done at each evaluation of the policy: every `select_every_updates` and after the last."""
        every = self.select_every_updates or self.num_updates
        points = tuple(range(every, self.num_updates + 1, every))
        return points if points and points[-1] == self.num_updates else (*points, self.num_updates)

    @property
    def minibatch_size(self) -> int:
        return self.steps_per_update // self.num_minibatches
