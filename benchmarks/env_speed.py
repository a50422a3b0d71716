"""Env throughput of our Kinetix-style tasks, and with `--vs kinetix` of Kinetix itself in the same run.

Prints env steps per second (random multi-discrete actions, auto-reset to each env's own level, symbolic flat
observations) at each batch size on random levels of each size, the level sampler's levels per second, and
compile times. `--vs kinetix` builds (once) a separate virtualenv holding kinetix-env from PyPI — it pins older
jax and zarr, so it cannot share ours — runs benchmarks/kinetix_env_baseline.py there, and prints ratios.
`--json` prints one JSON document instead.

    python -m benchmarks.env_speed --vs kinetix
    python -m benchmarks.env_speed --sizes s --batches 256 --json
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp

from benchmarks.kinetix_venv import DEFAULT_KINETIX_VENV, REPOSITORY, baseline_command, kinetix_python
from benchmarks.machine import describe_machine, provenance
from benchmarks.timing import best_time
from kforge.env import (
    MULTI_DISCRETE_SIZES,
    EnvParams,
    ObservationType,
    StaticEnvParams,
    observe,
    reset,
    sample_levels,
    step,
)

SAMPLER_BATCH = 4096
"""Levels per timed sampler call (ours)."""

KINETIX_SAMPLER_BATCH = {"s": 512, "m": 256, "l": 32}
"""Levels per timed Kinetix sampler call: its sampler is slow for m and l (about 22 levels/s for l on 2 cores)."""


def measure_sampler(size: str, batch: int, repeats: int) -> dict:
    static = StaticEnvParams.for_size(size)
    sample = jax.jit(lambda keys: sample_levels(keys, static))
    keys = jax.random.split(jax.random.key(0), batch)
    start = time.perf_counter()
    compiled = sample.lower(keys).compile()
    compile_seconds = time.perf_counter() - start
    seconds = best_time(lambda: compiled(keys), repeats)[0]
    return {"size": size, "batch": batch, "levels_per_second": batch / seconds, "compile_seconds": compile_seconds}


def observed_env_step(static: StaticEnvParams, params: EnvParams):
    """(state, action, level) -> (symbolic flat observation, state, step result): one env step as a policy sees it."""

    def env_step(state, action, level):
        state, result = step(state, action, level, params, static)
        return observe(state, static, ObservationType.SYMBOLIC_FLAT), state, result

    return env_step


def measure_steps(size: str, batch: int, n_steps: int, repeats: int) -> dict:
    static, params = StaticEnvParams.for_size(size), EnvParams()
    levels = jax.jit(lambda keys: sample_levels(keys, static))(jax.random.split(jax.random.key(1), batch))
    env_step = jax.vmap(observed_env_step(static, params))
    sizes = jnp.asarray(MULTI_DISCRETE_SIZES)

    def rollout(key):
        states = jax.vmap(reset)(levels)

        def body(states, key):
            actions = jax.random.randint(key, (batch, len(MULTI_DISCRETE_SIZES)), 0, sizes)
            obs, states, result = env_step(states, actions, levels)
            return states, result.reward.sum() + obs.sum()

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
    """Seconds to trace and compile one unbatched env step with its observation."""
    static, params = StaticEnvParams.for_size(size), EnvParams()
    level = jax.jit(lambda key: sample_levels(key[None], static))(jax.random.key(0))
    level = jax.tree.map(lambda x: x[0], level)
    action = jnp.zeros(len(MULTI_DISCRETE_SIZES), jnp.int32)
    start = time.perf_counter()
    jax.jit(observed_env_step(static, params)).lower(reset(level), action, level).compile()
    return time.perf_counter() - start


def measure_ours(sizes, batches, n_steps: int, repeats: int, log) -> dict:
    report = {}
    for size in sizes:
        sampler = measure_sampler(size, SAMPLER_BATCH, repeats)
        log(
            f"ours   size={size} sampler {sampler['levels_per_second']:>10,.0f} levels/s "
            f"(compile {sampler['compile_seconds']:.1f} s)"
        )
        compile_seconds = compile_single_step(size)
        log(f"ours   size={size} env step compile {compile_seconds:.1f} s")
        steps = []
        for batch in batches:
            steps.append(measure_steps(size, batch, n_steps, repeats))
            log(f"ours   size={size} batch={batch:>5} {steps[-1]['steps_per_second']:>12,.0f} env steps/s")
        report[size] = {"sampler": sampler, "step_compile_seconds": compile_seconds, "steps": steps}
    return report


def measure_kinetix(venv: Path, sizes, batches, n_steps: int, repeats: int, log) -> dict:
    python = kinetix_python(venv, log)
    command = baseline_command(
        python,
        "kinetix_env_baseline",
        "--sizes",
        *sizes,
        "--batches",
        *map(str, batches),
        "--steps",
        str(n_steps),
        "--repeats",
        str(repeats),
        "--sampler-batch",
        *(f"{size}={count}" for size, count in KINETIX_SAMPLER_BATCH.items()),
    )
    log("running Kinetix in its own virtualenv (its compiles take minutes)")
    output = subprocess.run(command, check=True, capture_output=True, text=True, cwd=REPOSITORY).stdout
    return json.loads(output.strip().splitlines()[-1])["sizes"]


def compare(ours: dict, theirs: dict, log) -> dict:
    ratios = {}
    for size, mine in ours.items():
        other = theirs[size]
        size_ratios = {
            "sampler": mine["sampler"]["levels_per_second"] / other["sampler"]["levels_per_second"],
            "steps": {},
        }
        log(
            f"size={size} sampler: ours {mine['sampler']['levels_per_second']:,.0f} vs kinetix "
            f"{other['sampler']['levels_per_second']:,.0f} levels/s ({size_ratios['sampler']:.1f}x); compile "
            f"{mine['sampler']['compile_seconds']:.1f} s vs {other['sampler']['compile_seconds']:.1f} s"
        )
        log(
            f"size={size} env step compile: ours {mine['step_compile_seconds']:.1f} s vs kinetix "
            f"{other['step_compile_seconds']:.1f} s"
        )
        for ours_batch, their_batch in zip(mine["steps"], other["steps"], strict=True):
            ratio = ours_batch["steps_per_second"] / their_batch["steps_per_second"]
            size_ratios["steps"][str(ours_batch["batch"])] = ratio
            log(
                f"size={size} batch={ours_batch['batch']:>5}: ours {ours_batch['steps_per_second']:>11,.0f} vs "
                f"kinetix {their_batch['steps_per_second']:>11,.0f} env steps/s ({ratio:.1f}x)"
            )
        ratios[size] = size_ratios
    return ratios


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", nargs="+", default=["s", "m", "l"], choices=["s", "m", "l"])
    parser.add_argument("--batches", nargs="+", type=int, default=[1, 256, 2048])
    parser.add_argument("--steps", type=int, default=32, help="env steps per timed rollout")
    parser.add_argument("--repeats", type=int, default=2, help="timed calls; the fastest is kept")
    parser.add_argument("--vs", choices=["kinetix"], help="also measure Kinetix (separate virtualenv) in this run")
    parser.add_argument("--kinetix-venv", type=Path, default=DEFAULT_KINETIX_VENV, help="where that virtualenv lives")
    parser.add_argument("--json", action="store_true", help="print one JSON document with every figure")
    args = parser.parse_args(argv)

    def log(line: str) -> None:
        print(line, file=sys.stderr if args.json else sys.stdout, flush=True)

    report = {
        **provenance(),
        "machine": describe_machine(),
        "steps_per_timed_rollout": args.steps,
        "ours": measure_ours(args.sizes, args.batches, args.steps, args.repeats, log),
    }
    if args.vs == "kinetix":
        report["kinetix"] = measure_kinetix(args.kinetix_venv, args.sizes, args.batches, args.steps, args.repeats, log)
        report["ratio_ours_over_kinetix"] = compare(report["ours"], report["kinetix"], log)
    if args.json:
        print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
