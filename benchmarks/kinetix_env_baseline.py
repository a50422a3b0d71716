"""Kinetix's own env throughput, run inside a separate virtualenv holding kinetix-env (benchmarks/kinetix_venv.py).

Measures, per size, env steps per second (random multi-discrete actions, auto-reset to each env's own level
passed as the override state, symbolic flat observations) at each batch size, the level sampler's levels
per second, and compile times; prints one JSON document. Not importable from the project's environment.

    python -m benchmarks.kinetix_env_baseline --sizes s --batches 1 256 --steps 64
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import jax.numpy as jnp
from kinetix.environment import (
    ActionType,
    EnvParams,
    ObservationType,
    StaticEnvParams,
    make_kinetix_env,
    static_env_params_from_size,
)
from kinetix.environment.ued.ued import make_reset_fn_sample_kinetix_level

from benchmarks.timing import best_time  # needs only jax

MULTI_DISCRETE_SIZES = (3, 3, 3, 3, 2, 2)


def _static(size: str) -> StaticEnvParams:
    return static_env_params_from_size(size)


def measure_sampler(size: str, batch: int, repeats: int) -> dict:
    static, params = _static(size), EnvParams()
    sample = jax.jit(jax.vmap(make_reset_fn_sample_kinetix_level(params, static)))
    keys = jax.random.split(jax.random.key(0), batch)
    start = time.perf_counter()
    compiled = sample.lower(keys).compile()
    compile_seconds = time.perf_counter() - start
    seconds = best_time(lambda: compiled(keys), repeats)[0]
    return {"size": size, "batch": batch, "levels_per_second": batch / seconds, "compile_seconds": compile_seconds}


def measure_steps(size: str, batch: int, n_steps: int, repeats: int) -> dict:
    static, params = _static(size), EnvParams()
    reset_fn = make_reset_fn_sample_kinetix_level(params, static)
    env = make_kinetix_env(ActionType.MULTI_DISCRETE, ObservationType.SYMBOLIC_FLAT, reset_fn, params, static)
    levels = jax.jit(jax.vmap(reset_fn))(jax.random.split(jax.random.key(1), batch))
    sizes = jnp.asarray(MULTI_DISCRETE_SIZES)

    def rollout(key):
        _, states = jax.vmap(env.reset, (0, None, 0))(jax.random.split(key, batch), params, levels)

        def body(states, key):
            action_key, step_key = jax.random.split(key)
            actions = jax.random.randint(action_key, (batch, len(sizes)), 0, sizes)
            obs, states, reward, done, _ = jax.vmap(env.step, (0, 0, 0, None, 0))(
                jax.random.split(step_key, batch), states, actions, params, levels
            )
            return states, reward.sum() + obs.sum()

        return jax.lax.scan(body, states, jax.random.split(key, n_steps))[1].sum()

    key = jax.random.key(2)
    start = time.perf_counter()
    compiled = jax.jit(rollout).lower(key).compile()
    compile_seconds = time.perf_counter() - start
    seconds = best_time(lambda: compiled(key), repeats)[0]
    return {
        "size": size,
        "batch": batch,
        "steps_per_second": batch * n_steps / seconds,
        "rollout_compile_seconds": compile_seconds,
    }


def compile_single_step(size: str) -> float:
    static, params = _static(size), EnvParams()
    reset_fn = make_reset_fn_sample_kinetix_level(params, static)
    env = make_kinetix_env(ActionType.MULTI_DISCRETE, ObservationType.SYMBOLIC_FLAT, reset_fn, params, static)
    level = jax.jit(reset_fn)(jax.random.key(0))
    action = jnp.zeros(len(MULTI_DISCRETE_SIZES), jnp.int32)
    step = jax.jit(lambda k, s, a, lv: env.step(k, s, a, params, lv))
    start = time.perf_counter()
    step.lower(jax.random.key(0), level, action, level).compile()
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", nargs="+", default=["s", "m", "l"])
    parser.add_argument("--batches", nargs="+", type=int, default=[1, 256, 2048])
    parser.add_argument("--steps", type=int, default=64, help="env steps per measured rollout")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--sampler-batch", nargs="+", default=["s=512", "m=256", "l=32"], help="levels per call")
    args = parser.parse_args()
    sampler_batch = dict(item.split("=") for item in args.sampler_batch)
    report = {"jax": jax.__version__, "backend": jax.default_backend(), "sizes": {}}
    for size in args.sizes:
        report["sizes"][size] = {
            "sampler": measure_sampler(size, int(sampler_batch.get(size, 64)), args.repeats),
            "step_compile_seconds": compile_single_step(size),
            "steps": [measure_steps(size, batch, args.steps, args.repeats) for batch in args.batches],
        }
    print(json.dumps(report))


if __name__ == "__main__":
    main()
