"""Kinetix's side of the transfer benchmark (benchmarks/kinetix_transfer.py): a kforge BC policy played inside
kinetix-env 3.0.2, its network reading Kinetix's own entity observations through `from_kinetix_observation`.

Runs in the Kinetix virtualenv as `python -m benchmarks.kinetix_transfer_player` from the top of the checkout, where
`kforge` imports from the checkout's folders (Kinetix's jax is older; kforge's agents and env run on it). Jobs, each
printing JSON documents on stdout, one a line:
- `--policy DIR --levels FILE ...`: the policy in DIR (`params.msgpack`, `network.json`, written by
  kinetix_transfer.py), the no-op and the uniform random policy each play `--episodes` first episodes from every
  level file's start (no reset; Kinetix's env without auto-reset, no dense reward, so a positive reward is success
  and a negative one failure); one document per size with each level's per-episode success and failure;
- `--record-observation NAME ... --out FILE`: Kinetix's entity observation of each bundled level's start (kforge's
  names, e.g. s/h3_point_the_thruster), in its size's shapes, written as JSON: the fixture of
  tests/pipeline/test_evaluation_transfer.py, which compares it field by field with kforge's observation of the
  same level.

`from_kinetix_observation` and `kinetix_action_mask` import nothing of Kinetix, so the tests import them.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from kforge.agents import (
    Architecture,
    NetworkConfig,
    make_bc_network,
)
from kforge.agents.policy import sample as sample_action  # the BC policy's sampling, as kforge's evaluation does
from kforge.env import MULTI_DISCRETE_SIZES, EntityObservation, bundled_level_path

PARAMS_FILE = "params.msgpack"
"""The policy's parameters (flax msgpack of the state dict)."""
NETWORK_FILE = "network.json"
"""The policy network's sizes (`agents.NetworkConfig` fields; the architecture by value)."""
CHUNK_LEVELS = 64
"""Levels played together in one compiled program."""
PLAYERS = ("bc", "noop", "random")
"""Who plays every level, by the index the compiled program switches on."""
ENTITY_FIELDS = tuple(EntityObservation.__dataclass_fields__)
"""The entity observation's fields, Kinetix's and kforge's alike."""


def from_kinetix_observation(obs) -> EntityObservation:
    """kforge's entity observation (the BC network's input) from Kinetix's `EntityObservation` of the same state:
    the same fields, shapes and feature order (kforge's observations follow Kinetix's renderers); rows and indexes of
    inactive entities zeroed, as kforge's are (Kinetix leaves them raw behind its masks)."""
    masks = {
        name: jnp.asarray(getattr(obs, f"{name}_mask"), bool) for name in ("polygon", "circle", "joint", "thruster")
    }

    def rows(values, mask):
        return jnp.where(mask[..., None], jnp.asarray(values, jnp.float32), 0.0)

    return EntityObservation(
        polygons=rows(obs.polygons, masks["polygon"]),
        circles=rows(obs.circles, masks["circle"]),
        joints=rows(obs.joints, masks["joint"]),
        thrusters=rows(obs.thrusters, masks["thruster"]),
        polygon_mask=masks["polygon"],
        circle_mask=masks["circle"],
        joint_mask=masks["joint"],
        thruster_mask=masks["thruster"],
        attention_mask=jnp.asarray(obs.attention_mask, bool),
        joint_indexes=jnp.where(masks["joint"][..., None], jnp.asarray(obs.joint_indexes), 0).astype(jnp.int32),
        thruster_indexes=jnp.where(masks["thruster"], jnp.asarray(obs.thruster_indexes), 0).astype(jnp.int32),
    )


def kinetix_action_mask(state, num_motor_bindings: int, num_thruster_bindings: int) -> jnp.ndarray:
    """(6,) bool: the action slots that can move anything in a Kinetix state (kforge's `env.action_mask`): motor
    slot i when an active revolute joint is bound to it, thruster slot 4 + k when an active thruster is."""
    revolute = state.joint.active & ~state.joint.is_fixed_joint
    motors = jnp.any(revolute[:, None] & (state.motor_bindings[:, None] == jnp.arange(num_motor_bindings)), axis=0)
    thrusters = jnp.any(
        state.thruster.active[:, None] & (state.thruster_bindings[:, None] == jnp.arange(num_thruster_bindings)),
        axis=0,
    )
    return jnp.concatenate([motors, thrusters])


def load_network(policy_dir: Path):
    """(network, params) of a policy folder written by kinetix_transfer.py."""
    from flax import serialization

    fields = json.loads((policy_dir / NETWORK_FILE).read_text())
    config = NetworkConfig(**(fields | {"architecture": Architecture(fields["architecture"])}))
    params = serialization.msgpack_restore((policy_dir / PARAMS_FILE).read_bytes())
    return make_bc_network(config), params


def _size_of(static) -> str:
    from kinetix.environment import static_env_params_from_size

    for size in ("s", "m", "l"):
        reference = static_env_params_from_size(size)
        counts = ("num_polygons", "num_circles", "num_joints", "num_thrusters")
        if all(getattr(static, name) == getattr(reference, name) for name in counts):
            return size
    raise ValueError(f"level sizes {static} match no Kinetix size")


def _load(path: str):
    """(size, start state in the size's shapes) of a Kinetix level file."""
    from kinetix.environment import static_env_params_from_size
    from kinetix.util.saving import expand_env_state, load_from_json_file

    state, static, _ = load_from_json_file(str(Path(path).resolve()))
    size = _size_of(static)
    return size, expand_env_state(state, static_env_params_from_size(size))


def _make_env(size: str):
    from kinetix.environment import (
        ActionType,
        EnvParams,
        ObservationType,
        make_kinetix_env,
        static_env_params_from_size,
    )

    params, static = EnvParams(dense_reward_scale=0.0), static_env_params_from_size(size)
    env = make_kinetix_env(
        ActionType.MULTI_DISCRETE, ObservationType.SYMBOLIC_ENTITY, None, params, static, auto_reset=False
    )
    return env, params, static


def _compiled_play(env, env_params, static, network, episodes: int):
    """jit(params, levels (L, ...), keys (L,), player index) -> (success, failure) (L, episodes) bool."""
    sizes = jnp.asarray(MULTI_DISCRETE_SIZES)
    steps = int(env_params.max_timesteps)

    def act(params, obs, state, key, player):
        mask = kinetix_action_mask(state, static.num_motor_bindings, static.num_thruster_bindings)

        def bc():
            logits = network.apply(params, from_kinetix_observation(obs))
            return sample_action(key, logits[0] if isinstance(logits, tuple) else logits, mask)

        def noop():
            return jnp.zeros(len(MULTI_DISCRETE_SIZES), jnp.int32)

        def uniform():
            return jax.random.randint(key, (len(MULTI_DISCRETE_SIZES),), 0, sizes)

        return jnp.where(mask, jax.lax.switch(player, [bc, noop, uniform]), 0).astype(jnp.int32)

    def episode(params, level, key, player):
        reset_key, key = jax.random.split(key)
        obs, state = env.reset(reset_key, env_params, override_reset_state=level)

        def step(carry, step_key):
            obs, state, finished, success, failure = carry
            action_key, env_key = jax.random.split(step_key)
            action = act(params, obs, state, action_key, player)
            obs, stepped, reward, done, _ = env.step(env_key, state, action, env_params)
            ended = done & ~finished
            return (
                obs,
                jax.tree.map(lambda new, old: jnp.where(finished, old, new), stepped, state),
                finished | done,
                success | (ended & (reward > 0)),
                failure | (ended & (reward < 0)),
            ), None

        start = (obs, state, jnp.zeros((), bool), jnp.zeros((), bool), jnp.zeros((), bool))
        (_, _, _, success, failure), _ = jax.lax.scan(step, start, jax.random.split(key, steps))
        return success, failure

    def level_episodes(params, level, key, player):
        return jax.vmap(lambda k: episode(params, level, k, player))(jax.random.split(key, episodes))

    return jax.jit(jax.vmap(level_episodes, in_axes=(None, 0, 0, None)))


def play(policy_dir: Path, paths: list[str], episodes: int, seed: int, emit) -> None:
    """Per size, each level file's per-episode (success, failure) of every player; level i of a size's list plays
    the keys of (seed, i) whoever plays, as kforge's evaluation does."""
    network, params = load_network(policy_dir)
    groups: dict[str, list[tuple[str, object]]] = {}
    for path in paths:
        size, state = _load(path)
        groups.setdefault(size, []).append((path, state))
    for size, members in groups.items():
        env, env_params, static = _make_env(size)
        run = _compiled_play(env, env_params, static, network, episodes)
        keys = jax.vmap(lambda i: jax.random.fold_in(jax.random.key(seed), i))(jnp.arange(len(members)))
        chunk = min(CHUNK_LEVELS, len(members))
        played = {path: {} for path, _ in members}
        for first in range(0, len(members), chunk):
            rows = np.minimum(np.arange(first, first + chunk), len(members) - 1)  # padding repeats the last level
            levels = jax.tree.map(lambda *xs: jnp.stack(xs), *(members[row][1] for row in rows))
            for index, name in enumerate(PLAYERS):
                success, failure = jax.device_get(run(params, levels, keys[rows], jnp.int32(index)))
                for offset, row in enumerate(rows[: len(members) - first]):
                    played[members[row][0]][name] = {
                        "success": success[offset].tolist(),
                        "failure": failure[offset].tolist(),
                    }
            print(
                f"kinetix {size}: levels {first + 1}-{min(first + chunk, len(members))} of {len(members)}",
                file=sys.stderr,
            )
        emit({"size": size, "played": played})


def record_observations(names: list[str], out: Path) -> None:
    """Kinetix's entity observation of each bundled level's start (reset), as JSON lists by field."""
    recorded = {}
    for name in names:
        size, state = _load(bundled_level_path(name))
        env, env_params, _ = _make_env(size)
        obs, _ = env.reset(jax.random.key(0), env_params, override_reset_state=state)
        recorded[name] = {
            "size": size,
            "observation": {field: np.asarray(getattr(obs, field)).tolist() for field in ENTITY_FIELDS},
        }
    out.write_text(json.dumps({"kinetix": "kinetix-env 3.0.2", "levels": recorded}) + "\n")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--policy", type=Path, help="folder with params.msgpack and network.json")
    parser.add_argument("--levels", nargs="*", default=[], help="level JSON files to play")
    parser.add_argument("--levels-from", type=Path, help="a text file listing level JSON files, one a line")
    parser.add_argument("--episodes", type=int, default=8, help="first episodes per level and player")
    parser.add_argument("--seed", type=int, default=0, help="seed of the episode keys")
    parser.add_argument("--record-observation", nargs="*", default=[], help="bundled levels whose start is recorded")
    parser.add_argument("--out", type=Path, help="JSON file of --record-observation")
    args = parser.parse_args(argv)
    if args.record_observation:
        record_observations(args.record_observation, args.out)
    paths = list(args.levels)
    if args.levels_from is not None:
        paths += [line for line in args.levels_from.read_text().splitlines() if line]
    if paths:
        play(args.policy, paths, args.episodes, args.seed, lambda document: print(json.dumps(document), flush=True))


if __name__ == "__main__":
    main()
