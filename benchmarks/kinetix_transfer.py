"""Transfer: a kforge BC policy played inside kinetix-env 3.0.2, its network reading Kinetix's own entity
observations, beside its success in kforge on the same levels.

    python -m benchmarks.kinetix_transfer --run outputs/bc/RUN --sampled-levels 512 \\
        --json benchmarks/results/kinetix_transfer.json

Two sets of levels: Kinetix's hand-designed levels of the sizes the network reads (all 74 for the entity transformer)
and `--sampled-levels` levels of the dataset's size from Kinetix's own level sampler (key `--sampler-seed`, written
as level files by `benchmarks.kinetix_fidelity_baseline --sample`). Each set is played in Kinetix
(`benchmarks.kinetix_transfer_player`, in Kinetix's virtualenv; the policy's network reads Kinetix's
`EntityObservation` mapped by `from_kinetix_observation`) and in kforge under the kinetix scheme, by the BC policy,
the no-op and the uniform random policy, `--episodes` first episodes per level from the level's start. Reported per
set and engine: success rates with standard errors, BC minus random paired by level, and BC's success in Kinetix
minus in kforge with the standard error of that difference. Each engine's outcomes of each set are kept in
`--work-dir`, so an interrupted run resumes where it stopped.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
from flax import serialization

from benchmarks.kinetix_transfer_player import NETWORK_FILE, PARAMS_FILE
from benchmarks.kinetix_venv import DEFAULT_KINETIX_VENV, REPOSITORY, baseline_command, kinetix_python
from benchmarks.machine import describe_machine, provenance
from kforge.engine import physics_scheme
from kforge.env import bundled_level_path, list_levels
from kforge.pipeline.learning import load_policy
from kforge.pipeline.learning.evaluation import level_set_entry, play_level_files, readable_sizes
from kforge.pipeline.learning.evaluation_sets import size_of

KINETIX_SCHEME = "kinetix"
"""kforge plays the levels under Kinetix's physics scheme."""
OUTCOME_KINDS = ("success", "failure")
"""What the Kinetix side reports of each episode."""
SAMPLED_LEVELS = 512
"""Levels drawn from Kinetix's sampler by default."""
SAMPLER_SEED = 0
"""Key of Kinetix's level sampler by default."""


def export_policy(policy, folder: Path) -> Path:
    """The policy's network sizes and parameters as files the Kinetix side reads."""
    folder.mkdir(parents=True, exist_ok=True)
    network = {name: getattr(policy.network, name) for name in policy.network.__dataclass_fields__}
    network["architecture"] = policy.network.architecture.value
    (folder / NETWORK_FILE).write_text(json.dumps(network))
    (folder / PARAMS_FILE).write_bytes(serialization.msgpack_serialize(serialization.to_state_dict(policy.params)))
    return folder


def sampled_files(python: Path, size: str, count: int, seed: int, folder: Path, log) -> list[str]:
    """Paths of `count` levels of `size` from Kinetix's sampler with key `seed` (sampled once, then reused)."""
    paths = [folder / size / f"k{seed}-{index:05d}.json" for index in range(count)]
    if not all(path.is_file() for path in paths):
        log(f"sampling {count} {size} levels with Kinetix's sampler (key {seed})")
        command = baseline_command(python, "kinetix_fidelity_baseline", "--sample", f"{size}:{count}:{seed}")
        sample = [*command, "--sample-dir", str(folder.absolute())]
        subprocess.run(sample, check=True, cwd=REPOSITORY, stdout=subprocess.DEVNULL)  # the paths are known
    return [str(path.absolute()) for path in paths]


def kinetix_played(python: Path, policy_dir: Path, files: dict[str, list[str]], episodes: int, seed: int, cache: Path):
    """size -> (files, outcomes) of every player in Kinetix; kept in `cache`, which a re-run reads instead."""
    if not cache.is_file():
        listing = cache.with_suffix(".levels")
        listing.write_text("\n".join(path for paths in files.values() for path in paths))
        command = baseline_command(python, "kinetix_transfer_player", "--policy", str(policy_dir.absolute()))
        command += ["--levels-from", str(listing.absolute()), "--episodes", str(episodes), "--seed", str(seed)]
        output = subprocess.run(command, check=True, cwd=REPOSITORY, stdout=subprocess.PIPE, text=True).stdout
        documents = [json.loads(line) for line in output.splitlines() if line.startswith("{")]
        cache.write_text(json.dumps({document["size"]: document["played"] for document in documents}))
    by_size = json.loads(cache.read_text())
    played = {}
    for size, paths in files.items():
        levels = by_size[size]
        outcomes = {
            name: tuple(
                np.asarray([levels[path][name][kind] for path in paths], bool) for kind in ("success", "failure")
            )
            for name in ("bc", "noop", "random")
        }
        played[size] = (paths, outcomes)
    return played


def engine_gap(kinetix: dict, kforge: dict) -> dict:
    """BC's success in Kinetix minus in kforge, with the standard error of the difference (independent episodes)."""
    a, b = kinetix["from_start"]["bc"], kforge["from_start"]["bc"]
    return {"difference": a["success"] - b["success"], "se": math.hypot(a["success_se"], b["success_se"])}


def transfer(
    run_dir: Path,
    sampled_levels: int,
    episodes: int,
    seed: int,
    sampler_seed: int,
    work_dir: Path,
    venv: Path,
    log,
) -> dict:
    """The transfer report of the BC run in `run_dir`: per set, Kinetix's and kforge's entries side by side."""
    policy = load_policy(run_dir)
    scheme = physics_scheme(KINETIX_SCHEME)
    sizes = readable_sizes(policy, scheme)
    python = kinetix_python(venv, log)
    policy_dir = export_policy(policy, work_dir / f"policy-step-{policy.step}")
    dataset_size = size_of(policy.static, scheme)
    sets = {
        "hand": {size: [str(bundled_level_path(name)) for name in list_levels(size)] for size in sizes},
        "kinetix_sampler": {
            dataset_size: sampled_files(python, dataset_size, sampled_levels, sampler_seed, work_dir / "levels", log)
        },
    }
    report = {}
    for name, files in sets.items():
        log(f"{name}: playing {sum(map(len, files.values()))} levels in Kinetix")
        cache = work_dir / f"kinetix-{name}-step-{policy.step}-episodes-{episodes}-seed-{seed}.json"
        kinetix = level_set_entry(kinetix_played(python, policy_dir, files, episodes, seed, cache))
        log(f"{name}: playing them in kforge")
        kforge = play_level_files(policy, files, scheme, episodes, seed)
        report[name] = {"kinetix": kinetix, "kforge": kforge, "bc_kinetix_minus_kforge": engine_gap(kinetix, kforge)}
        log(format_rows(name, report[name]))
    return {"policy": str(run_dir), "step": policy.step, "episodes": episodes, "seed": seed, "sets": report}


def format_rows(name: str, entry: dict) -> str:
    """One line per engine: success of BC, no-op and random, and BC minus random."""
    lines = []
    for engine in ("kinetix", "kforge"):
        rates = entry[engine]["from_start"]
        gain = rates["bc_minus_random"]
        lines.append(
            f"{name:<16} {engine:<8} n={entry[engine]['levels']:>4} BC {rates['bc']['success']:.3f}"
            f"±{rates['bc']['success_se']:.3f}  no-op {rates['noop']['success']:.3f}  random "
            f"{rates['random']['success']:.3f}  BC-random {gain['difference']:+.3f}±{gain['se']:.3f}"
        )
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", type=Path, required=True, help="a BC run directory (kforge bc train)")
    parser.add_argument("--sampled-levels", type=int, default=SAMPLED_LEVELS, help="levels from Kinetix's sampler")
    parser.add_argument("--sampler-seed", type=int, default=SAMPLER_SEED, help="key of Kinetix's level sampler")
    parser.add_argument("--episodes", type=int, default=8, help="first episodes per level and player")
    parser.add_argument("--seed", type=int, default=0, help="seed of the episode keys")
    parser.add_argument("--work-dir", type=Path, default=Path("outputs/benchmarks/kinetix_transfer"))
    parser.add_argument("--kinetix-venv", type=Path, default=DEFAULT_KINETIX_VENV)
    parser.add_argument("--json", type=Path, help="write the report here")
    args = parser.parse_args(argv)

    def log(line: str) -> None:
        print(line, file=sys.stderr, flush=True)

    args.work_dir.mkdir(parents=True, exist_ok=True)
    result = transfer(
        args.run,
        args.sampled_levels,
        args.episodes,
        args.seed,
        args.sampler_seed,
        args.work_dir,
        args.kinetix_venv,
        log,
    )
    report = provenance() | {"machine": describe_machine()} | result
    for name, entry in result["sets"].items():
        print(format_rows(name, entry))
    if args.json:
        args.json.write_text(json.dumps(report, indent=1) + "\n")


if __name__ == "__main__":
    main()
