"""GAE, the PPO loss and the masked multi-discrete policy against hand-computed values."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from kforge.agents import initial_params, policy
from kforge.agents.config import PPOConfig
from kforge.agents.networks import make_network
from kforge.agents.ppo import Batch, gae, learn, make_optimizer, ppo_loss
from kforge.env import StaticEnvParams, observation_shape

pytestmark = pytest.mark.smoke

THRUSTER_ONLY = jnp.asarray([False, False, False, False, True, False])
"""Action mask of a level whose only actuator is a thruster bound to slot 4."""

ALL_SLOTS = jnp.ones((6,), bool)
"""Action mask of a level that uses every slot."""


# --------------------------------------------------------------------------- GAE
GAMMA, LAMBDA = 0.9, 0.5
REWARDS = [1.0, 2.0, 3.0]
VALUES = [0.5, 1.0, 1.5]
NEXT_VALUES = [1.0, 9.0, 2.0]  # value of the state each step reached (before any reset)


def _gae(terminals, dones):
    as_array = lambda x, dtype=jnp.float32: jnp.asarray(x, dtype)  # noqa: E731
    return gae(
        as_array(REWARDS),
        as_array(VALUES),
        as_array(NEXT_VALUES),
        as_array(terminals, bool),
        as_array(dones, bool),
        GAMMA,
        LAMBDA,
    )


def test_gae_stops_at_a_terminal_in_the_middle():
    advantages, targets = _gae(terminals=[False, True, False], dones=[False, True, False])
    # deltas: 1 + .9 * 1 - .5 = 1.4;  2 + 0 - 1 = 1.0 (terminal: no bootstrap);  3 + .9 * 2 - 1.5 = 3.3
    # A2 = 3.3;  A1 = 1.0 (episode ends: nothing from step 2);  A0 = 1.4 + .9 * .5 * 1.0 = 1.85
    np.testing.assert_allclose(advantages, [1.85, 1.0, 3.3], rtol=1e-6)
    np.testing.assert_allclose(targets, [2.35, 2.0, 4.8], rtol=1e-6)


def test_gae_bootstraps_a_truncated_step_from_its_next_value():
    advantages, _ = _gae(terminals=[False, False, False], dones=[False, True, False])
    # delta1 = 2 + .9 * 9 - 1 = 9.1 (bootstrapped); A1 = 9.1; A0 = 1.4 + .45 * 9.1 = 5.495
    np.testing.assert_allclose(advantages, [5.495, 9.1, 3.3], rtol=1e-6)


def test_gae_without_episode_ends_is_the_discounted_sum_of_deltas():
    advantages, _ = _gae(terminals=[False] * 3, dones=[False] * 3)
    deltas = [1.4, 2 + 0.9 * 9.0 - 1.0, 3.3]
    expected = [sum((GAMMA * LAMBDA) ** (k - t) * deltas[k] for k in range(t, 3)) for t in range(3)]
    np.testing.assert_allclose(advantages, expected, rtol=1e-6)


def test_gae_treats_trailing_axes_as_independent_envs():
    rewards = jnp.asarray([[1.0, 0.0], [2.0, 0.0], [3.0, 1.0]])
    values = jnp.asarray([[0.5, 0.0], [1.0, 0.0], [1.5, 0.0]])
    next_values = jnp.asarray([[1.0, 0.0], [9.0, 0.0], [2.0, 0.0]])
    ends = jnp.asarray([[False, False], [True, False], [False, False]])
    advantages, _ = gae(rewards, values, next_values, ends, ends, GAMMA, LAMBDA)
    np.testing.assert_allclose(advantages[:, 0], [1.85, 1.0, 3.3], rtol=1e-6)
    np.testing.assert_allclose(advantages[:, 1], [0.45**2, 0.45, 1.0], rtol=1e-6)  # reward 1 at the end only


# --------------------------------------------------------------------------- PPO loss
def _fixed_outputs(params, obs):
    """An 'network' whose outputs are its parameters: logits (B, 16) and values (B,)."""
    return params["logits"], params["values"]


def _loss_batch():
    ln2, ln15 = math.log(2.0), math.log(1.5)
    return Batch(
        obs=jnp.zeros((2, 1)),
        action=jnp.asarray([[0, 0, 0, 0, 1, 0], [0, 0, 0, 0, 0, 0]], jnp.int32),
        # With uniform logits the new log-probability of either action is -ln 2: ratios 1.5 and 0.5.
        log_prob=jnp.asarray([-ln2 - ln15, 0.0], jnp.float32),
        value=jnp.asarray([0.5, 0.3]),
        advantage=jnp.asarray([3.0, 1.0]),  # normalised over the minibatch to +1, -1
        target=jnp.asarray([2.0, -1.0]),
    )


LOSS_CONFIG = PPOConfig(clip_eps=0.2, vf_coef=0.5, ent_coef=0.01)


def _loss(logits, mask=THRUSTER_ONLY, batch=None):
    params = {"logits": logits, "values": jnp.asarray([1.0, 0.0])}
    return ppo_loss(params, _fixed_outputs, batch or _loss_batch(), mask, LOSS_CONFIG)


def test_ppo_loss_matches_hand_computation():
    total, terms = _loss(jnp.zeros((2, 16)))
    # actor: -mean(min(1.5 * 1, 1.2 * 1), min(0.5 * -1, 0.8 * -1)) = -mean(1.2, -0.8) = -0.2
    assert float(terms.actor) == pytest.approx(-0.2, abs=1e-6)
    # value: new (1.0, 0.0), old (0.5, 0.3), targets (2, -1); clipped new (0.7, 0.1)
    # 0.5 * mean(max(1, 1.69), max(1, 1.21)) = 0.5 * 1.45
    assert float(terms.value) == pytest.approx(0.725, abs=1e-6)
    assert float(terms.entropy) == pytest.approx(math.log(2.0), abs=1e-6)  # one valid two-choice slot, uniform
    assert float(total) == pytest.approx(-0.2 + 0.5 * 0.725 - 0.01 * math.log(2.0), abs=1e-6)
    kl = ((0.5 - math.log(1.5)) + (-0.5 - math.log(0.5))) / 2
    assert float(terms.approx_kl) == pytest.approx(kl, abs=1e-6)
    assert float(terms.clip_fraction) == 1.0


def test_ppo_loss_ignores_and_does_not_train_masked_slots():
    rng = np.random.default_rng(0)
    noisy = jnp.asarray(rng.normal(0.0, 3.0, (2, 16)), jnp.float32).at[:, 12:14].set(0.0)  # slot 4 stays uniform
    base, _ = _loss(jnp.zeros((2, 16)))
    total, _ = _loss(noisy)
    assert float(total) == pytest.approx(float(base), abs=1e-6)
    unclipped = _loss_batch()._replace(log_prob=jnp.full((2,), -math.log(2.0)))  # ratio 1: the surrogate has slope
    grads = jax.grad(lambda logits: _loss(logits, batch=unclipped)[0])(noisy)
    assert np.all(np.asarray(grads[:, :12]) == 0.0) and np.all(np.asarray(grads[:, 14:]) == 0.0)
    assert np.any(np.asarray(grads[:, 12:14]) != 0.0)


# --------------------------------------------------------------------------- masked multi-discrete policy
def test_entropy_sums_valid_slots():
    all_valid = jnp.ones(6, bool)
    assert float(policy.entropy(jnp.zeros(16), all_valid)) == pytest.approx(4 * math.log(3) + 2 * math.log(2), 1e-6)
    assert float(policy.entropy(jnp.zeros(16), THRUSTER_ONLY)) == pytest.approx(math.log(2), abs=1e-6)
    assert float(policy.entropy(jnp.full(16, 5.0), jnp.zeros(6, bool))) == 0.0


def test_log_prob_of_each_slot_is_its_softmax():
    logits = jnp.zeros(16).at[0:3].set(jnp.log(jnp.asarray([1.0, 2.0, 5.0])))
    logits = logits.at[14:16].set(jnp.log(jnp.asarray([3.0, 1.0])))
    action = jnp.asarray([2, 1, 0, 0, 1, 0])
    expected = math.log(5 / 8) + 3 * math.log(1 / 3) + math.log(1 / 2) + math.log(3 / 4)
    assert float(policy.log_prob(logits, action, jnp.ones(6, bool))) == pytest.approx(expected, abs=1e-6)
    # Masking slots 0-3 and 5 leaves slot 4 alone, whatever the action says for the others.
    assert float(policy.log_prob(logits, action, THRUSTER_ONLY)) == pytest.approx(math.log(1 / 2), abs=1e-6)


def test_masked_slots_are_never_sampled_and_valid_slots_follow_their_probabilities():
    samples = 4000
    # Masked slots strongly prefer non-zero choices; slot 4 fires with probability 3/4.
    choice_zero = np.asarray([0, 3, 6, 9, 12, 14])
    logits = jnp.full(16, 10.0).at[choice_zero].set(-10.0).at[12:14].set(jnp.log(jnp.asarray([1.0, 3.0])))
    actions = jax.vmap(lambda key: policy.sample(key, logits, THRUSTER_ONLY))(
        jax.random.split(jax.random.PRNGKey(0), samples)
    )
    actions = np.asarray(actions)
    assert np.all(actions[:, [0, 1, 2, 3, 5]] == 0)
    fire = actions[:, 4].mean()
    assert abs(fire - 0.75) < 4 * math.sqrt(0.75 * 0.25 / samples)
    assert np.all(np.asarray(policy.mode(logits, THRUSTER_ONLY)) == [0, 0, 0, 0, 1, 0])


def test_two_choice_slots_never_sample_a_third_choice():
    draw = jax.vmap(lambda key: policy.sample(key, jnp.zeros(16), jnp.ones(6, bool)))
    actions = np.asarray(draw(jax.random.split(jax.random.PRNGKey(1), 500)))
    assert actions[:, :4].max() == 2 and actions[:, 4:].max() == 1 and actions.min() == 0


# ------------------------------------------------------------------------------------------------- the learner
def _learn_inputs(config: PPOConfig):
    """Fresh parameters for size-s observations and one update's batch of random samples."""
    static = StaticEnvParams.for_size("s")
    params = initial_params(jax.random.key(0), config, static)
    samples = config.steps_per_update
    keys = jax.random.split(jax.random.key(1), 3)
    batch = Batch(
        obs=jax.random.normal(keys[0], (samples,) + observation_shape(static, config.observation_type).shape),
        action=jax.random.randint(keys[1], (samples, 6), 0, 2),
        log_prob=jnp.full((samples,), -2.0),
        value=jnp.zeros((samples,)),
        advantage=jax.random.normal(keys[2], (samples,)),
        target=jnp.ones((samples,)),
    )
    return params, batch


def test_one_epoch_of_one_minibatch_is_one_adam_step_on_the_whole_batch():
    """The minibatch is the batch shuffled, and the loss does not depend on the order of samples."""
    config = PPOConfig(num_envs=4, num_steps=8, num_minibatches=1, update_epochs=1, env_steps_per_level=32)
    params, batch = _learn_inputs(config)
    optimizer = optax.chain(
        optax.clip_by_global_norm(config.max_grad_norm), optax.adam(config.learning_rate, eps=config.adam_eps)
    )
    grads, _ = jax.grad(ppo_loss, has_aux=True)(params, make_network(config).apply, batch, ALL_SLOTS, config)
    updates, expected_opt_state = optimizer.update(grads, optimizer.init(params), params)
    expected = optax.apply_updates(params, updates)

    learnt, opt_state, terms = learn(params, optimizer.init(params), batch, jax.random.key(2), ALL_SLOTS, config)

    assert terms.total.shape == (1, 1)
    for got, want in zip(
        jax.tree.leaves((learnt, opt_state)), jax.tree.leaves((expected, expected_opt_state)), strict=True
    ):
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-7)
    assert not all(np.array_equal(a, b) for a, b in zip(jax.tree.leaves(learnt), jax.tree.leaves(params), strict=True))


def test_the_learner_takes_one_step_per_minibatch_of_every_epoch():
    config = PPOConfig(num_envs=4, num_steps=8, num_minibatches=4, update_epochs=3, env_steps_per_level=32)
    params, batch = _learn_inputs(config)
    optimizer = make_optimizer(config)
    _, opt_state, terms = learn(params, optimizer.init(params), batch, jax.random.key(2), ALL_SLOTS, config)
    assert terms.total.shape == (3, 4)
    adam_state = opt_state[1][0]
    assert int(adam_state.count) == 12
