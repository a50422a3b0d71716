"""One unattended accelerator report: engine, env, PPO training and a tiny pipeline run on whatever JAX sees.

Measures, on the default JAX backend (a GPU or TPU when one is installed, else the CPU), in this order and within
`--budget` seconds (a measurement that would start after its section's share of the budget is listed as skipped):

- engine: physics steps/s of ours and, where the `bench` extra is installed, of Jax2D in the same run (timed calls
  alternate), at batches 4,096-65,536 for sizes s, m and l, with Jax2D's published peaks beside them; ours with the
  solver's loops in the form `engine.Batching`'s "auto" picks for the backend and, where `--engine-solver-loops` names
  others, in those side by side, so that one run says which form the backend should use;
- env: env steps/s of our env (step, auto-reset, symbolic observation) at large batches;
- PPO: training env steps/s of `agents.train_levels` at pipeline-sized level batches (configs/ppo_specialist.yaml,
  a few updates), and Kinetix's own PPO in the same run when `--kinetix-venv` holds kinetix-env (see
  benchmarks/kinetix_venv.py; it is not built here, so that the run stays unattended and offline) or `--kinetix-site` a
  folder of its packages (benchmarks/offline_wheels.py);
- pipeline: a tiny `kforge run` end to end in a fresh process (one Ray worker with the accelerator, or the job's own
  process where Ray is not installed; zarr output), its wall time and level outcomes;
- determinism: an engine rollout with random actions run twice on the accelerator (bitwise equal?), timed there, and
  once on the CPU (largest difference), with XLA's deterministic GPU ops off and on (engine/determinism.py), and the
  tiny job run twice, in two processes, with its workers' deterministic ops off (byte-identical data without paying
  for them?).

It prints one JSON document with every figure and, under "targets", each target of the accelerator issue checked
(null where a figure is missing): engine >= 2x Jax2D in the same run and >= Jax2D's published peaks, PPO >= 5x
Kinetix's PPO. `--quick` runs every section at toy sizes (a CPU check that the script works end to end);
`--dry-run` prints the plan without measuring.

    python -m benchmarks.accelerator > accelerator.json
    python -m benchmarks.accelerator --quick
"""

from __future__ import annotations

import argparse
import concurrent.futures
import contextlib
import dataclasses
import functools
import importlib
import json
import os
import subprocess
import sys
import tempfile
import time
import traceback
from pathlib import Path

# The report's own measurements and the pipeline section's Ray worker share one accelerator: JAX must allocate
# as it goes rather than take most of the device's memory at start.
os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

import jax  # noqa: E402
import numpy as np  # noqa: E402

from benchmarks.engine_speed import JAX2D_PUBLISHED_PEAK_STEPS_PER_SECOND  # noqa: E402
from benchmarks.kinetix_venv import REPOSITORY  # noqa: E402
from benchmarks.machine import describe_machine, provenance  # noqa: E402
from kforge.engine.batch_last import SOLVER_LOOP_FORMS  # noqa: E402

XLA_FLAGS = "XLA_FLAGS"
"""The environment variable XLA reads its flags from, once per process."""
ENGINE_SPEEDUP_TARGET = 2.0
"""Engine steps/s at least this many times Jax2D's, measured in the same run."""
PPO_SPEEDUP_TARGET = 5.0
"""PPO training env steps/s at least this many times Kinetix's PPO, measured in the same run."""
SECTION_SHARES = {"engine": 0.45, "env": 0.15, "ppo": 0.25, "pipeline": 0.1, "determinism": 0.05}
"""Share of the time budget by which each section's measurements must have started (cumulative, in this order)."""


@dataclasses.dataclass(frozen=True)
class Plan:
    sizes: tuple[str, ...]
    engine_batches: tuple[int, ...]
    engine_steps: int  # physics steps per timed call
    engine_solver_loops: tuple[str, ...]  # forms of the solver's loops timed beside the one "auto" picks
    env_batches: tuple[int, ...]
    env_steps: int  # env steps per timed call
    ppo_levels: tuple[int, ...]  # levels trained together
    ppo_updates: int  # PPO updates per level per timed call
    ppo_overrides: tuple[str, ...]  # PPOConfig key=value overrides of configs/ppo_specialist.yaml
    pipeline_overrides: tuple[str, ...]  # job config overrides of the tiny pipeline run
    repeats: int
    determinism_batch: int  # scenes of the repeated engine rollout
    determinism_steps: int  # its physics steps


FULL = Plan(
    sizes=("s", "m", "l"),
    engine_batches=(16384, 65536, 4096),  # measured in this order, every size at a batch before the next
    engine_steps=20,
    engine_solver_loops=(),  # the backend's own form only: on a GPU unrolled ran 2.5x looped (H200, s at 16,384)
    env_batches=(4096, 16384),
    env_steps=32,
    ppo_levels=(64, 256),
    ppo_updates=2,
    ppo_overrides=(),
    pipeline_overrides=(
        "split.num_levels=16",
        "split.expert_budget=64000",  # a multiple of num_envs * num_steps = 16 * 125
        "work.levels_per_shard=16",
        "work.levels_per_batch=16",
    ),
    repeats=2,
    determinism_batch=1024,
    determinism_steps=100,
)
QUICK = Plan(
    sizes=("s",),
    engine_batches=(8,),
    engine_steps=2,
    engine_solver_loops=("unrolled", "looped"),
    env_batches=(8,),
    env_steps=2,
    ppo_levels=(2,),
    ppo_updates=1,
    ppo_overrides=("num_envs=4", "num_steps=8", "num_minibatches=2", "update_epochs=1", "select_episodes=1"),
    pipeline_overrides=(
        "split.num_levels=2",
        "split.expert_budget=64",
        "work.levels_per_shard=2",
        "work.levels_per_batch=2",
        "ppo.num_envs=4",
        "ppo.num_steps=8",
        "ppo.num_minibatches=2",
        "ppo.update_epochs=1",
        "ppo.select_episodes=1",
        "collect.window_steps=8",
    ),
    repeats=1,
    determinism_batch=8,
    determinism_steps=4,
)


class Budget:
    """Section deadlines from a total number of seconds and `SECTION_SHARES`."""

    def __init__(self, seconds: float, sections=tuple(SECTION_SHARES)):
        self._start = time.monotonic()
        total_share = sum(SECTION_SHARES[section] for section in sections)
        self._deadlines, elapsed_share = {}, 0.0
        for section in SECTION_SHARES:
            if section in sections:
                elapsed_share += SECTION_SHARES[section] / total_share
                self._deadlines[section] = seconds * elapsed_share

    def enabled(self, section: str) -> bool:
        return section in self._deadlines

    def allows(self, section: str) -> bool:
        """False for a section not asked for, or one whose share of the budget has passed."""
        return section in self._deadlines and time.monotonic() - self._start < self._deadlines[section]


def _attempt(report: dict, section: str, key: str, budget: Budget, measure, log, budget_section: str | None = None):
    """Run `measure()` into report[section][key] unless the time of its budget section (`section` unless named) is
    up; errors are recorded, not raised."""
    budget_section = budget_section or section
    if not budget.enabled(budget_section):
        return None
    entries = report.setdefault(section, {})
    if not budget.allows(budget_section):
        entries[key] = {"skipped": "time budget"}
        log(f"{section} {key}: skipped (time budget)")
        return None
    try:
        entries[key] = measure()
    except Exception as error:  # one failed figure must not lose the rest of an unattended report
        entries[key] = {"error": f"{type(error).__name__}: {error}", "traceback": traceback.format_exc(limit=3)}
        log(f"{section} {key}: failed: {type(error).__name__}: {error}")
        return None
    log(f"{section} {key}: {json.dumps(entries[key])}")
    return entries[key]


def _importable(module: str) -> bool:
    try:
        importlib.import_module(module)
    except ImportError:
        return False
    return True


@dataclasses.dataclass(frozen=True)
class EnginePrograms:
    """One size and batch's compiled engine rollouts: ours in each form of the solver's loops (the backend's "auto"
    form first), then Jax2D's where measured, each with its compile seconds."""

    forms: list[str]
    calls: list
    compile_seconds: list[float]
    with_jax2d: bool


def _timed(build):
    started = time.perf_counter()
    call = build()
    return call, time.perf_counter() - started


def compile_concurrently(builders: dict, threads: int) -> dict:
    """Call every builder (each compiles a program) on `threads` threads at once: XLA compiles outside Python's
    lock, so a machine's idle cores take the next programs. Per key the builder's result, or the error that stopped
    it."""
    with concurrent.futures.ThreadPoolExecutor(max(1, threads)) as pool:
        futures = {key: pool.submit(build) for key, build in builders.items()}
    results = {}
    for key, future in futures.items():
        try:
            results[key] = future.result()
        except Exception as error:  # recorded under the key's figure, where it is measured
            results[key] = error
    return results


def compile_engine_programs(
    sizes, batch: int, plan: Plan, with_jax2d: bool, threads: int
) -> dict[str, EnginePrograms | Exception]:
    """Every engine program of one batch, for every size, compiled at once (`compile_concurrently`); per size its
    programs, or the error that stopped one of them."""
    from benchmarks import jax2d_baseline
    from benchmarks.engine_speed import compile_rollout_ours
    from kforge.engine import Batching

    batching = Batching().resolved()
    forms = list(dict.fromkeys((batching.solver_loops, *plan.engine_solver_loops)))
    builders = {
        (size, index): functools.partial(
            _timed,
            functools.partial(
                compile_rollout_ours,
                size,
                batch,
                plan.engine_steps,
                batching=Batching(batching.mode, batching.chunk_limit, form),
            ),
        )
        for index, form in enumerate(forms)
        for size in sizes
    }
    if with_jax2d:
        builders |= {
            (size, len(forms)): functools.partial(jax2d_baseline.compile_rollout, size, batch, plan.engine_steps)
            for size in sizes
        }
    compiled = compile_concurrently(builders, threads)
    programs: dict[str, EnginePrograms | Exception] = {}
    for size in sizes:
        results = [compiled[(size, index)] for index in range(len(forms) + with_jax2d)]
        errors = [result for result in results if isinstance(result, Exception)]
        programs[size] = (
            errors[0]
            if errors
            else EnginePrograms(forms, [call for call, _ in results], [seconds for _, seconds in results], with_jax2d)
        )
    return programs


def measure_engine(programs: EnginePrograms | Exception, batch: int, plan: Plan, concurrency: int) -> dict:
    """Steps/s of ours in each form of the solver's loops and of Jax2D, timed alternately, from their compiled
    programs (`compile_engine_programs`)."""
    from benchmarks.timing import best_time, best_times_interleaved

    if isinstance(programs, Exception):
        raise programs
    calls, forms, compile_seconds = programs.calls, programs.forms, programs.compile_seconds
    seconds = best_times_interleaved(calls, plan.repeats) if len(calls) > 1 else [best_time(calls[0], plan.repeats)[0]]
    rates = [batch * plan.engine_steps / s for s in seconds]
    by_form = {
        form: {"steps_per_second": rates[k], "compile_seconds": compile_seconds[k]} for k, form in enumerate(forms)
    }
    result = {
        "ours_solver_loops": forms[0],
        "ours_steps_per_second": rates[0],
        "ours_compile_seconds": compile_seconds[0],
        "compiled_concurrently": concurrency,
        "solver_loops": by_form,
    }
    if programs.with_jax2d:
        result |= {
            "jax2d_steps_per_second": rates[-1],
            "jax2d_compile_seconds": compile_seconds[-1],
            "speedup_vs_jax2d": rates[0] / rates[-1],
        }
        for figures in by_form.values():
            figures["speedup_vs_jax2d"] = figures["steps_per_second"] / rates[-1]
    return result


def measure_env(size: str, batch: int, plan: Plan) -> dict:
    from benchmarks.env_speed import measure_steps

    return measure_steps(size, batch, plan.env_steps, plan.repeats)


def _ppo_config(plan: Plan):
    from benchmarks.ppo import load_ppo_config

    return load_ppo_config(None, list(plan.ppo_overrides), plan.ppo_updates)


def compile_ppo_programs(plan: Plan, threads: int) -> dict:
    """Our training program for every size and level batch of the plan, compiled at once (`compile_concurrently`);
    per (size, levels) the program or the error that stopped it."""
    from benchmarks.ppo import compile_ours

    config = _ppo_config(plan)
    builders = {
        (size, levels): functools.partial(compile_ours, size, levels, config)
        for size in plan.sizes
        for levels in plan.ppo_levels
    }
    return compile_concurrently(builders, threads)


def measure_ppo(program, size: str, levels: int, plan: Plan, concurrency: int) -> dict:
    """Training env steps/s of our compiled `program` (`compile_ppo_programs`, `concurrency` programs at once)."""
    from benchmarks.ppo import measure_ours

    if isinstance(program, Exception):
        raise program
    return measure_ours(size, levels, _ppo_config(plan), plan.repeats, program=program) | {
        "compiled_concurrently": concurrency
    }


def measure_kinetix_ppo(python: Path, size: str, plan: Plan, site: Path | None = None) -> dict:
    """Kinetix's PPO in `python`, with the packages of `site` first on its path where given."""
    from benchmarks.ppo import measure_kinetix

    options = argparse.Namespace(updates=plan.ppo_updates, repeats=plan.repeats, kinetix_network="ours")
    environment = None if site is None else _with_path_first(site)
    return measure_kinetix(python, size, _ppo_config(plan), options, environment)


def _with_path_first(folder: Path | str) -> dict[str, str]:
    """This process's environment with `folder` first on PYTHONPATH."""
    return {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(folder), os.environ.get("PYTHONPATH")]))}


def measure_pipeline(
    size: str, plan: Plan, scratch: Path, compile_cache: Path, extra_overrides: tuple[str, ...] = ()
) -> dict:
    """A tiny job end to end into `scratch`, `kforge run` in a fresh process: one Ray worker on the accelerator, or
    where Ray is not installed the job's own process (`ray.num_workers=0`); programs go to `compile_cache`, so a
    second run loads them."""
    from kforge.pipeline.generation import load_config, to_yaml

    with_ray = _importable("ray")
    gpus = 1.0 if jax.default_backend() == "gpu" else 0.0
    output = scratch / f"pipeline-{size}"
    overrides = [
        f"output_dir={output}",
        f"split.name=accelerator/{size}",
        f"split.size={size}",
        f"ray.num_workers={1 if with_ray else 0}",
        f"ray.gpus_per_worker={gpus if with_ray else 0.0}",
        f"compile_cache.dir={compile_cache}",
        "tracking.wandb=disabled",
        *plan.pipeline_overrides,
        *extra_overrides,
    ]
    config_file = scratch / f"pipeline-{size}.yaml"
    scratch.mkdir(parents=True, exist_ok=True)
    config_file.write_text(to_yaml(load_config(None, overrides)))
    command = [sys.executable, "-m", "kforge", "run", str(config_file), "--no-progress", "--json"]
    finished = subprocess.run(command, capture_output=True, text=True, env=_with_path_first(REPOSITORY), cwd=REPOSITORY)
    if finished.returncode != 0:
        raise RuntimeError(f"kforge run exited {finished.returncode}: {finished.stderr.strip()[-2000:]}")
    summary = json.loads(finished.stdout)
    return {
        "ray": with_ray,
        "wall_seconds": summary["seconds"],
        "levels": summary["levels"],
        "outcomes": summary["outcomes"],
    }


def engine_determinism(size: str, batch: int, steps: int) -> dict:
    """A rollout of `steps` with random motor and thruster actions: run twice on the default backend (and timed
    there), and once on the CPU."""
    from benchmarks.scenes import batched_scenes, build_scene
    from benchmarks.timing import best_time
    from kforge.engine import SimParams, step

    static = build_scene(size, 0)[1]
    params = SimParams()
    batched = jax.vmap(lambda state, motor, thruster: step(state, params, motor, thruster, static=static)[0])

    def rollout(states, key):
        def one(states, key):
            motor_key, thruster_key = jax.random.split(key)
            motors = jax.random.uniform(motor_key, (batch, static.num_joints), minval=-1.0, maxval=1.0)
            thrusters = jax.random.uniform(thruster_key, (batch, static.num_thrusters))
            return batched(states, motors, thrusters), None

        return jax.lax.scan(one, states, jax.random.split(key, steps))[0]

    key = jax.random.key(0)
    states = batched_scenes(size, batch)
    compiled = jax.jit(rollout).lower(states, key).compile()
    first, second = compiled(states, key), compiled(states, key)
    seconds, _ = best_time(lambda: compiled(states, key), repeats=3)
    cpu = jax.devices("cpu")[0]
    on_cpu = jax.jit(rollout)(jax.device_put(states, cpu), jax.device_put(key, cpu))
    leaves = zip(jax.tree.leaves(first), jax.tree.leaves(second), jax.tree.leaves(on_cpu), strict=True)
    bitwise, finite, cpu_difference = True, True, 0.0
    for a, b, c in leaves:
        a, b, c = np.asarray(a), np.asarray(b), np.asarray(c)
        bitwise &= a.tobytes() == b.tobytes()
        if np.issubdtype(a.dtype, np.floating):
            finite &= bool(np.isfinite(a).all())
            cpu_difference = max(cpu_difference, float(np.nanmax(np.abs(a - c), initial=0.0)))
    return {
        "batch": batch,
        "steps": steps,
        "repeat_bitwise_equal": bool(bitwise),
        "max_abs_difference_vs_cpu": cpu_difference,
        "finite": finite,
        "steps_per_second": batch * steps / seconds,  # the price of the deterministic ops, beside their absence
    }


def measure_engine_determinism(size: str, batch: int, steps: int) -> dict:
    """`engine_determinism` in fresh processes (XLA reads its flags once per process), with XLA's deterministic GPU
    ops off and on."""
    from kforge.engine.determinism import with_deterministic_ops

    results = {}
    for ops, flag in (("default_ops", "--xla_gpu_deterministic_ops=false"), ("deterministic_ops", "")):
        flags = with_deterministic_ops(f"{os.environ.get(XLA_FLAGS, '')} {flag}".strip())
        command = [sys.executable, "-m", "benchmarks.accelerator", "--engine-determinism", size, str(batch), str(steps)]
        finished = subprocess.run(
            command, env={**os.environ, XLA_FLAGS: flags}, capture_output=True, text=True, check=True, cwd=REPOSITORY
        )
        results[ops] = json.loads(finished.stdout.strip().splitlines()[-1])
    return results


def _data_digests(root: Path) -> dict[tuple[int, str], str]:
    """(level batch, array) -> the digest of its data, as the commit records give it."""
    from kforge.pipeline.storage import iter_records

    return {(r.global_batch, name): e.data_sha256 for r in iter_records(root) for name, e in r.arrays.items()}


WORKERS_WITHOUT_DETERMINISTIC_OPS = ("ray.deterministic_gpu_ops=false",)
"""The tiny job's repeat runs without XLA's deterministic GPU ops: the engine repeats bit for bit without them
(docs/performance.md), and this tells whether the whole pipeline does, so that workers can stop paying
for them."""


def measure_pipeline_determinism(size: str, plan: Plan, scratch: Path, compile_cache: Path) -> dict:
    """The tiny job twice, each in a fresh process into a fresh folder, without XLA's deterministic GPU ops: are its
    stored arrays byte-identical?"""
    digests = []
    for run in ("first", "second"):
        measure_pipeline(size, plan, scratch / run, compile_cache, WORKERS_WITHOUT_DETERMINISTIC_OPS)
        digests.append(_data_digests(scratch / run / f"pipeline-{size}"))
    differing = sorted(
        f"{batch}/{name}" for batch, name in digests[0] if digests[0][batch, name] != digests[1].get((batch, name))
    )
    return {
        "data_arrays": len(digests[0]),
        "byte_identical": not differing and digests[0] == digests[1],
        "differing_arrays": differing[:20],
        "worker_overrides": list(WORKERS_WITHOUT_DETERMINISTIC_OPS),
    }


def check_targets(report: dict) -> dict:
    """Each target of the accelerator issue: true, false, or null where a figure is missing."""
    targets = {"engine_vs_jax2d": {}, "engine_vs_published_peak": {}, "ppo_vs_kinetix": {}}
    for key, figures in report.get("engine", {}).items():
        size = key.split("/")[0]
        speedup = figures.get("speedup_vs_jax2d")
        targets["engine_vs_jax2d"][key] = None if speedup is None else speedup >= ENGINE_SPEEDUP_TARGET
        rate = figures.get("ours_steps_per_second")
        peak = JAX2D_PUBLISHED_PEAK_STEPS_PER_SECOND[size]
        targets["engine_vs_published_peak"][key] = None if rate is None else rate >= peak
    for size, figures in report.get("kinetix_ppo", {}).items():
        theirs = figures.get("steps_per_second")
        ours = [f.get("steps_per_second") for k, f in report.get("ppo", {}).items() if k.startswith(f"{size}/")]
        ours = [rate for rate in ours if rate is not None]
        targets["ppo_vs_kinetix"][size] = (
            None if theirs is None or not ours else max(ours) >= PPO_SPEEDUP_TARGET * theirs
        )
    return targets


def kinetix_interpreter(venv: Path | None, site: Path | None) -> tuple[Path, Path | None] | None:
    """(Python, package folder or None) that runs Kinetix's PPO: a virtualenv's, or this interpreter with a folder of
    packages (`pip install --target`) first on its path, for a machine where no virtualenv can be built."""
    if site is not None:
        return Path(sys.executable), site.resolve()
    if venv is not None:
        return venv.resolve() / "bin" / "python", None
    return None


def run(
    plan: Plan,
    budget_seconds: float,
    kinetix: tuple[Path, Path | None] | None,
    log,
    sections=tuple(SECTION_SHARES),
    compile_threads: int = 1,
    checkpoint=None,
) -> dict:
    """The report of `plan` within `budget_seconds`; each figure is logged and, with `checkpoint`, the report so far
    (its targets checked) handed to it."""
    budget = Budget(budget_seconds, sections)
    with_jax2d = _importable("jax2d")
    if checkpoint is not None:
        given_log = log

        def log(line: str) -> None:
            given_log(line)
            checkpoint(report | {"targets": check_targets(report)})

    report = {
        **provenance(),
        "machine": describe_machine(),
        "backend": jax.default_backend(),
        "devices": [str(device) for device in jax.devices()],
        "plan": dataclasses.asdict(plan),
        "jax2d_in_run": with_jax2d,
        "compile_threads": compile_threads,
        "jax2d_published_peak_steps_per_second": JAX2D_PUBLISHED_PEAK_STEPS_PER_SECOND,
    }
    for batch in plan.engine_batches:  # every size at a batch before the next batch: a short budget covers them all
        programs = {}
        if budget.allows("engine"):
            started = time.perf_counter()
            programs = compile_engine_programs(plan.sizes, batch, plan, with_jax2d, compile_threads)
            log(f"engine: programs at batch {batch} compiled in {time.perf_counter() - started:.0f} s")
        concurrency = min(compile_threads, len(plan.sizes) * (1 + with_jax2d))  # the first form's round, the largest
        for size in plan.sizes:
            _attempt(
                report,
                "engine",
                f"{size}/{batch}",
                budget,
                functools.partial(measure_engine, programs.get(size), batch, plan, concurrency),
                log,
            )
        del programs  # the compiled programs hold their batches' states on the device
    for size in plan.sizes:
        for batch in plan.env_batches:
            _attempt(report, "env", f"{size}/{batch}", budget, functools.partial(measure_env, size, batch, plan), log)
    trainings = {}
    if budget.allows("ppo"):
        started = time.perf_counter()
        trainings = compile_ppo_programs(plan, compile_threads)
        log(f"ppo: training programs compiled in {time.perf_counter() - started:.0f} s")
    concurrency = min(compile_threads, len(plan.sizes) * len(plan.ppo_levels))
    for size in plan.sizes:
        for levels in plan.ppo_levels:
            measure = functools.partial(measure_ppo, trainings.get((size, levels)), size, levels, plan, concurrency)
            _attempt(report, "ppo", f"{size}/{levels}", budget, measure, log)
        if kinetix is not None and kinetix[0].exists():
            _attempt(
                report,
                "kinetix_ppo",
                size,
                budget,
                functools.partial(measure_kinetix_ppo, kinetix[0], size, plan, kinetix[1]),
                log,
                budget_section="ppo",
            )
    del trainings  # the training programs hold their levels on the device
    with tempfile.TemporaryDirectory(prefix="kforge-accelerator-") as scratch:
        scratch, compile_cache = Path(scratch), Path(scratch) / "compile-cache"
        size = plan.sizes[0]
        _attempt(
            report,
            "pipeline",
            size,
            budget,
            functools.partial(measure_pipeline, size, plan, scratch / "once", compile_cache),
            log,
        )
        _attempt(
            report,
            "determinism",
            f"engine/{size}",
            budget,
            functools.partial(measure_engine_determinism, size, plan.determinism_batch, plan.determinism_steps),
            log,
        )
        _attempt(
            report,
            "determinism",
            f"pipeline/{size}",
            budget,
            functools.partial(measure_pipeline_determinism, size, plan, scratch / "twice", compile_cache),
            log,
        )
    report["targets"] = check_targets(report)
    return report


def _write_report(path: Path, report: dict) -> None:
    """`report` as JSON at `path`, replacing the file whole (a reader never sees half of it)."""
    partial = path.with_name(path.name + ".partial")
    partial.write_text(json.dumps(report, indent=2))
    partial.replace(path)


def _log(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="toy sizes: check that every section runs")
    parser.add_argument("--dry-run", action="store_true", help="print the plan and the backend, measure nothing")
    parser.add_argument("--budget", type=float, default=540.0, help="seconds for all measurements (default 540)")
    parser.add_argument("--sizes", nargs="+", choices=["s", "m", "l"], help="override the plan's sizes")
    parser.add_argument("--kinetix-venv", type=Path, help="virtualenv holding kinetix-env, for Kinetix's PPO")
    parser.add_argument(
        "--kinetix-site",
        type=Path,
        help="or a folder holding kinetix-env and its needs (pip install --target), run with this interpreter",
    )
    parser.add_argument(
        "--sections", nargs="+", choices=list(SECTION_SHARES), default=list(SECTION_SHARES), help="what to measure"
    )
    parser.add_argument("--engine-batches", nargs="+", type=int, help="override the plan's engine batches")
    parser.add_argument(
        "--engine-solver-loops",
        nargs="+",
        choices=SOLVER_LOOP_FORMS,
        help="forms of the solver's loops timed beside the backend's own (default: none)",
    )
    parser.add_argument("--env-batches", nargs="+", type=int, help="override the plan's env batches")
    parser.add_argument("--ppo-levels", nargs="+", type=int, help="override the plan's PPO level batches")
    parser.add_argument("--determinism-batch", type=int, help="override the scenes of the repeated engine rollout")
    parser.add_argument(
        "--compile-threads",
        type=int,
        default=os.cpu_count() or 1,
        help="programs compiled at once: the engine's of one batch, our PPO's (default: the machine's cores)",
    )
    parser.add_argument(
        "--out", type=Path, help="also write the report here after every figure, so a run cut short keeps what it had"
    )
    parser.add_argument("--engine-determinism", nargs=3, metavar=("SIZE", "BATCH", "STEPS"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.engine_determinism:  # the child process of `measure_engine_determinism`
        size, batch, steps = args.engine_determinism
        print(json.dumps(engine_determinism(size, int(batch), int(steps))))
        return
    plan = QUICK if args.quick else FULL
    for field in ("sizes", "engine_batches", "engine_solver_loops", "env_batches", "ppo_levels"):
        if getattr(args, field):
            plan = dataclasses.replace(plan, **{field: tuple(getattr(args, field))})
    if args.determinism_batch:
        plan = dataclasses.replace(plan, determinism_batch=args.determinism_batch)
    if args.dry_run:
        print(
            json.dumps(
                {"backend": jax.default_backend(), "budget_seconds": args.budget, "plan": dataclasses.asdict(plan)}
            )
        )
        return
    with contextlib.redirect_stdout(sys.stderr):  # Ray and the measurements may print; stdout holds only the JSON
        kinetix = kinetix_interpreter(args.kinetix_venv, args.kinetix_site)
        checkpoint = None if args.out is None else functools.partial(_write_report, args.out)
        report = run(plan, args.budget, kinetix, _log, tuple(args.sections), max(1, args.compile_threads), checkpoint)
    if args.out is not None:
        _write_report(args.out, report)
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
