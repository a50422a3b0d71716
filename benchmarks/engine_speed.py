"""Physics throughput of our engine and of Jax2D on the same fully populated s, m and l scenes.

Prints physics steps per second under jit + vmap at each batch size, the compile time of one step, and with
`--vs jax2d` the same figures for Jax2D (PyPI package `jax2d`, extra `bench`) measured in the same run, with
the speed-up; the two engines' timed calls then alternate, so both see the same machine load. `--json` prints
one JSON document instead. On a GPU it also measures large batches and prints Jax2D's published peak throughputs
next to ours.

`--physics NAME` runs ours under a named physics scheme (default "kforge"); `--vs-physics NAME` also times ours under
another, alternating call by call with the first (and with Jax2D's if asked), with the speed-ups of both over Jax2D.

`--kernels` instead counts the kernels that one physics step and one env step run in sequence, for ours (under
the backend's "auto" batching, as one whole vmap with the solver's loops looped, and as a GPU or TPU runs it: one
whole vmap with the solver's loops unrolled) and for Jax2D's physics step, at each batch, with the ratios ours / Jax2D.
On a GPU each kernel launch costs microseconds whatever the batch, so this count bounds the step rate at large
batch. Method (`benchmarks.kernels`): compile the vmapped step with `jax.jit(...).lower(...).compile()` and count,
in the optimized HLO, the instructions that do work (fusions, custom calls, unfused operations) in the entry
computation, with `while` bodies multiplied by XLA's `known_trip_count`.

    python -m benchmarks.engine_speed --vs jax2d
    python -m benchmarks.engine_speed --sizes s --batches 256 --json
    python -m benchmarks.engine_speed --kernels --batches 1 256
    python -m benchmarks.engine_speed --sizes s m l --batches 256 --vs-physics kinetix --vs jax2d --json
    python -m benchmarks.engine_speed --sizes s --batches 256 --repeats 7 --vs-sim swept_speculative_contacts=0
    python -m benchmarks.engine_speed --sizes s m --batches 1 256 --repeats 15 --vs-substeps 2
    python -m benchmarks.engine_speed --sizes s m l --batches 1 256 --repeats 9 --vs-substeps 1 --vs-iterations 10 \
        --vs-relax-iterations 0 --vs-sim contact_law=1 --vs-sim force_timing=1 --vs-sim speculative_distance=0 \
        --vs-sim speculative_reach=0

`--vs-sim KEY=VALUE` also times ours with those `SimParams` (compiled in as constants) or `StaticSimParams` laws,
called alternately with the defaults, and prints the ratio: what a physics option costs. `--vs-substeps N` does the
same for N solver substeps per step (alone or with `--vs-sim`), `--vs-iterations` and `--vs-relax-iterations` for the
passes per substep.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time

import jax
import jax.numpy as jnp

from benchmarks.kernels import count_kernels
from benchmarks.machine import describe_machine, provenance
from benchmarks.scenes import batched_scenes, build_scene
from benchmarks.sim_overrides import (
    sim_override,
    solver_count_errors,
    with_sim_overrides,
    with_solver_scheme,
)
from benchmarks.timing import best_time, best_times_interleaved
from kforge.engine import PHYSICS_SCHEMES, Batching, SimParams, physics_scheme, step
from kforge.engine.schemes import DEFAULT_PHYSICS_SCHEME

GPU_BATCHES = (4096, 16384, 65536)
JAX2D_PUBLISHED_PEAK_STEPS_PER_SECOND = {"s": 2e7, "m": 9e6, "l": 1.7e6}
"""Jax2D README plots (hardware not stated), for comparison when a GPU is present."""


SCHEME_FIELDS = ("substeps", "iterations", "relax_iterations")
"""Solver counts that `--vs-substeps`, `--vs-iterations`, `--vs-relax-iterations` set (SOLVER_SCHEME_FIELDS)."""


def scheme_params(size: str, physics: str = DEFAULT_PHYSICS_SCHEME, overrides=(), scheme=None, batching=None):
    """`SimParams` and `StaticSimParams` of the benchmark scene of `size` under the named physics scheme, then the
    `sim_override` pairs `overrides`, the solver counts of `scheme` (keys of SCHEME_FIELDS) and `batching` (default:
    the engine's "auto")."""
    named = physics_scheme(physics)
    static = named.static(build_scene(size, 0)[1])
    params, static = with_sim_overrides(named.sim(SimParams()), static, overrides)
    static = with_solver_scheme(static, scheme or {})
    return params, static if batching is None else dataclasses.replace(static, batching=batching)


def compile_rollout_ours(
    size: str, batch: int, n_steps: int, physics=DEFAULT_PHYSICS_SCHEME, overrides=(), scheme=None, batching=None
):
    """`call()` running `n_steps` vmapped steps inside one compiled scan (motors at +1, thrusters on) under
    `scheme_params`, its `SimParams` compiled in as constants."""
    params, static = scheme_params(size, physics, overrides, scheme, batching)
    states = batched_scenes(size, batch)
    motors, thrusters = jnp.ones(static.num_joints), jnp.ones(static.num_thrusters)
    batched = jax.vmap(lambda s: step(s, params, motors, thrusters, static=static)[0])

    def rollout(states):
        return jax.lax.scan(lambda s, _: (batched(s), None), states, None, length=n_steps)[0]

    compiled = jax.jit(rollout).lower(states).compile()
    return lambda: compiled(states)


def compile_ours(size: str, physics: str = DEFAULT_PHYSICS_SCHEME, overrides=(), scheme=None) -> float:
    """Seconds to trace and compile one (unbatched) step under `scheme_params`."""
    state = build_scene(size, 0)[0]
    params, static = scheme_params(size, physics, overrides, scheme)
    start = time.perf_counter()
    jax.jit(step, static_argnames="static").lower(
        state, params, jnp.ones(static.num_joints), jnp.ones(static.num_thrusters), static=static
    ).compile()
    return time.perf_counter() - start


def compile_jax2d(size: str) -> float:
    """Seconds to trace and compile one (unbatched) Jax2D step."""
    from jax2d.engine import PhysicsEngine
    from jax2d.sim_state import SimParams as Jax2dParams

    from benchmarks import jax2d_baseline

    state, static = jax2d_baseline.build_scene(size, 0)
    actions = jnp.ones(static.num_joints + static.num_thrusters)
    start = time.perf_counter()
    jax.jit(PhysicsEngine(static).step).lower(state, Jax2dParams(), actions).compile()
    return time.perf_counter() - start


def run(
    sizes,
    batches,
    n_steps: int,
    repeats: int,
    versus_jax2d: bool,
    log=print,
    sim_overrides=(),
    scheme=None,
    physics: str = DEFAULT_PHYSICS_SCHEME,
    versus_physics: str | None = None,
) -> dict:
    """Measure every (size, batch) of ours under the named `physics`; `log` receives one human-readable line per
    figure. With `sim_overrides`, solver counts in `scheme` (`scheme_params`) and/or another named physics
    `versus_physics`, ours is also timed with those (`ours_sim`), alternating call by call with the first."""
    scheme = {key: count for key, count in (scheme or {}).items() if count is not None}
    versus_physics = physics if versus_physics is None else versus_physics
    on_gpu = jax.default_backend() == "gpu"
    sim_overrides = list(sim_overrides)
    variant = bool(sim_overrides) or bool(scheme) or versus_physics != physics
    engines = ["ours"] + (["ours_sim"] if variant else []) + (["jax2d"] if versus_jax2d else [])
    report = {
        **provenance(),
        "machine": describe_machine(),
        "physics": physics,
        "steps_per_timed_call": n_steps,
        "steps_per_second": {engine: {} for engine in engines},
        "compile_seconds": {engine: {} for engine in engines},
    }
    variant_text = ",".join(
        ([f"physics={versus_physics}"] if versus_physics != physics else [])
        + ([_overrides_text(sim_overrides)] if sim_overrides else [])
        + [f"{k}={v}" for k, v in scheme.items()]
    )
    if variant:
        report["sim_physics"] = versus_physics
        report["sim_overrides"] = dict(sim_overrides)
        report |= {key: scheme.get(key) for key in SCHEME_FIELDS}
        report["sim_vs_default"] = {}
    if versus_jax2d:
        from benchmarks import jax2d_baseline

        report["speedup_vs_jax2d"] = {}
        if variant:
            report["sim_speedup_vs_jax2d"] = {}
    for size in sizes:
        report["compile_seconds"]["ours"][size] = compile_ours(size, physics)
        line = f"size={size} compile one step: ours {report['compile_seconds']['ours'][size]:.1f} s"
        if variant:
            report["compile_seconds"]["ours_sim"][size] = compile_ours(size, versus_physics, sim_overrides, scheme)
            line += f", with {variant_text} {report['compile_seconds']['ours_sim'][size]:.1f} s"
        if versus_jax2d:
            report["compile_seconds"]["jax2d"][size] = compile_jax2d(size)
            line += f", jax2d {report['compile_seconds']['jax2d'][size]:.1f} s"
        log(line)
        for batch in list(batches) + (list(GPU_BATCHES) if on_gpu else []):
            calls = [compile_rollout_ours(size, batch, n_steps, physics)]
            if variant:
                calls.append(compile_rollout_ours(size, batch, n_steps, versus_physics, sim_overrides, scheme))
            if versus_jax2d:
                calls.append(jax2d_baseline.compile_rollout(size, batch, n_steps)[0])
            seconds = best_times_interleaved(calls, repeats) if len(calls) > 1 else [best_time(calls[0], repeats)[0]]
            rates = dict(zip(engines, (batch * n_steps / s for s in seconds), strict=True))
            for engine, rate in rates.items():
                report["steps_per_second"][engine].setdefault(size, {})[str(batch)] = rate
            line = f"size={size} batch={batch:>6} ours={rates['ours']:>12,.0f} steps/s"
            if variant:
                report["sim_vs_default"].setdefault(size, {})[str(batch)] = rates["ours_sim"] / rates["ours"]
                line += f"  with {variant_text}={rates['ours_sim']:>12,.0f} steps/s"
                line += f" ({rates['ours_sim'] / rates['ours']:.2f}x)"
            if versus_jax2d:
                report["speedup_vs_jax2d"].setdefault(size, {})[str(batch)] = rates["ours"] / rates["jax2d"]
                line += f"  jax2d={rates['jax2d']:>12,.0f} steps/s  speedup={rates['ours'] / rates['jax2d']:6.2f}x"
                if variant:
                    speedup = rates["ours_sim"] / rates["jax2d"]
                    report["sim_speedup_vs_jax2d"].setdefault(size, {})[str(batch)] = speedup
                    line += f" (with {variant_text} {speedup:6.2f}x)"
            if on_gpu and batch in GPU_BATCHES:
                line += f"  (jax2d published peak {JAX2D_PUBLISHED_PEAK_STEPS_PER_SECOND[size]:,.0f})"
            log(line)
    return report


def _overrides_text(overrides) -> str:
    return ",".join(f"{key}={value:g}" for key, value in overrides)


def physics_step_kernels(
    size: str, batch: int, physics: str = DEFAULT_PHYSICS_SCHEME, batching: Batching | None = None
) -> int:
    """Kernels one vmapped physics step of ours runs at `batch` scenes under the named physics scheme and `batching`
    (default: the engine's "auto")."""
    params, static = scheme_params(size, physics, batching=batching)
    motors, thrusters = jnp.ones(static.num_joints), jnp.ones(static.num_thrusters)
    one_step = jax.vmap(lambda s: step(s, params, motors, thrusters, static=static)[0])
    return _known(count_kernels(one_step, batched_scenes(size, batch)))


def env_step_kernels(
    size: str, batch: int, physics: str = DEFAULT_PHYSICS_SCHEME, batching: Batching | None = None
) -> int:
    """Kernels one vmapped env step of ours (step, auto-reset and observation) runs at `batch` levels under the named
    physics scheme and `batching` (default: the engine's "auto")."""
    from benchmarks.env_speed import observed_env_step
    from kforge.env import MULTI_DISCRETE_SIZES, EnvParams, StaticEnvParams, reset, sample_levels, under_scheme

    params, static = under_scheme(physics_scheme(physics), EnvParams(), StaticEnvParams.for_size(size))
    if batching is not None:
        static = dataclasses.replace(static, sim=dataclasses.replace(static.sim, batching=batching))
    levels = jax.jit(lambda keys: sample_levels(keys, static))(jax.random.split(jax.random.key(1), batch))
    actions = jnp.zeros((batch, len(MULTI_DISCRETE_SIZES)), jnp.int32)
    return _known(count_kernels(jax.vmap(observed_env_step(static, params)), jax.vmap(reset)(levels), actions, levels))


def jax2d_physics_step_kernels(size: str, batch: int) -> int:
    """Kernels one vmapped Jax2D physics step runs at `batch` scenes."""
    from jax2d.engine import PhysicsEngine
    from jax2d.sim_state import SimParams as Jax2dParams

    from benchmarks import jax2d_baseline

    states, static = jax2d_baseline.build_batch(size, batch)
    actions = jnp.ones(static.num_joints + static.num_thrusters)
    physics = PhysicsEngine(static)  # builds its pair tables on the host: outside the trace
    one_step = jax.vmap(lambda s: physics.step(s, Jax2dParams(), actions)[0])
    return _known(count_kernels(one_step, states))


def _known(count) -> int:
    if count.unknown_trip_loops:
        raise RuntimeError(f"{count.unknown_trip_loops} loops without a known trip count: the kernel count is wrong")
    return count.kernels


ACCELERATOR_BATCHING = Batching("whole", solver_loops="unrolled")
"""The batching mode and form of the solver's loops that `engine.Batching`'s "auto" picks on a GPU or TPU."""


def count_all_kernels(sizes, batches, log=print, physics: str = DEFAULT_PHYSICS_SCHEME) -> dict:
    """Kernel counts per size and batch under the named physics scheme: ours under the backend's "auto" batching, as
    one whole vmap with the solver's loops looped, and as an accelerator runs it (`ACCELERATOR_BATCHING`); our env
    step (auto; accelerator's); Jax2D's physics step; and the ratios to Jax2D."""
    batching = Batching().resolved()
    report = {
        **provenance(),
        "machine": describe_machine(),
        "physics": physics,
        "batching": batching.mode,
        "chunk_limit": batching.chunk_limit,
        "solver_loops": batching.solver_loops,
    }
    whole_looped = Batching("whole", batching.chunk_limit, "looped")
    for size in sizes:
        for batch in batches:
            row = {
                "physics_step": physics_step_kernels(size, batch, physics),
                "env_step": env_step_kernels(size, batch, physics),
                "physics_step_whole_looped": physics_step_kernels(size, batch, physics, whole_looped),
                "physics_step_accelerator": physics_step_kernels(size, batch, physics, ACCELERATOR_BATCHING),
                "env_step_accelerator": env_step_kernels(size, batch, physics, ACCELERATOR_BATCHING),
            }
            jax2d = row["jax2d_physics_step"] = jax2d_physics_step_kernels(size, batch)
            for form in ("physics_step", "physics_step_whole_looped", "physics_step_accelerator"):
                row[f"{form}_ratio_vs_jax2d"] = row[form] / jax2d
            report.setdefault("kernels", {}).setdefault(size, {})[str(batch)] = row
            log(
                f"size={size} batch={batch:>6} kernels: physics step ours {row['physics_step']} "
                f"({batching.mode}, {batching.solver_loops}; whole vmap looped {row['physics_step_whole_looped']}, "
                f"as on an accelerator {row['physics_step_accelerator']}), jax2d {jax2d}, ratio "
                f"{row['physics_step_ratio_vs_jax2d']:.2f} (whole looped "
                f"{row['physics_step_whole_looped_ratio_vs_jax2d']:.2f}, accelerator "
                f"{row['physics_step_accelerator_ratio_vs_jax2d']:.2f}); env step ours {row['env_step']} "
                f"(accelerator {row['env_step_accelerator']})"
            )
    return report


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", nargs="+", default=["s", "m", "l"], choices=["s", "m", "l"])
    parser.add_argument("--batches", nargs="+", type=int, default=[1, 256, 2048])
    parser.add_argument("--steps", type=int, default=20, help="physics steps per timed call")
    parser.add_argument("--repeats", type=int, default=3, help="timed calls (per engine); the fastest is kept")
    parser.add_argument("--vs", choices=["jax2d"], help="also measure the reference engine in the same run")
    parser.add_argument("--json", action="store_true", help="print one JSON document with every figure")
    parser.add_argument("--kernels", action="store_true", help="count kernels per step instead of timing steps")
    parser.add_argument(
        "--physics", choices=list(PHYSICS_SCHEMES), default=DEFAULT_PHYSICS_SCHEME, help="ours' physics scheme"
    )
    parser.add_argument(
        "--vs-physics",
        choices=list(PHYSICS_SCHEMES),
        help="also time ours under this physics scheme (with any --vs-sim), alternating with --physics",
    )
    parser.add_argument(
        "--vs-sim",
        type=sim_override,
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="also time ours with these SimParams or law overrides, alternating with the defaults (repeatable)",
    )
    parser.add_argument(
        "--vs-substeps",
        type=int,
        metavar="N",
        help="also time ours with N solver substeps per step (with any --vs-sim), alternating with the defaults",
    )
    parser.add_argument(
        "--vs-iterations", type=int, metavar="N", help="as --vs-substeps, N position-correcting passes per substep"
    )
    parser.add_argument(
        "--vs-relax-iterations", type=int, metavar="N", help="as --vs-substeps, N relaxing passes per substep"
    )
    args = parser.parse_args(argv)
    scheme = {key: getattr(args, f"vs_{key}") for key in SCHEME_FIELDS}
    for error in solver_count_errors(scheme, "--vs-"):
        parser.error(error)
    log = (
        (lambda line: print(line, file=sys.stderr, flush=True)) if args.json else (lambda line: print(line, flush=True))
    )
    if args.kernels:
        report = count_all_kernels(args.sizes, args.batches, log, args.physics)
        if args.json:
            print(json.dumps(report, indent=2))
        return
    report = run(
        args.sizes,
        args.batches,
        args.steps,
        args.repeats,
        args.vs == "jax2d",
        log,
        args.vs_sim,
        scheme,
        args.physics,
        args.vs_physics,
    )
    if args.json:
        print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
