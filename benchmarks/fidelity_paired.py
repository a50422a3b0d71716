"""Paired fidelity against Kinetix: the same action sequences replayed in both engines, each episode against its twin.

Per level, `--episodes` uniform random multi-discrete action sequences are drawn once, as numpy arrays, from the
seed and the level file's bytes (`paired_inputs`), and played from the level's start in kforge (under `--physics`,
`kinetix` by default) and in kinetix-env 3.0.2 (benchmarks/kinetix_paired_player.py, in its own virtualenv). Kinetix
plays each sequence a second time from the start with every active shape moved by PERTURBATION_M in a direction drawn
with the actions: the ceiling that chaos sets, since no other engine can follow Kinetix more closely than Kinetix
follows itself after a change that small.

Reported per set and size ("hand/s", "random/m", ...) and per size:
- the share of episodes whose end (success, failure or timeout, and the env step it comes at) is the same in kforge
  as in Kinetix, the same share of Kinetix against its perturbed self (the ceiling), and ours minus the ceiling;
- the trajectory error by env step: per episode, the largest position distance [m] and the largest angle
  difference [rad] over the level's active shapes, its median and 95th percentile over episodes, for kforge against
  Kinetix and for perturbed Kinetix against Kinetix (`--plot` draws both). Neither engine resets at an episode's
  end: the physics plays on to the last action, so every step counts every episode.

Kinetix's traces are kept per level file, episodes and seed in `--kinetix-traces` (a run that stops resumes, a run
over more levels plays only the new ones on Kinetix's side).

    python -m benchmarks.fidelity_paired --sizes s --random-levels 0 --episodes 4          # hand-designed s, quick
    python -m benchmarks.fidelity_paired --sizes s m --random-levels 64 32 --level-dir fidelity-levels \\
        --kinetix-traces kx-paired --plot docs/fidelity_trajectory_error.png --json
"""

from __future__ import annotations

import argparse
import functools
import hashlib
import json
import sys
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks.fidelity import level_paths, run_kinetix
from benchmarks.fidelity_trace import EPISODE_STEPS, episode_ends
from benchmarks.kinetix_venv import DEFAULT_KINETIX_VENV, kinetix_python
from benchmarks.machine import describe_machine, provenance
from kforge.engine import PHYSICS_SCHEMES, physics_scheme
from kforge.env import MULTI_DISCRETE_SIZES, ActionType, EnvParams, advance, load_level, reset, under_scheme

KINETIX_PLAYER = "kinetix_paired_player"
SIZES = ("s", "m", "l")
PERTURBATION_M = 1e-6
"""[m] How far the ceiling's runs move each active shape's start position."""
EPISODES_PER_CALL = 256
"""Episodes of ours played in one compiled call (a smaller call is padded to it)."""
REPORTED_STEPS = (1, 8, 32, 64, 128, 256)
"""Env steps whose errors the printed table shows."""
TRACE_FIELDS = ("position", "rotation", "reward", "done")
"""What a trace holds per episode: poses per step (the start at step 0), and reward sign and done per env step."""
CURVE_DIGITS = 3
"""Significant digits of the error curves in the report."""


def level_digest(path: str) -> str:
    """The SHA-256 of a level file's bytes."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def paired_inputs(path: str, episodes: int, seed: int, shapes: int) -> dict[str, np.ndarray]:
    """A level's `actions` (episodes, EPISODE_STEPS, 6) int32, uniform multi-discrete, and `offsets` (episodes,
    shapes, 2) [m] of length PERTURBATION_M in uniform directions: drawn from `seed` and the level file's bytes
    alone, so a level's inputs do not depend on the levels played with it."""
    rng = np.random.default_rng([seed, int(level_digest(path)[:15], 16)])
    columns = [rng.integers(0, size, (episodes, EPISODE_STEPS)) for size in MULTI_DISCRETE_SIZES]
    angle = rng.uniform(0.0, 2 * np.pi, (episodes, shapes))
    offsets = PERTURBATION_M * np.stack([np.cos(angle), np.sin(angle)], -1)
    return {"actions": np.stack(columns, -1).astype(np.int32), "offsets": offsets}


def active_shapes(path: str) -> np.ndarray:
    """(shapes,) bool: the level's active shape slots at its start, polygons then circles (Kinetix's order)."""
    return np.asarray(reset(load_level(path).level).sim.bodies.active)


@functools.partial(jax.jit, static_argnames=("static",))
def _play(levels, level_index, actions, params, static):
    """Per episode: positions and rotations of every body (start at step 0), reward sign and done, without reset."""

    def episode(index, episode_actions):
        start = reset(jax.tree.map(lambda x: x[index], levels))

        def body(state, action):
            stepped, result = advance(state, action, params, static, ActionType.MULTI_DISCRETE)
            reward = jnp.where(result.success, 1.0, jnp.where(result.failure, -1.0, 0.0))
            bodies = stepped.sim.bodies
            return stepped, (bodies.position, bodies.rotation, reward, result.done)

        _, (position, rotation, reward, done) = jax.lax.scan(body, start, episode_actions)
        bodies = start.sim.bodies
        position = jnp.concatenate([bodies.position[None], position])
        return position, jnp.concatenate([bodies.rotation[None], rotation]), reward, done

    return jax.vmap(episode)(level_index, actions)


def play_ours(paths: dict[str, str], inputs: dict[str, dict], physics: str, log) -> dict[str, dict]:
    """Per level name: kforge's trace (`position`, `rotation`, `reward`, `done`) of its inputs' actions under the
    named physics scheme, levels of one static setting EPISODES_PER_CALL episodes per call."""
    params = EnvParams(dense_reward_scale=0.0)
    params = params.replace(sim=physics_scheme(physics).sim(params.sim))
    groups: dict = {}
    for name, path in paths.items():
        loaded = load_level(path)
        _, static = under_scheme(physics_scheme(physics), params, loaded.static)
        groups.setdefault(static, []).append((name, loaded.level))
    traces = {}
    for static, members in groups.items():
        started = time.perf_counter()
        levels = jax.tree.map(lambda *xs: np.stack(xs), *(level for _, level in members))
        actions = np.concatenate([inputs[name]["actions"] for name, _ in members])
        index = np.repeat(np.arange(len(members)), [len(inputs[name]["actions"]) for name, _ in members])
        played = [[] for _ in TRACE_FIELDS]
        for first in range(0, len(actions), EPISODES_PER_CALL):
            rows = np.arange(first, first + EPISODES_PER_CALL).clip(max=len(actions) - 1)
            for parts, value in zip(played, _play(levels, index[rows], actions[rows], params, static), strict=True):
                parts.append(np.asarray(value)[: len(actions) - first])
        played = [np.concatenate(parts) for parts in played]
        for number, (name, _) in enumerate(members):
            chosen = index == number
            traces[name] = dict(zip(TRACE_FIELDS, (x[chosen] for x in played), strict=True))
        log(f"kforge: {len(members)} levels, {len(actions)} episodes in {time.perf_counter() - started:.0f} s")
    return traces


def kept_trace(folder: Path, path: str, episodes: int, seed: int) -> Path:
    """Where `folder` keeps Kinetix's traces of a level file's paired inputs (`paired_inputs`)."""
    return folder / f"{level_digest(path)}-e{episodes}-s{seed}-p{PERTURBATION_M:g}.kinetix.npz"


def kinetix_traces(python: Path, paths: dict, inputs: dict, seed: int, folder: Path, chunk_levels: int, log) -> dict:
    """Per level name: Kinetix's `plain` and `perturbed` traces of its inputs (`paired_inputs` with `seed`;
    benchmarks/kinetix_paired_player.py), those kept in `folder` and the others played now. Raises if Kinetix played
    other actions than ours."""
    folder.mkdir(parents=True, exist_ok=True)
    jobs, outs = [], {}
    for name, path in paths.items():
        outs[name] = kept_trace(folder, path, len(inputs[name]["actions"]), seed)
        if not outs[name].exists():
            inputs_file = outs[name].with_name(outs[name].name.replace(".kinetix.", ".inputs."))
            np.savez(inputs_file, actions=inputs[name]["actions"], offsets=inputs[name]["offsets"])
            jobs.append(f"{Path(path).absolute()}\t{inputs_file}\t{outs[name]}")
    log(f"Kinetix's traces of {len(paths) - len(jobs)} of {len(paths)} levels read from {folder}")
    if jobs:
        listing = folder / "jobs.txt"
        listing.write_text("\n".join(jobs) + "\n")
        run_kinetix(python, ["--jobs", str(listing), "--chunk-levels", str(chunk_levels)], log, baseline=KINETIX_PLAYER)
    traces = {}
    for name, out in outs.items():
        stored = dict(np.load(out))
        if str(stored["actions_sha256"]) != hashlib.sha256(inputs[name]["actions"].tobytes()).hexdigest():
            raise RuntimeError(f"{name}: Kinetix's trace in {out} played other actions than ours")
        traces[name] = {
            run: {k[len(run) + 1 :]: v for k, v in stored.items() if k.startswith(run)}
            for run in ("plain", "perturbed")
        }
    return traces


def same_ends(a: dict, b: dict) -> np.ndarray:
    """Per episode: whether two traces' first episodes end alike, in the same outcome at the same env step."""
    (step_a, outcome_a), (step_b, outcome_b) = episode_ends(a), episode_ends(b)
    return (step_a == step_b) & (outcome_a == outcome_b)


def pose_errors(a: dict, b: dict, active: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(episodes, steps + 1) the largest position distance [m] and angle difference [rad, in 0..pi] over the
    active shapes of two traces, step by step; NaN where either trace is (an engine gone unstable)."""
    distance = np.linalg.norm(a["position"] - b["position"], axis=-1)[..., active]
    with np.errstate(invalid="ignore"):
        turn = np.abs((a["rotation"] - b["rotation"] + np.pi) % (2 * np.pi) - np.pi)[..., active]
    return distance.max(-1), turn.max(-1)


def compare_level(ours: dict, kinetix: dict, active: np.ndarray) -> dict:
    """One level's paired episodes: ends alike and pose errors of ours against Kinetix (`kforge`) and of perturbed
    Kinetix against Kinetix (`ceiling`)."""
    plain = kinetix["plain"]
    compared = {}
    for label, other in (("kforge", ours), ("ceiling", kinetix["perturbed"])):
        position, angle = pose_errors(other, plain, active)
        compared[label] = {"same_end": same_ends(other, plain), "position": position, "angle": angle}
    return compared


def _curve(errors: np.ndarray) -> dict:
    """Median and 95th percentile over episodes (axis 0) per step, to CURVE_DIGITS significant digits; an episode
    counts up to its first NaN step, and `nan_episodes` says how many have one."""

    def rounded(values):
        return [float(f"{value:.{CURVE_DIGITS}g}") for value in values]

    return {
        "median": rounded(np.nanmedian(errors, 0)),
        "p95": rounded(np.nanpercentile(errors, 95, 0)),
        "nan_episodes": int(np.isnan(errors).any(1).sum()),
    }


def summarize(compared: dict[str, dict]) -> dict:
    """Per set and size, and per size ("size/s"): episodes, ends alike in ours and in the ceiling, their shares, ours
    minus the ceiling in points, and the error curves of both."""
    groups: dict[str, list] = {}
    for name, level in compared.items():
        group = name.rsplit("/", 1)[0]
        for key in (group, f"size/{group.rsplit('/', 1)[-1]}"):
            groups.setdefault(key, []).append(level)
    summary = {}
    for group, levels in sorted(groups.items()):
        entry = {"levels": len(levels)}
        for label in ("kforge", "ceiling"):
            same = np.concatenate([level[label]["same_end"] for level in levels])
            entry["episodes"] = len(same)
            entry[label] = {"same_end": int(same.sum()), "share": float(same.mean())}
            entry[label] |= {
                f"{quantity}_error": _curve(np.concatenate([level[label][quantity] for level in levels]))
                for quantity in ("position", "angle")
            }
        entry["kforge_minus_ceiling_points"] = 100 * (entry["kforge"]["share"] - entry["ceiling"]["share"])
        summary[group] = entry
    return summary


def plot(summary: dict, out: Path) -> None:
    """Per set and size, one column: position and angle error by step, median and 95th percentile, for kforge
    against Kinetix and perturbed Kinetix against Kinetix (log scale)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = sorted(
        (group for group in summary if not group.startswith("size/")), key=lambda g: (SIZES.index(g[-1]), g)
    )
    figure, axes = plt.subplots(2, len(groups), figsize=(4 * len(groups), 6.5), sharex=True, squeeze=False)
    for column, group in enumerate(groups):
        entry = summary[group]
        for row, (quantity, unit) in enumerate((("position", "m"), ("angle", "rad"))):
            axis = axes[row, column]
            for label, colour, name in (
                ("kforge", "C0", "kforge vs Kinetix"),
                ("ceiling", "C1", "Kinetix vs 1e-6 moved"),
            ):
                curve = entry[label][f"{quantity}_error"]
                axis.plot(curve["median"], colour, label=f"{name}, median")
                axis.plot(curve["p95"], colour, linestyle="--", label=f"{name}, 95th pct.")
            axis.set_yscale("log")
            axis.set_ylim(1e-8, 20 if quantity == "position" else 4)
            axis.set_ylabel(f"largest {quantity} error [{unit}]")
            axis.grid(alpha=0.3)
        axes[0, column].set_title(f"{group}: {entry['levels']} levels, {entry['episodes']} episodes", fontsize=10)
        axes[1, column].set_xlabel("env step")
    axes[0, 0].legend(fontsize=7)
    figure.tight_layout()
    figure.savefig(out, dpi=110)
    plt.close(figure)


def format_summary(summary: dict) -> str:
    """A table of ends alike per group and the median position error at REPORTED_STEPS."""
    header = f"{'group':10s} {'episodes':>8s} {'kforge':>7s} {'ceiling':>7s} {'diff':>6s}"
    lines = [f"{header}   median position error [m] at steps {REPORTED_STEPS} (kforge | ceiling)"]
    for group, entry in summary.items():
        errors = [
            " ".join(f"{entry[label]['position_error']['median'][step]:.1e}" for step in REPORTED_STEPS)
            for label in ("kforge", "ceiling")
        ]
        lines.append(
            f"{group:10s} {entry['episodes']:8d} {entry['kforge']['share']:7.1%} {entry['ceiling']['share']:7.1%} "
            f"{entry['kforge_minus_ceiling_points']:+6.1f}   {errors[0]} | {errors[1]}"
        )
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", nargs="+", default=["s", "m"], choices=SIZES)
    parser.add_argument("--no-hand", action="store_true", help="skip the hand-designed levels")
    parser.add_argument(
        "--random-levels",
        type=int,
        nargs="+",
        default=[0],
        help="Kinetix-sampled random levels per size: one count for every size, or one per --sizes entry",
    )
    parser.add_argument("--episodes", type=int, default=16, help="paired random-action episodes per level")
    parser.add_argument("--seed", type=int, default=0, help="seed of Kinetix's level sampler and of the inputs")
    parser.add_argument("--physics", choices=list(PHYSICS_SCHEMES), default="kinetix", help="our physics scheme")
    parser.add_argument("--kinetix-venv", type=Path, default=DEFAULT_KINETIX_VENV)
    parser.add_argument("--level-dir", type=Path, help="keep the sampled level files here (default: a temp folder)")
    parser.add_argument("--kinetix-traces", type=Path, help="folder that keeps Kinetix's traces (default: temp)")
    parser.add_argument("--chunk-levels", type=int, default=8, help="levels Kinetix plays per compiled call")
    parser.add_argument("--plot", type=Path, help="PNG that receives the error curves")
    parser.add_argument("--json", action="store_true", help="print the report as one JSON document")
    args = parser.parse_args(argv)
    if args.episodes < 1 or args.chunk_levels < 1:
        parser.error("--episodes and --chunk-levels must be at least 1")
    counts = args.random_levels * len(args.sizes) if len(args.random_levels) == 1 else args.random_levels
    if len(counts) != len(args.sizes):
        parser.error(f"--random-levels: give one count or one per size ({len(args.sizes)}), got {len(counts)}")

    def log(line: str) -> None:
        print(line, file=sys.stderr if args.json else sys.stdout, flush=True)

    python = kinetix_python(args.kinetix_venv, log)
    scratch = Path(tempfile.mkdtemp(prefix="kforge-paired-"))
    level_dir = (args.level_dir or scratch / "levels").absolute()
    paths = {}
    for size, count in zip(args.sizes, counts, strict=True):
        paths |= level_paths(python, [size], not args.no_hand, count, args.seed, level_dir, log)
    active = {name: active_shapes(path) for name, path in paths.items()}
    inputs = {name: paired_inputs(path, args.episodes, args.seed, len(active[name])) for name, path in paths.items()}
    started = time.perf_counter()
    traces = args.kinetix_traces or scratch / "traces"
    theirs = kinetix_traces(python, paths, inputs, args.seed, traces, args.chunk_levels, log)
    kinetix_seconds = time.perf_counter() - started
    started = time.perf_counter()
    ours = play_ours(paths, inputs, args.physics, log)
    ours_seconds = time.perf_counter() - started
    compared = {name: compare_level(ours[name], theirs[name], active[name]) for name in paths}
    summary = summarize(compared)
    if args.plot is not None:
        plot(summary, args.plot)
    report = {
        **provenance(),
        "machine": describe_machine(),
        "physics": args.physics,
        "episodes": args.episodes,
        "seed": args.seed,
        "perturbation_m": PERTURBATION_M,
        "seconds": {"kforge": ours_seconds, "kinetix": kinetix_seconds},
        "summary": summary,
        "levels": {
            name: {label: int(level[label]["same_end"].sum()) for label in ("kforge", "ceiling")}
            for name, level in compared.items()
        },
    }
    if args.json:
        print(json.dumps(report, indent=1))
    log(format_summary(summary))


if __name__ == "__main__":
    main()
