"""Kinetix's own PPO training throughput, run inside a separate virtualenv holding kinetix-env (see benchmarks/ppo.py).

kinetix-env on PyPI does not ship Kinetix's experiments/ppo.py, so `make_train` below re-states its PureJaxRL loop
(FLAIROx/Kinetix experiments/ppo.py; settings in docs/kinetix.md, PPO settings) with the package's own pieces:
`make_kinetix_env` with auto-reset wrapped in `LogWrapper`, the network from `make_network_from_config` (symbolic
flat observations: Dense(width) + ReLU, then separate tanh actor and critic MLPs), `ScannedRNN` carries, a
`TrainState` with Adam after global-norm clipping. Kept as in ppo.py: one network call per env step giving action,
log-probability and value; GAE with the value of the last observation; `update_epochs` epochs, each permuting the
*envs* and splitting them into `num_minibatches` minibatches (so num_envs % num_minibatches == 0); the per-update
episode metrics over `info`. Changed for a specialist on one level: every env starts on, and auto-resets to, the
same level, passed as Kinetix's `override_reset_state` (ppo.py samples a new random level at every reset); no
wandb logging, evaluation or video. Prints one JSON document. Not importable from the project's environment.

    python -m benchmarks.kinetix_ppo_baseline --size s --num-envs 16 --num-steps 125 --updates 4
"""

from __future__ import annotations

import argparse
import json
import time
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax.training.train_state import TrainState
from kinetix.environment import (
    ActionType,
    EnvParams,
    LogWrapper,
    ObservationType,
    make_kinetix_env,
    static_env_params_from_size,
)
from kinetix.environment.ued.ued import make_reset_fn_sample_kinetix_level
from kinetix.models import ScannedRNN, make_network_from_config

from benchmarks.timing import best_time  # needs only jax

KINETIX_NUM_ENVS = 2048
"""Parallel envs of Kinetix's configs/learning/ppo-base.yaml (num_train_envs)."""

KINETIX_NUM_STEPS = 64
"""Rollout length per update of Kinetix's configs/learning/ppo-rnn.yaml."""

KINETIX_NUM_MINIBATCHES = 32
KINETIX_UPDATE_EPOCHS = 8
"""configs/learning/ppo-base.yaml."""

KINETIX_WIDTH = 128
KINETIX_DEPTH = 5
"""Hidden units and tanh layers of the actor and of the critic (Kinetix's model-base)."""

KINETIX_LEARNING_RATE = 5e-5
KINETIX_MAX_GRAD_NORM = 1.0
KINETIX_GAMMA, KINETIX_GAE_LAMBDA = 0.995, 0.9
KINETIX_CLIP_EPS, KINETIX_ENT_COEF, KINETIX_VF_COEF = 0.2, 0.01, 0.5
ADAM_EPS = 1e-5
"""Kinetix's PPO settings that do not change the amount of work per env step (docs/kinetix.md, PPO settings)."""


class Transition(NamedTuple):
    """One env step of every env, as ppo.py stores it."""

    done: jnp.ndarray
    action: jnp.ndarray
    value: jnp.ndarray
    reward: jnp.ndarray
    log_prob: jnp.ndarray
    obs: Any
    info: Any


def make_network(env, env_params, static_env_params, width: int, depth: int):
    """Kinetix's actor-critic for symbolic flat observations and multi-discrete actions, without recurrence."""
    config = {
        "action_type": ActionType.MULTI_DISCRETE,
        "observation_type": ObservationType.SYMBOLIC_FLAT,
        "static_env_params": {
            "num_motor_bindings": static_env_params.num_motor_bindings,
            "num_thruster_bindings": static_env_params.num_thruster_bindings,
        },
        "recurrent_model": False,
        "actor_width": width,
        "critic_width": width,
        "actor_depth": depth,
        "critic_depth": depth,
        "activation": "tanh",
    }
    return make_network_from_config(env, env_params, config, network_kws={})


def make_train(args, env, env_params, network):
    """`train(rng, level)`: `args.updates` PPO updates on `level`, as in Kinetix's experiments/ppo.py."""
    num_envs, num_steps = args.num_envs, args.num_steps
    tx = optax.chain(optax.clip_by_global_norm(KINETIX_MAX_GRAD_NORM), optax.adam(KINETIX_LEARNING_RATE, eps=ADAM_EPS))

    def train(rng, level):
        rng, _rng = jax.random.split(rng)
        obsv, env_state = jax.vmap(env.reset, (0, None, None))(jax.random.split(_rng, num_envs), env_params, level)
        dones = jnp.zeros((num_envs,), dtype=jnp.bool_)
        rng, _rng = jax.random.split(rng)
        init_hstate = ScannedRNN.initialize_carry(num_envs)
        network_params = network.init(_rng, init_hstate, jax.tree.map(lambda x: x[None, ...], (obsv, dones)))
        train_state = TrainState.create(apply_fn=network.apply, params=network_params, tx=tx)

        def _update_step(runner_state, unused):
            def _env_step(runner_state, unused):
                train_state, env_state, last_obs, last_done, hstate, rng, update_step = runner_state
                rng, _rng = jax.random.split(rng)
                ac_in = (jax.tree.map(lambda x: x[np.newaxis, :], last_obs), last_done[np.newaxis, :])
                hstate, pi, value = network.apply(train_state.params, hstate, ac_in)
                action = pi.sample(seed=_rng)
                log_prob = pi.log_prob(action)
                value, action, log_prob = value.squeeze(0), action.squeeze(0), log_prob.squeeze(0)

                rng, _rng = jax.random.split(rng)
                obsv, env_state, reward, done, info = jax.vmap(env.step, in_axes=(0, 0, 0, None, None))(
                    jax.random.split(_rng, num_envs), env_state, action, env_params, level
                )
                transition = Transition(last_done, action, value, reward, log_prob, last_obs, info)
                return (train_state, env_state, obsv, done, hstate, rng, update_step), transition

            initial_hstate = runner_state[-3]
            runner_state, traj_batch = jax.lax.scan(_env_step, runner_state, None, num_steps)

            train_state, env_state, last_obs, last_done, hstate, rng, update_step = runner_state
            ac_in = (jax.tree.map(lambda x: x[np.newaxis, :], last_obs), last_done[np.newaxis, :])
            _, _, last_val = network.apply(train_state.params, hstate, ac_in)
            last_val = last_val.squeeze(0)

            def _get_advantages(carry, transition):
                gae, next_value, next_done = carry
                delta = transition.reward + KINETIX_GAMMA * next_value * (1 - next_done) - transition.value
                gae = delta + KINETIX_GAMMA * KINETIX_GAE_LAMBDA * (1 - next_done) * gae
                return (gae, transition.value, transition.done), gae

            _, advantages = jax.lax.scan(
                _get_advantages, (jnp.zeros_like(last_val), last_val, last_done), traj_batch, reverse=True, unroll=16
            )
            targets = advantages + traj_batch.value

            def _update_epoch(update_state, unused):
                def _update_minbatch(train_state, batch_info):
                    init_hstate, traj_batch, advantages, targets = batch_info

                    def _loss_fn(params, init_hstate, traj_batch, gae, targets):
                        _, pi, value = network.apply(params, init_hstate[0], (traj_batch.obs, traj_batch.done))
                        log_prob = pi.log_prob(traj_batch.action)
                        value_pred_clipped = traj_batch.value + (value - traj_batch.value).clip(
                            -KINETIX_CLIP_EPS, KINETIX_CLIP_EPS
                        )
                        value_losses = jnp.square(value - targets)
                        value_losses_clipped = jnp.square(value_pred_clipped - targets)
                        value_loss = 0.5 * jnp.maximum(value_losses, value_losses_clipped).mean()
                        ratio = jnp.exp(log_prob - traj_batch.log_prob)
                        gae = (gae - gae.mean()) / (gae.std() + 1e-8)
                        loss_actor = -jnp.minimum(
                            ratio * gae, jnp.clip(ratio, 1.0 - KINETIX_CLIP_EPS, 1.0 + KINETIX_CLIP_EPS) * gae
                        ).mean()
                        entropy = pi.entropy().mean()
                        total_loss = loss_actor + KINETIX_VF_COEF * value_loss - KINETIX_ENT_COEF * entropy
                        return total_loss, (value_loss, loss_actor, entropy)

                    grad_fn = jax.value_and_grad(_loss_fn, has_aux=True)
                    total_loss, grads = grad_fn(train_state.params, init_hstate, traj_batch, advantages, targets)
                    return train_state.apply_gradients(grads=grads), total_loss

                train_state, init_hstate, traj_batch, advantages, targets, rng = update_state
                rng, _rng = jax.random.split(rng)
                permutation = jax.random.permutation(_rng, num_envs)
                batch = (init_hstate, traj_batch, advantages, targets)
                shuffled_batch = jax.tree.map(lambda x: jnp.take(x, permutation, axis=1), batch)
                minibatches = jax.tree.map(
                    lambda x: jnp.swapaxes(
                        jnp.reshape(x, [x.shape[0], args.num_minibatches, -1] + list(x.shape[2:])), 1, 0
                    ),
                    shuffled_batch,
                )
                train_state, total_loss = jax.lax.scan(_update_minbatch, train_state, minibatches)
                return (train_state, init_hstate, traj_batch, advantages, targets, rng), total_loss

            update_state = (train_state, initial_hstate[None, :], traj_batch, advantages, targets, rng)
            update_state, loss_info = jax.lax.scan(_update_epoch, update_state, None, args.update_epochs)
            train_state, rng = update_state[0], update_state[-1]
            metric = jax.tree.map(
                lambda x: (x * traj_batch.info["returned_episode"]).sum() / traj_batch.info["returned_episode"].sum(),
                traj_batch.info,
            )
            return (train_state, env_state, last_obs, last_done, hstate, rng, update_step + 1), metric

        rng, _rng = jax.random.split(rng)
        runner_state = (train_state, env_state, obsv, jnp.zeros((num_envs,), dtype=bool), init_hstate, _rng, 0)
        runner_state, metric = jax.lax.scan(_update_step, runner_state, None, args.updates)
        return {"runner_state": runner_state, "metric": metric}

    return train


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", default="s", choices=["s", "m", "l"])
    parser.add_argument("--num-envs", type=int, default=KINETIX_NUM_ENVS, help="a multiple of --num-minibatches")
    parser.add_argument("--num-steps", type=int, default=KINETIX_NUM_STEPS, help="env steps per env per update")
    parser.add_argument("--num-minibatches", type=int, default=KINETIX_NUM_MINIBATCHES)
    parser.add_argument("--update-epochs", type=int, default=KINETIX_UPDATE_EPOCHS)
    parser.add_argument("--width", type=int, default=KINETIX_WIDTH, help="hidden units of actor and critic")
    parser.add_argument("--depth", type=int, default=KINETIX_DEPTH, help="tanh layers of actor and critic")
    parser.add_argument("--updates", type=int, default=4, help="PPO updates per timed call")
    parser.add_argument("--repeats", type=int, default=1, help="timed calls; the fastest is kept")
    parser.add_argument("--level-seed", type=int, default=0, help="seed of the random level trained on")
    args = parser.parse_args()
    if args.num_envs % args.num_minibatches:
        parser.error("Kinetix's minibatches split the envs: --num-envs must be a multiple of --num-minibatches")

    static_env_params, env_params = static_env_params_from_size(args.size), EnvParams()
    reset_fn = make_reset_fn_sample_kinetix_level(env_params, static_env_params)
    env = LogWrapper(
        make_kinetix_env(
            ActionType.MULTI_DISCRETE, ObservationType.SYMBOLIC_FLAT, reset_fn, env_params, static_env_params
        )
    )
    level = jax.jit(reset_fn)(jax.random.key(args.level_seed))
    network = make_network(env, env_params, static_env_params, args.width, args.depth)
    rng = jax.random.key(1)

    start = time.perf_counter()
    compiled = jax.jit(make_train(args, env, env_params, network)).lower(rng, level).compile()
    compile_seconds = time.perf_counter() - start
    seconds, cpu_seconds = best_time(lambda: compiled(rng, level), args.repeats)
    obs, _ = env.reset(rng, env_params, level)
    params = jax.eval_shape(
        network.init, rng, ScannedRNN.initialize_carry(1), (obs[None, None], jnp.zeros((1, 1), dtype=bool))
    )
    env_steps = args.updates * args.num_envs * args.num_steps
    report = {
        "jax": jax.__version__,
        "backend": jax.default_backend(),
        "size": args.size,
        "level_seed": args.level_seed,
        "num_envs": args.num_envs,
        "num_steps": args.num_steps,
        "num_minibatches": args.num_minibatches,
        "update_epochs": args.update_epochs,
        "width": args.width,
        "depth": args.depth,
        "network_parameters": sum(x.size for x in jax.tree.leaves(params)),
        "updates": args.updates,
        "env_steps_per_call": env_steps,
        "compile_seconds": compile_seconds,
        "seconds": seconds,
        "cpu_seconds": cpu_seconds,
        "steps_per_second": env_steps / seconds,
        "steps_per_cpu_second": env_steps / cpu_seconds,
    }
    print(json.dumps(report))


if __name__ == "__main__":
    main()
