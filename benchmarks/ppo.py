"""PPO training throughput of our specialists, and with `--vs kinetix` of Kinetix's own PPO in the same run.

For each size, L random levels are trained together by `agents.train_levels` (one parameter set per level), N envs each,
with configs/ppo_specialist.yaml's settings unless overridden (`--set key=value`). The rate counts every env step of
every level over whole PPO updates (rollout, GAE, epochs of minibatch SGD), timed on an already compiled program;
compile time is printed on its own. Measuring several level counts (`--levels 1 16`) shows what training levels together
(vmapped) gains over training one. `--vs kinetix` runs benchmarks/kinetix_ppo_baseline.py (Kinetix's PPO loop with its
5 x 128 network, one of its random levels) in the kinetix-env virtualenv of benchmarks/kinetix_venv.py, with our envs,
rollout length, epochs and minibatches, so both sides collect and learn from the same number of samples per update; it
prints the ratios. `--learner` also times the learner alone (`agents.ppo.learn`: one update's epochs of minibatch SGD,
on a batch of one update's samples per level) alternately with the training call, and prints its share of the training
time (the training call also plays its final evaluation). Wall time is the figure; process CPU seconds are printed
beside it because a shared machine makes wall times noisy. `--json` prints one JSON document instead.

    python -m benchmarks.ppo --vs kinetix
    python -m benchmarks.ppo --sizes s --levels 1 8 --updates 2 --json
    python -m benchmarks.ppo --sizes s m --levels 4 --learner --repeats 3
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys
import time
from pathlib import Path

import jax
import yaml

from benchmarks.kinetix_venv import DEFAULT_KINETIX_VENV, REPOSITORY, baseline_command, kinetix_python
from benchmarks.machine import describe_machine, provenance
from benchmarks.timing import best_time, best_times_interleaved
from kforge.agents import PPOConfig, initial_params, train_levels
from kforge.agents.ppo import Batch, learn, make_optimizer
from kforge.env import MULTI_DISCRETE_SIZES, EnvParams, StaticEnvParams, observation_shape, sample_levels

LEVEL_SEED = 0
"""Seed of the random levels: L levels are sampled from `jax.random.split(jax.random.key(LEVEL_SEED), L)`; Kinetix's
side samples its level from `jax.random.key(LEVEL_SEED)` with its own sampler."""

TRAIN_SEED = 1
"""Seed of the per-level training keys."""

LEARNER_ROUNDS = 3
"""Alternating rounds of the training call and the learner alone; the fastest of each is kept."""

TARGET_RATIO = 5.0
"""Issue #4: our training throughput should be at least this many times Kinetix's."""


def load_ppo_config(path: Path | None, overrides: list[str], updates: int) -> PPOConfig:
    """The YAML config (None: `PPOConfig`'s defaults, those of configs/ppo_specialist.yaml) with `key=value` overrides,
    its budget cut to `updates` updates per level."""
    values = dataclasses.asdict(PPOConfig()) if path is None else yaml.safe_load(Path(path).read_text())
    for item in overrides:
        key, separator, value = item.partition("=")
        if not separator:
            raise SystemExit(f"--set expects key=value, got {item!r}")
        values[key] = yaml.safe_load(value)
    values["env_steps_per_level"] = updates * values["num_envs"] * values["num_steps"]
    return PPOConfig.from_mapping(values)


@dataclasses.dataclass(frozen=True)
class TrainingProgram:
    """`train_levels` compiled for `num_levels` random levels of one size; `call()` runs it once."""

    call: object
    num_levels: int
    static: StaticEnvParams
    compile_seconds: float


def compile_ours(size: str, num_levels: int, config: PPOConfig) -> TrainingProgram:
    """`train_levels` on `num_levels` random levels of `size` for `config`, compiled."""
    static, env_params = StaticEnvParams.for_size(size), EnvParams()
    level_keys = jax.random.split(jax.random.key(LEVEL_SEED), num_levels)
    levels = jax.jit(lambda keys: sample_levels(keys, static))(level_keys)
    keys = jax.random.split(jax.random.key(TRAIN_SEED), num_levels)
    start = time.perf_counter()
    compiled = train_levels.lower(levels, keys, config, env_params, static).compile()
    compile_seconds = time.perf_counter() - start
    return TrainingProgram(lambda: compiled(levels, keys, env_params), num_levels, static, compile_seconds)


def measure_ours(
    size: str,
    num_levels: int,
    config: PPOConfig,
    repeats: int,
    learner: bool = False,
    program: TrainingProgram | None = None,
) -> dict:
    """Env steps per second of `train_levels` on `num_levels` random levels of `size` (compile excluded; `program`
    if compiled already, `compile_ours`); with `learner`, also the learner's seconds per update and its share of
    the training call's time."""
    program = program or compile_ours(size, num_levels, config)
    seconds, cpu_seconds = best_time(program.call, repeats)
    env_steps = num_levels * config.env_steps_per_level
    result = {
        "levels": num_levels,
        "env_steps_per_call": env_steps,
        "compile_seconds": program.compile_seconds,
        "seconds": seconds,
        "cpu_seconds": cpu_seconds,
        "steps_per_second": env_steps / seconds,
        "steps_per_cpu_second": env_steps / cpu_seconds,
    }
    if learner:
        result["learner"] = measure_learner(program.call, num_levels, config, program.static)
    return result


def learner_program(num_levels: int, config: PPOConfig, static: StaticEnvParams):
    """`agents.ppo.learn` on `num_levels` levels at once (vmap, as in training) and its arguments: fresh parameters and
    a batch of one update's samples per level (random observations and actions; the learner's work does not depend
    on the values)."""
    keys = jax.random.split(jax.random.key(TRAIN_SEED), 4)
    samples = (num_levels, config.steps_per_update)
    params = jax.vmap(lambda key: initial_params(key, config, static))(jax.random.split(keys[0], num_levels))
    opt_state = jax.vmap(make_optimizer(config).init)(params)
    obs = observation_shape(static, config.observation_type)
    slot_choices = jax.numpy.asarray(MULTI_DISCRETE_SIZES)
    batch = Batch(
        obs=jax.random.normal(keys[1], samples + obs.shape, obs.dtype),
        action=jax.random.randint(keys[2], samples + slot_choices.shape, 0, slot_choices),
        log_prob=jax.numpy.full(samples, -3.0),
        value=jax.numpy.zeros(samples),
        advantage=jax.random.normal(keys[3], samples),
        target=jax.numpy.ones(samples),
    )
    mask = jax.numpy.ones((num_levels, len(MULTI_DISCRETE_SIZES)), bool)
    epoch_keys = jax.random.split(jax.random.key(LEVEL_SEED), num_levels)
    program = jax.jit(jax.vmap(lambda *args: learn(*args, config)))
    return program, (params, opt_state, batch, epoch_keys, mask)


def measure_learner(train_call, num_levels: int, config: PPOConfig, static: StaticEnvParams) -> dict:
    """The learner alone against `train_call` (the compiled training of `num_levels` levels), timed alternately."""
    program, arguments = learner_program(num_levels, config, static)
    updates = config.num_updates
    train_seconds, learner_seconds = best_times_interleaved([train_call, lambda: program(*arguments)], LEARNER_ROUNDS)
    return {
        "seconds_per_update": learner_seconds,
        "training_seconds_per_update": train_seconds / updates,
        "share_of_training": learner_seconds * updates / train_seconds,
    }


def network_parameters(config: PPOConfig, static: StaticEnvParams) -> int:
    shapes = jax.eval_shape(lambda key: initial_params(key, config, static), jax.random.key(0))
    return sum(x.size for x in jax.tree.leaves(shapes))


def measure_kinetix(python: Path, size: str, config: PPOConfig, args, environment: dict | None = None) -> dict:
    """Kinetix's PPO on one of its random levels of `size`, with our envs, rollout, epochs and minibatches (in
    `environment`, else this process's)."""
    command = baseline_command(
        python,
        "kinetix_ppo_baseline",
        f"--size={size}",
        f"--num-envs={config.num_envs}",
        f"--num-steps={config.num_steps}",
        f"--num-minibatches={config.num_minibatches}",
        f"--update-epochs={config.update_epochs}",
        f"--updates={args.updates}",
        f"--repeats={args.repeats}",
        f"--level-seed={LEVEL_SEED}",
    )
    if args.kinetix_network == "ours":
        command += [f"--width={config.hidden_size}", f"--depth={config.num_hidden_layers}"]
    output = subprocess.run(command, check=True, capture_output=True, text=True, env=environment, cwd=REPOSITORY).stdout
    return json.loads(output.strip().splitlines()[-1])


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", nargs="+", default=["s", "m", "l"], choices=["s", "m", "l"])
    parser.add_argument("--levels", nargs="+", type=int, default=[1, 16], help="level counts L trained together")
    parser.add_argument(
        "--config",
        type=Path,
        help="PPO settings (YAML of PPOConfig; default: its defaults, configs/ppo_specialist.yaml)",
    )
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="PPOConfig overrides")
    parser.add_argument("--updates", type=int, default=4, help="PPO updates per level per timed call")
    parser.add_argument("--repeats", type=int, default=1, help="timed calls after a warm-up; the fastest is kept")
    parser.add_argument("--vs", choices=["kinetix"], help="also measure Kinetix's PPO (separate virtualenv)")
    parser.add_argument("--kinetix-venv", type=Path, default=DEFAULT_KINETIX_VENV, help="where that virtualenv lives")
    parser.add_argument(
        "--kinetix-network",
        choices=["kinetix", "ours"],
        default="kinetix",
        help="Kinetix's side: its default 5 x 128 network, or its network at our width and depth",
    )
    parser.add_argument("--learner", action="store_true", help="also time the learner alone and print its share")
    parser.add_argument("--json", action="store_true", help="print one JSON document with every figure")
    args = parser.parse_args(argv)
    config = load_ppo_config(args.config, args.set, args.updates)

    def log(line: str) -> None:
        print(line, file=sys.stderr if args.json else sys.stdout, flush=True)

    python = kinetix_python(args.kinetix_venv, log) if args.vs == "kinetix" else None
    log(
        f"PPO: {config.num_envs} envs x {config.num_steps} steps per update, {config.update_epochs} epochs x "
        f"{config.num_minibatches} minibatches, {config.num_hidden_layers} x {config.hidden_size} MLP; "
        f"{args.updates} updates per timed call"
    )
    report = {
        **provenance(),
        "machine": describe_machine(),
        "config": dataclasses.asdict(config),
        "updates_per_call": args.updates,
        "sizes": {},
    }
    for size in args.sizes:
        entry = {"network_parameters": network_parameters(config, StaticEnvParams.for_size(size)), "ours": []}
        for num_levels in args.levels:
            ours = measure_ours(size, num_levels, config, args.repeats, args.learner)
            entry["ours"].append(ours)
            log(
                f"ours    size={size} L={num_levels:>3} x N={config.num_envs}: {ours['steps_per_second']:>9,.0f} env "
                f"steps/s ({ours['steps_per_cpu_second']:,.0f} per CPU-s); compile {ours['compile_seconds']:.0f} s"
            )
            if "learner" in ours:
                learner = ours["learner"]
                log(
                    f"learner size={size} L={num_levels:>3}: {learner['seconds_per_update'] * 1e3:.1f} ms per update "
                    f"of {config.update_epochs} epochs x {config.num_minibatches} minibatches, of "
                    f"{learner['training_seconds_per_update'] * 1e3:.1f} ms per training update: "
                    f"{learner['share_of_training']:.0%} of training"
                )
        single = next((ours for ours in entry["ours"] if ours["levels"] == 1), None)
        if single is not None:
            entry["speedup_over_one_level"] = {
                str(ours["levels"]): ours["steps_per_second"] / single["steps_per_second"] for ours in entry["ours"]
            }
            for levels, speedup in entry["speedup_over_one_level"].items():
                log(f"ours    size={size} L={levels:>3}: {speedup:.1f}x the throughput of one level")
        if python is not None:
            log(f"kinetix size={size}: running its PPO in {args.kinetix_venv} (compiling takes minutes)")
            theirs = measure_kinetix(python, size, config, args)
            entry["kinetix"] = theirs
            log(
                f"kinetix size={size} L=  1 x N={theirs['num_envs']}: {theirs['steps_per_second']:>9,.0f} env steps/s "
                f"({theirs['steps_per_cpu_second']:,.0f} per CPU-s; {theirs['depth']} x {theirs['width']} MLP, "
                f"{theirs['network_parameters']:,} parameters vs our {entry['network_parameters']:,}); "
                f"compile {theirs['compile_seconds']:.0f} s"
            )
            entry["ratio_ours_over_kinetix"] = {
                str(ours["levels"]): ours["steps_per_second"] / theirs["steps_per_second"] for ours in entry["ours"]
            }
            entry["ratio_ours_over_kinetix_per_cpu_second"] = {
                str(ours["levels"]): ours["steps_per_cpu_second"] / theirs["steps_per_cpu_second"]
                for ours in entry["ours"]
            }
            for levels, ratio in entry["ratio_ours_over_kinetix"].items():
                verdict = "meets" if ratio >= TARGET_RATIO else "misses"
                log(
                    f"size={size} ours L={levels:>3} / kinetix: {ratio:.1f}x ({verdict} the {TARGET_RATIO:.0f}x "
                    f"target); per CPU-s {entry['ratio_ours_over_kinetix_per_cpu_second'][levels]:.1f}x"
                )
        report["sizes"][size] = entry
    if args.json:
        print(json.dumps(report, indent=2, default=str))  # default: the observation type enum


if __name__ == "__main__":
    main()
