"""Behaviour cloning's pieces: the masked per-slot loss against its closed form, the BC networks (overfitting a
handful of expert decisions, the transformer's invariance to entity order) and episodes of a scripted actor."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from agents_test_helpers import ENV_PARAMS, STATIC, thruster_level

from kforge.agents import (
    Architecture,
    NetworkConfig,
    imitation_terms,
    make_bc_network,
    run_episode,
)
from kforge.env import (
    ActionType,
    ObservationType,
    StaticEnvParams,
    action_mask,
    load_level,
    noop_action,
    observe,
    random_action,
    reset,
    sample_levels,
)

SIZE_S = StaticEnvParams.for_size("s")
SLOT_CHOICES = (3, 3, 3, 3, 2, 2)
THRUSTER_SLOT = 4
FIRE_THRUSTER = 1


@pytest.mark.smoke
def test_uniform_logits_cost_the_log_of_each_valid_slots_choice_count():
    logits = jnp.zeros((5, 16))
    action = jnp.zeros((5, 6), jnp.int32)
    mask = jnp.zeros((5, 6), bool).at[:, 0].set(True).at[:, 4].set(True)
    terms = imitation_terms(logits, action, mask)
    np.testing.assert_allclose(terms.loss, (math.log(3) + math.log(2)) / 2, rtol=1e-6)
    np.testing.assert_allclose(terms.slot_nll[jnp.array([0, 4])], [math.log(3), math.log(2)], rtol=1e-6)
    np.testing.assert_array_equal(terms.slot_count, [5, 0, 0, 0, 5, 0])


@pytest.mark.smoke
def test_masked_slots_contribute_nothing_whatever_their_logits():
    key_logits, key_noise, key_action = jax.random.split(jax.random.key(0), 3)
    logits = jax.random.normal(key_logits, (4, 7, 16))
    action = jax.random.randint(key_action, (4, 7, 6), 0, jnp.asarray(SLOT_CHOICES))
    mask = jnp.array([True, False, True, False, False, True])
    masked_logits = np.r_[3:6, 9:12, 12:14]  # logits of slots 1, 3 and 4
    noise = jnp.zeros((16,)).at[masked_logits].set(jax.random.normal(key_noise, (8,)) * 50.0)

    def loss(x):
        return imitation_terms(x, action, jnp.broadcast_to(mask, action.shape)).loss

    np.testing.assert_allclose(loss(logits + noise), loss(logits), rtol=1e-6)
    gradient = jax.grad(loss)(logits)
    np.testing.assert_array_equal(gradient[..., masked_logits], 0.0)
    assert float(jnp.abs(gradient[..., :3]).sum()) > 0  # a valid slot's logits do receive gradient


def test_a_zero_weight_leaves_a_transition_out():
    logits = jax.random.normal(jax.random.key(1), (3, 16))
    action = jnp.array([[0, 1, 2, 0, 1, 0], [2, 2, 2, 2, 1, 1], [1, 0, 0, 0, 0, 1]])
    mask = jnp.ones((3, 6), bool)
    weighted = imitation_terms(logits, action, mask, weight=jnp.array([1.0, 0.0, 1.0]))
    kept = imitation_terms(logits[::2], action[::2], mask[::2])
    np.testing.assert_allclose(weighted.loss, kept.loss, rtol=1e-6)
    np.testing.assert_allclose(weighted.slot_accuracy, kept.slot_accuracy, rtol=1e-6)
    assert float(weighted.transition_count) == 2.0


def _expert_steps(count: int):
    """Start states of `count` random size-s levels, each with a fixed random multi-discrete action."""
    levels = sample_levels(jax.random.split(jax.random.key(3), count), SIZE_S)
    actions = jax.vmap(random_action, in_axes=(0, None))(
        jax.random.split(jax.random.key(4), count), ActionType.MULTI_DISCRETE
    )
    return jax.vmap(reset)(levels), actions


@pytest.mark.parametrize("architecture", list(Architecture))
def test_bc_overfits_a_handful_of_expert_decisions(architecture):
    states, actions = _expert_steps(24)
    config = NetworkConfig(architecture=architecture, hidden_size=64, embed_size=32, num_heads=2, num_layers=1)
    network = make_bc_network(config)
    obs = jax.vmap(lambda s: observe(s, SIZE_S, architecture.observation_type))(states)
    mask = jnp.ones(actions.shape, bool)
    params = network.init(jax.random.key(0), jax.tree.map(lambda x: x[0], obs))
    optimizer = optax.adam(3e-3)

    @jax.jit
    def update(params, opt_state):
        grads = jax.grad(lambda p: imitation_terms(network.apply(p, obs), actions, mask).loss)(params)
        updates, opt_state = optimizer.update(grads, opt_state)
        return optax.apply_updates(params, updates), opt_state

    opt_state = optimizer.init(params)
    before = imitation_terms(network.apply(params, obs), actions, mask)
    for _ in range(400):
        params, opt_state = update(params, opt_state)
    after = imitation_terms(network.apply(params, obs), actions, mask)
    assert float(before.accuracy) < 0.7
    assert float(after.accuracy) >= 0.98
    assert float(after.loss) < 0.1


def _permuted(obs, joint_order, thruster_order):
    return obs.replace(
        joints=obs.joints[joint_order],
        joint_mask=obs.joint_mask[joint_order],
        joint_indexes=obs.joint_indexes[joint_order],
        thrusters=obs.thrusters[thruster_order],
        thruster_mask=obs.thruster_mask[thruster_order],
        thruster_indexes=obs.thruster_indexes[thruster_order],
    )


@pytest.mark.smoke
def test_the_transformer_ignores_the_order_of_entities():
    car = load_level("m/h7_car_flip")  # two motorised joints and two thrusters
    obs = observe(reset(car.level), car.static, ObservationType.SYMBOLIC_ENTITY)
    network = make_bc_network(NetworkConfig(architecture=Architecture.TRANSFORMER, embed_size=32, num_heads=2))
    params = network.init(jax.random.key(0), obs)
    joints, thrusters = obs.joints.shape[0], obs.thrusters.shape[0]
    permuted = _permuted(obs, np.random.default_rng(0).permutation(joints), np.arange(thrusters)[::-1])
    logits = network.apply(params, obs)  # near zero at initialisation (a near-uniform policy): compare tightly
    np.testing.assert_allclose(network.apply(params, permuted), logits, rtol=0, atol=1e-7)
    active_joint = int(np.flatnonzero(np.asarray(obs.joint_mask))[0])
    changed = obs.replace(joints=obs.joints.at[active_joint, 2:4].add(0.5))  # another anchor: other logits
    assert float(jnp.abs(network.apply(params, changed) - logits).max()) > 1e-5


@pytest.mark.smoke
def test_the_transformer_reads_nothing_of_inactive_entities():
    """A polygon no joint or thruster is attached to, masked off, is not read; active, it is."""
    car = load_level("m/h7_car_flip")
    obs = observe(reset(car.level), car.static, ObservationType.SYMBOLIC_ENTITY)
    network = make_bc_network(NetworkConfig(architecture=Architecture.TRANSFORMER, embed_size=32, num_heads=2))
    params = network.init(jax.random.key(0), obs)
    attached = set(np.asarray(obs.joint_indexes).ravel().tolist()) | set(np.asarray(obs.thruster_indexes).tolist())
    free = int(next(i for i in np.flatnonzero(np.asarray(obs.polygon_mask)) if i not in attached))
    hidden = obs.replace(polygon_mask=obs.polygon_mask.at[free].set(False))
    logits = network.apply(params, hidden)
    changed = hidden.replace(polygons=hidden.polygons.at[free].add(3.0))
    np.testing.assert_array_equal(network.apply(params, changed), logits)
    shown = obs.replace(polygons=obs.polygons.at[free].add(3.0))
    assert float(jnp.abs(network.apply(params, shown) - network.apply(params, obs)).max()) > 1e-5


def test_a_scripted_actor_gets_the_outcome_kinematics_predict():
    level = thruster_level()
    mask = action_mask(level)

    def fire(state, mask, key):
        return noop_action(ActionType.MULTI_DISCRETE).at[THRUSTER_SLOT].set(FIRE_THRUSTER)

    def idle(state, mask, key):
        return noop_action(ActionType.MULTI_DISCRETE)

    key = jax.random.key(0)
    fired = run_episode(fire, reset(level), mask, key, ENV_PARAMS, STATIC)
    idled = run_episode(idle, reset(level), mask, key, ENV_PARAMS, STATIC)
    assert bool(fired.success) and not bool(fired.failure) and int(fired.length) < STATIC.max_timesteps
    assert not bool(idled.success) and not bool(idled.failure) and int(idled.length) == STATIC.max_timesteps
