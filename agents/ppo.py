"""PPO specialists: one parameter set per level, many levels trained in one program (vmap over levels).

`train_level` is one pure function of (level, key): nested `lax.scan`s over updates, rollout steps, epochs and
minibatches, with no reduction across levels, so in `train_levels` (its vmap over a leading level axis) a level's
training never depends on the other levels of its batch: bit for bit within one batch size, to rounding across
sizes (XLA's CPU code vectorises some reductions differently by batch size). GAE and the loss are top-level
functions so they can be tested alone.

Expert selection: every `PPOConfig.select_every_updates` updates and after the last, the policy plays
`select_episodes` episodes from the level's start (drawn from their own key stream, so evaluating never changes the
training), and training returns the parameters of the best evaluation. Long budgets need it: with a constant
learning rate, some policies that had solved their level unlearnt it later in training.

Time limits: with `PPOConfig.bootstrap_truncation`, an episode cut by `StaticEnvParams.max_timesteps`
(`StepResult.truncated`) bootstraps its last step from the value of the state it reached (observed before the
auto-reset); otherwise (the default) the time limit is terminal like success, failure and instability. Kinetix
observations carry no time and a level counts as solved only within the limit, so the default treats it as part of the
task: bootstrapping made a slow approach look as valuable as reaching the goal, and policies that had learnt the test
thruster level unlearnt it.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from kforge.agents import policy
from kforge.agents.batching import ACTION_TYPE, check_level_keys, num_levels
from kforge.agents.config import PPOConfig
from kforge.agents.episodes import EpisodePlan, level_episodes
from kforge.agents.networks import make_network
from kforge.env import (
    EnvParams,
    EnvState,
    Level,
    StaticEnvParams,
    StepResult,
    action_mask,
    advance,
    observation_shape,
    observe,
    reset,
)

ADVANTAGE_NORM_EPS = 1e-8
"""Added to the minibatch advantage standard deviation before dividing by it."""

SELECTION_STREAM = 0x5E1EC7
"""Folded into a level's training key to draw its evaluation episodes, apart from the training randomness (so a
run's rollouts and updates are the same whether or not, and how often, it is evaluated)."""


# --------------------------------------------------------------------------- data carried through training
class Transition(NamedTuple):
    """One env step of every env of a level (leading axes (num_steps, num_envs) in a rollout)."""

    obs: jnp.ndarray  # (D,) f32 observation the action was chosen from
    next_obs: jnp.ndarray  # (D,) f32 observation of the state the step reached, before any auto-reset
    action: jnp.ndarray  # (6,) i32 multi-discrete action
    log_prob: jnp.ndarray  # () f32 log-probability of the action under the acting policy
    reward: jnp.ndarray  # () f32
    done: jnp.ndarray  # () bool: the episode ended at this step
    truncated: jnp.ndarray  # () bool: ended by the time limit only
    success: jnp.ndarray  # () bool
    episode_return: jnp.ndarray  # () f32 undiscounted return of the episode so far, this step included
    episode_length: jnp.ndarray  # () i32 env steps of the episode so far, this step included


class Batch(NamedTuple):
    """Samples of an update, flattened over (num_steps, num_envs)."""

    obs: jnp.ndarray  # (B, D) f32
    action: jnp.ndarray  # (B, 6) i32
    log_prob: jnp.ndarray  # (B,) f32 log-probability under the acting policy
    value: jnp.ndarray  # (B,) f32 value under the acting parameters
    advantage: jnp.ndarray  # (B,) f32 GAE advantage (normalised per minibatch in the loss)
    target: jnp.ndarray  # (B,) f32 value target: advantage + value


class LossTerms(NamedTuple):
    """The PPO loss and its parts, averaged over a minibatch."""

    total: jnp.ndarray  # actor + vf_coef * value - ent_coef * entropy
    actor: jnp.ndarray  # clipped surrogate, negated
    value: jnp.ndarray  # 0.5 * clipped squared value error
    entropy: jnp.ndarray  # [nats] policy entropy over valid slots
    approx_kl: jnp.ndarray  # estimate of KL(old || new): mean((ratio - 1) - log ratio)
    clip_fraction: jnp.ndarray  # share of samples whose ratio left [1 - clip_eps, 1 + clip_eps]


class UpdateMetrics(NamedTuple):
    """What one update saw and did; episode figures cover the episodes that ended in its rollout (NaN if none)."""

    episodes: jnp.ndarray  # () i32 episodes that ended during the rollout
    mean_return: jnp.ndarray  # () f32 undiscounted return of those episodes
    success_rate: jnp.ndarray  # () f32 share of them that ended in success
    mean_length: jnp.ndarray  # () f32 [env steps]
    loss: LossTerms  # averaged over epochs and minibatches


class Selection(NamedTuple):
    """The policy's evaluations during training (at `PPOConfig.selection_updates`) and the one whose parameters
    training returns: the highest success rate, the latest on ties."""

    env_steps: jnp.ndarray  # (C,) i32 env steps trained when each evaluation ran
    success_rate: jnp.ndarray  # (C,) f32 share of the `select_episodes` episodes from the start that succeeded
    mean_return: jnp.ndarray  # (C,) f32 their mean undiscounted return
    best: jnp.ndarray  # () i32 index of the evaluation whose parameters are returned

    def at_best(self, values) -> np.ndarray:
        """Per-evaluation `values` (..., C), e.g. `success_rate`, at the chosen evaluation (...), on the host."""
        return np.take_along_axis(np.asarray(values), np.asarray(self.best)[..., None], axis=-1)[..., 0]


class TrainOutput(NamedTuple):
    """Result of training; `train_levels` adds a leading level axis to every leaf."""

    params: dict  # network parameters of the best evaluation (`selection.best`)
    metrics: UpdateMetrics  # leaves (num_updates,): learning curves
    selection: Selection


class _Best(NamedTuple):
    params: dict
    success_rate: jnp.ndarray  # () f32
    index: jnp.ndarray  # () i32


class _TrainCarry(NamedTuple):
    params: dict
    opt_state: optax.OptState
    env_state: EnvState  # (E, ...) current state of every env
    obs: jnp.ndarray  # (E, D) its observation
    episode_return: jnp.ndarray  # (E,) f32 return of the running episodes
    key: jax.Array


# --------------------------------------------------------------------------- GAE and loss
def gae(
    rewards: jnp.ndarray,
    values: jnp.ndarray,
    next_values: jnp.ndarray,
    terminals: jnp.ndarray,
    dones: jnp.ndarray,
    gamma: float,
    gae_lambda: float,
) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Generalised advantage estimates and value targets, both shaped like `rewards` (time-major, (T, ...)).

    `next_values[t]` is the value of the state step t reached (before any reset); it is used unless `terminals[t]`.
    The sum over later steps stops where `dones[t]` (terminal or truncated): A_t = d_t + gamma * lambda * A_{t+1},
    d_t = r_t + gamma * V'_t - V_t.
    """
    deltas = rewards + gamma * jnp.where(terminals, 0.0, next_values) - values

    def backwards(next_advantage, step):
        delta, done = step
        advantage = delta + gamma * gae_lambda * jnp.where(done, 0.0, next_advantage)
        return advantage, advantage

    _, advantages = jax.lax.scan(backwards, jnp.zeros_like(rewards[0]), (deltas, dones), reverse=True)
    return advantages, advantages + values


def ppo_loss(
    params, apply_fn: Callable, batch: Batch, mask: jnp.ndarray, config: PPOConfig
) -> tuple[jnp.ndarray, LossTerms]:
    """Clipped-surrogate PPO loss of a minibatch, with clipped value loss and entropy bonus.

    `apply_fn(params, obs) -> (logits (B, 16), values (B,))`; `mask` (6,) is the level's action mask.
    Advantages are normalised over the minibatch.
    """
    logits, values = apply_fn(params, batch.obs)
    log_probs = policy.log_prob(logits, batch.action, mask)
    log_ratio = log_probs - batch.log_prob
    ratio = jnp.exp(log_ratio)
    advantage = (batch.advantage - batch.advantage.mean()) / (batch.advantage.std() + ADVANTAGE_NORM_EPS)
    clipped_ratio = jnp.clip(ratio, 1.0 - config.clip_eps, 1.0 + config.clip_eps)
    actor = -jnp.mean(jnp.minimum(ratio * advantage, clipped_ratio * advantage))

    clipped_values = batch.value + jnp.clip(values - batch.value, -config.clip_eps, config.clip_eps)
    value = 0.5 * jnp.mean(jnp.maximum((values - batch.target) ** 2, (clipped_values - batch.target) ** 2))

    entropy = jnp.mean(policy.entropy(logits, mask))
    total = actor + config.vf_coef * value - config.ent_coef * entropy
    terms = LossTerms(
        total=total,
        actor=actor,
        value=value,
        entropy=entropy,
        approx_kl=jnp.mean((ratio - 1.0) - log_ratio),
        clip_fraction=jnp.mean(jnp.abs(ratio - 1.0) > config.clip_eps),
    )
    return total, terms


# --------------------------------------------------------------------------- env interaction
def env_step(
    state: EnvState, action: jnp.ndarray, level: Level, env_params: EnvParams, static: StaticEnvParams
) -> tuple[EnvState, EnvState, StepResult]:
    """(state to continue from, state the step reached before any reset, result); resets to `level` when done."""
    reached, result = advance(state, action, env_params, static, ACTION_TYPE)
    following = jax.tree.map(lambda fresh, old: jnp.where(result.done, fresh, old), reset(level), reached)
    return following, reached, result


def make_optimizer(config: PPOConfig) -> optax.GradientTransformation:
    """Adam after global-norm gradient clipping."""
    return optax.chain(
        optax.clip_by_global_norm(config.max_grad_norm), optax.adam(config.learning_rate, eps=config.adam_eps)
    )


def _tile(tree, count: int):
    return jax.tree.map(lambda x: jnp.broadcast_to(x, (count,) + x.shape), tree)


def _mean_where(values: jnp.ndarray, where: jnp.ndarray) -> jnp.ndarray:
    count = jnp.sum(where)
    return jnp.where(count > 0, jnp.sum(jnp.where(where, values, 0.0)) / jnp.maximum(count, 1), jnp.nan)


def learn(
    params, opt_state, batch: Batch, key: jax.Array, mask: jnp.ndarray, config: PPOConfig
) -> tuple[Any, Any, LossTerms]:
    """The learner's part of one PPO update: `config.update_epochs` passes over `batch` (one update's samples,
    leading axis `config.steps_per_update`), each in `config.num_minibatches` shuffled minibatches with one Adam
    step per minibatch; `mask` (6,) is the level's action mask. Returns the new parameters and optimiser state and
    the loss terms of every minibatch step, shaped (epochs, minibatches)."""
    network = make_network(config)
    optimizer = make_optimizer(config)

    def sgd_step(params_and_opt, minibatch: Batch):
        params, opt_state = params_and_opt
        grads, terms = jax.grad(ppo_loss, has_aux=True)(params, network.apply, minibatch, mask, config)
        updates, opt_state = optimizer.update(grads, opt_state, params)
        return (optax.apply_updates(params, updates), opt_state), terms

    def epoch(params_and_opt, epoch_key):
        order = jax.random.permutation(epoch_key, config.steps_per_update)
        minibatches = jax.tree.map(
            lambda x: x[order].reshape((config.num_minibatches, config.minibatch_size) + x.shape[1:]), batch
        )
        return jax.lax.scan(sgd_step, params_and_opt, minibatches)

    (params, opt_state), terms = jax.lax.scan(epoch, (params, opt_state), jax.random.split(key, config.update_epochs))
    return params, opt_state, terms


# --------------------------------------------------------------------------- training of one level
def initial_params(key: jax.Array, config: PPOConfig, static: StaticEnvParams):
    """Fresh network parameters for the observations of `static`'s size."""
    obs = observation_shape(static, config.observation_type)
    return make_network(config).init(key, jnp.zeros(obs.shape, obs.dtype))


def train_level(
    level: Level, key: jax.Array, config: PPOConfig, env_params: EnvParams, static: StaticEnvParams
) -> TrainOutput:
    """PPO on one level from fresh parameters drawn from `key`; pure and deterministic in (level, key)."""
    init_key, run_key = jax.random.split(key)
    return train_from(level, initial_params(init_key, config, static), run_key, config, env_params, static)


def train_from(
    level: Level,
    params,
    key: jax.Array,
    config: PPOConfig,
    env_params: EnvParams,
    static: StaticEnvParams,
) -> TrainOutput:
    """PPO on one level starting from `params`, with the randomness of rollouts and minibatches drawn from `key`."""
    train_and_evaluate = _segment_program(level, config, env_params, static)
    carry = _initial_carry(level, params, key, config, static)
    selection_key = jax.random.fold_in(key, SELECTION_STREAM)
    best = _Best(params, jnp.array(-jnp.inf, jnp.float32), jnp.array(-1, jnp.int32))
    points = config.selection_updates
    every = points[0]
    regular = config.num_updates // every  # evaluations after `every` updates each; one more after a remainder

    def regular_segment(state, index):
        carry, best, metrics, evaluation = train_and_evaluate(*state, index, (index + 1) * every, selection_key, every)
        return (carry, best), (metrics, evaluation)

    (carry, best), (metrics, evaluations) = jax.lax.scan(
        regular_segment, (carry, best), jnp.arange(regular, dtype=jnp.int32)
    )
    metrics = jax.tree.map(lambda x: x.reshape((regular * every,) + x.shape[2:]), metrics)
    if len(points) > regular:
        carry, best, last_metrics, last = train_and_evaluate(
            carry,
            best,
            jnp.int32(regular),
            config.num_updates,
            selection_key,
            config.num_updates - regular * every,
        )
        metrics = jax.tree.map(lambda a, b: jnp.concatenate([a, b]), metrics, last_metrics)
        evaluations = jax.tree.map(lambda a, b: jnp.concatenate([a, b[None]]), evaluations, last)
    selection = Selection(
        env_steps=jnp.asarray(points, jnp.int32) * config.steps_per_update,
        success_rate=evaluations[0],
        mean_return=evaluations[1],
        best=best.index,
    )
    return TrainOutput(params=best.params, metrics=metrics, selection=selection)


def _initial_carry(level: Level, params, key: jax.Array, config: PPOConfig, static: StaticEnvParams) -> _TrainCarry:
    """Training state before the first update: every env at the level's start."""
    start = reset(level)
    start_obs = observe(start, static, config.observation_type)
    return _TrainCarry(
        params=params,
        opt_state=make_optimizer(config).init(params),
        env_state=_tile(start, config.num_envs),
        obs=_tile(start_obs, config.num_envs),
        episode_return=jnp.zeros((config.num_envs,), jnp.float32),
        key=key,
    )


def _segment_program(level: Level, config: PPOConfig, env_params: EnvParams, static: StaticEnvParams) -> Callable:
    """`train_and_evaluate(carry, best, index, updates_done, selection_key, num_updates)` on `level`:
    `num_updates` PPO updates (`_update_program`), then evaluation `index` of the policy (`_evaluation_program`);
    returns (carry, best, per-update metrics, (success rate, mean return) of the evaluation)."""
    updates = _update_program(level, config, env_params, static)
    evaluate_and_keep = _evaluation_program(level, config, env_params, static)

    def train_and_evaluate(carry: _TrainCarry, best: _Best, index, updates_done, selection_key, num_updates: int):
        carry, metrics = updates(carry, num_updates)
        best, evaluation = evaluate_and_keep(carry.params, best, index, updates_done, selection_key)
        return carry, best, metrics, evaluation

    return train_and_evaluate


def _update_program(level: Level, config: PPOConfig, env_params: EnvParams, static: StaticEnvParams) -> Callable:
    """`updates(carry, num_updates)` on `level`: `num_updates` PPO updates; returns (carry, per-update metrics)."""
    return _LevelUpdates(level, config, env_params, static)


class _LevelUpdates:
    """PPO updates on one level: a rollout of every env (auto-reset at the level's start), its advantages, and the
    learner's epochs over it; called as `updates(carry, num_updates)`."""

    def __init__(self, level: Level, config: PPOConfig, env_params: EnvParams, static: StaticEnvParams):
        self.level, self.config, self.env_params, self.static = level, config, env_params, static
        self.network = make_network(config)
        self.mask = action_mask(level)
        self.start_obs = observe(reset(level), static, config.observation_type)

    def __call__(self, carry: _TrainCarry, num_updates: int) -> tuple[_TrainCarry, UpdateMetrics]:
        return jax.lax.scan(self.update, carry, None, length=num_updates)

    def update(self, carry: _TrainCarry, _) -> tuple[_TrainCarry, UpdateMetrics]:
        """One PPO update: a rollout of `config.num_steps` steps, then the learner on its samples."""
        key, rollout_key, epochs_key = jax.random.split(carry.key, 3)
        carry, rollout = jax.lax.scan(
            self.act_and_step, carry._replace(key=key), jax.random.split(rollout_key, self.config.num_steps)
        )
        batch = self.batch(carry.params, rollout)
        params, opt_state, terms = learn(carry.params, carry.opt_state, batch, epochs_key, self.mask, self.config)
        return carry._replace(params=params, opt_state=opt_state), _update_metrics(rollout, terms)

    def act_and_step(self, carry: _TrainCarry, step_key) -> tuple[_TrainCarry, Transition]:
        """Every env acts on the policy with `carry.params` and steps, resetting when its episode ends."""
        static, observation_type = self.static, self.config.observation_type
        logits, _ = self.network.apply(carry.params, carry.obs)
        action = policy.sample(step_key, logits, self.mask)
        log_prob = policy.log_prob(logits, action, self.mask)
        following, reached, result = jax.vmap(env_step, in_axes=(0, 0, None, None, None))(
            carry.env_state, action, self.level, self.env_params, static
        )
        next_obs = jax.vmap(observe, in_axes=(0, None, None))(reached, static, observation_type)
        episode_return = carry.episode_return + result.reward
        transition = Transition(
            obs=carry.obs,
            next_obs=next_obs,
            action=action,
            log_prob=log_prob,
            reward=result.reward,
            done=result.done,
            truncated=result.truncated,
            success=result.success,
            episode_return=episode_return,
            episode_length=reached.timestep,
        )
        carry = carry._replace(
            env_state=following,
            obs=jnp.where(result.done[:, None], self.start_obs, next_obs),
            episode_return=jnp.where(result.done, 0.0, episode_return),
        )
        return carry, transition

    def batch(self, params, rollout: Transition) -> Batch:
        """The rollout's samples, flattened over (steps, envs), with their values, advantages and targets."""
        config = self.config
        _, values = self.network.apply(params, rollout.obs)
        _, next_values = self.network.apply(params, rollout.next_obs)
        terminals = rollout.done & ~rollout.truncated if config.bootstrap_truncation else rollout.done
        advantages, targets = gae(
            rollout.reward, values, next_values, terminals, rollout.done, config.gamma, config.gae_lambda
        )
        flat = functools.partial(jax.tree.map, lambda x: x.reshape((config.steps_per_update,) + x.shape[2:]))
        return flat(Batch(rollout.obs, rollout.action, rollout.log_prob, values, advantages, targets))


def _update_metrics(rollout: Transition, terms: LossTerms) -> UpdateMetrics:
    """What an update saw (the episodes that ended in its rollout) and its loss terms, averaged."""
    return UpdateMetrics(
        episodes=jnp.sum(rollout.done).astype(jnp.int32),
        mean_return=_mean_where(rollout.episode_return, rollout.done),
        success_rate=_mean_where(rollout.success.astype(jnp.float32), rollout.done),
        mean_length=_mean_where(rollout.episode_length.astype(jnp.float32), rollout.done),
        loss=jax.tree.map(jnp.mean, terms),
    )


def _evaluation_program(level: Level, config: PPOConfig, env_params: EnvParams, static: StaticEnvParams) -> Callable:
    """`evaluate_and_keep(params, best, index, updates_done, selection_key)` on `level`: evaluation `index` of the
    policy, kept as best unless a better one was; returns (best, (success rate, mean return) of the evaluation).
    The episodes' key depends on the updates done, so a policy gets the same episodes whatever the period."""
    start = reset(level)
    plan = EpisodePlan(config, static, config.select_episodes, config.select_greedy)

    def evaluate_and_keep(params, best: _Best, index, updates_done, selection_key):
        key = jax.random.fold_in(selection_key, updates_done)
        episodes = level_episodes(params, level, start, key, plan, env_params)
        success_rate = jnp.mean(episodes.success.astype(jnp.float32))
        better = success_rate >= best.success_rate
        best = jax.tree.map(lambda new, old: jnp.where(better, new, old), _Best(params, success_rate, index), best)
        return best, (success_rate, jnp.mean(episodes.episode_return))

    return evaluate_and_keep


@functools.partial(jax.jit, static_argnames=("config", "static"))
def train_levels(
    levels: Level,
    keys: jax.Array,
    config: PPOConfig,
    env_params: EnvParams,
    static: StaticEnvParams,
    params=None,
) -> TrainOutput:
    """`train_level` on every level of a batch (leading axis L) with its own key; outputs gain a leading L axis.

    `params`: each level's starting parameters (leading axis L; e.g. a BC policy's, through `with_bc_actor`), to
    fine-tune instead of training from fresh ones. The rollouts and minibatches draw the same randomness from `keys`
    either way, so a fine-tuned level and its fresh twin differ only in where they start.

    Fresh parameters are drawn level after level (`lax.map`, not `vmap`): a batched orthogonal initialisation
    runs LAPACK QR on XLA's CPU thread pool, which deadlocked with two such calls in flight on a 2-core machine.
    """
    check_level_keys(keys, num_levels(levels))
    split = jax.vmap(jax.random.split)(keys)
    if params is None:
        params = jax.lax.map(lambda key: initial_params(key, config, static), split[:, 0])
    return jax.vmap(lambda level, level_params, key: train_from(level, level_params, key, config, env_params, static))(
        levels, params, split[:, 1]
    )
