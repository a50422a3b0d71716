"""Dynamics fidelity against Kinetix: the same levels played by the same simple policies in kforge and in kinetix-env.

Levels: Kinetix's hand-designed levels of each size (bundled with `env`), and random levels of each size sampled by
Kinetix's own sampler and written as level files, which both engines then load, so both play the very same levels.
Policies: the no-op policy (deterministic: one episode) and the uniform random multi-discrete policy (`--episodes`
episodes; 280 keep every rate's standard error at or below 0.03). Each episode starts at the level's start and runs
until its first end or one episode's length (256 steps); it ends in success (green touches blue), failure (green
touches red), timeout, or instability (NaN).

A level agrees when the no-op outcome is the same in both engines and the random policy's success and failure
rates differ by at most two standard errors of the difference plus 0.02. Per level the report gives both engines'
rates and the difference in standard errors; per set and size, the share of levels that agree.

Kinetix runs in its own virtualenv (`--kinetix-venv`, built with kinetix-env 3.0.2 on first use, as for
benchmarks/env_speed.py). Physics options of ours can be switched for a measurement (`--sim motor_model=0`) to see which
difference of the engine moves which level. `--kinetix-variant KEY=VALUE` puts Kinetix changed in one respect in
ours' place (benchmarks/kinetix_variants.py): the agreement of Kinetix with itself under a change that any other
engine makes too.

    python -m benchmarks.fidelity --sizes s --random-levels 0            # hand-designed s levels only
    python -m benchmarks.fidelity --sizes s m l --random-levels 1024 --json
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import math
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import jax
import numpy as np

from benchmarks.kinetix_variants import parse_variant, variant_label
from benchmarks.kinetix_venv import DEFAULT_KINETIX_VENV, REPOSITORY, baseline_command, kinetix_python
from benchmarks.machine import describe_machine, provenance
from benchmarks.sim_overrides import (
    add_physics_option,
    add_solver_scheme_options,
    sim_override,
    solver_scheme,
    split_sim_overrides,
)
from benchmarks.sim_overrides import with_solver_scheme as with_sim_scheme
from kforge.engine import physics_scheme
from kforge.engine.schemes import DEFAULT_PHYSICS_SCHEME
from kforge.env import (
    EnvParams,
    Policy,
    StaticEnvParams,
    bundled_level_path,
    list_levels,
    load_level,
    under_scheme,
)
from kforge.env.rollout import Outcome, first_episode_outcomes

KINETIX_BASELINE = "kinetix_fidelity_baseline"
OUTCOME_NAMES = {
    Outcome.TIMEOUT: "timeout",
    Outcome.SUCCESS: "success",
    Outcome.FAILURE: "failure",
    Outcome.UNSTABLE: "unstable",
}
EPISODES_PER_CALL = 4096
"""Most episodes stepped together in one compiled call of ours."""
CALL_ROUNDING = 64
"""A smaller call is padded to a multiple of this many episodes."""
PROGRESS_SECONDS = 60.0
"""Least time between two progress lines of our side."""
AGREEMENT_STANDARD_ERRORS = 2.0
AGREEMENT_SLACK = 0.02
"""Rates agree when they differ by at most AGREEMENT_STANDARD_ERRORS standard errors plus this."""


def with_solver_scheme(static: StaticEnvParams, scheme: dict) -> StaticEnvParams:
    """`static` with the solver scheme's settings in `scheme` (options of `add_solver_scheme_options`; None leaves
    one unchanged)."""
    sim = with_sim_scheme(static.sim, scheme)
    return static if sim == static.sim else dataclasses.replace(static, sim=sim)


def play_ours(
    paths: dict[str, str],
    episodes: int,
    seed: int,
    sim_overrides: dict,
    log,
    scheme=None,
    physics: str = DEFAULT_PHYSICS_SCHEME,
) -> dict:
    """Per level name: the no-op outcome and the random policy's outcome counts, in kforge under the named `physics`
    scheme, then with the solver scheme's counts in `scheme`, if given (`with_solver_scheme`), and `sim_overrides`."""
    named = physics_scheme(physics)
    constants, laws = split_sim_overrides(sim_overrides)
    params = EnvParams(dense_reward_scale=0.0)
    params = params.replace(sim=dataclasses.replace(named.sim(params.sim), **constants))
    groups: dict = {}
    for name, path in paths.items():
        loaded = load_level(path)
        _, static = under_scheme(named, EnvParams(), loaded.static)
        static = dataclasses.replace(static, sim=dataclasses.replace(static.sim, **laws))
        groups.setdefault(with_solver_scheme(static, scheme or {}), []).append((name, loaded))
    report = {}
    for static, members in groups.items():
        levels = jax.tree.map(lambda *xs: np.stack(xs), *(loaded.level for _, loaded in members))
        started = time.perf_counter()
        noop = _outcomes(levels, params, static, 1, None)
        random = _outcomes(levels, params, static, episodes, jax.random.key(seed), log)
        log(f"kforge: {len(members)} levels x {episodes} episodes in {time.perf_counter() - started:.0f} s")
        for index, (name, _) in enumerate(members):
            report[name] = {
                "noop": OUTCOME_NAMES[Outcome(int(noop[index, 0]))],
                "random": {label: int((random[index] == code).sum()) for code, label in OUTCOME_NAMES.items()},
            }
    return report


def _outcomes(levels, params, static, episodes: int, key, log=None) -> np.ndarray:
    """(levels, episodes) first-episode outcome codes under the random policy (with `key`) or the no-op; `log`
    receives a progress line about every PROGRESS_SECONDS."""
    num_levels = jax.tree.leaves(levels)[0].shape[0]
    rows = np.repeat(np.arange(num_levels), episodes)
    call = min(EPISODES_PER_CALL, -(-len(rows) // CALL_ROUNDING) * CALL_ROUNDING)
    policy = Policy.NOOP if key is None else Policy.UNIFORM_RANDOM
    codes, reported = [], time.perf_counter()
    for start in range(0, len(rows), call):
        if log is not None and time.perf_counter() - reported > PROGRESS_SECONDS:
            log(f"kforge: {start // episodes} of {num_levels} levels played")
            reported = time.perf_counter()
        chunk = rows[start : start + call]
        padded = np.concatenate([chunk, np.full(call - len(chunk), chunk[-1])])
        batch = jax.tree.map(lambda x, r=padded: x[r], levels)
        call_key = None if key is None else jax.random.fold_in(key, start)
        result = first_episode_outcomes(batch, params, static, policy, call_key)
        codes.append(np.asarray(result.outcome)[: len(chunk)])
    return np.concatenate(codes).reshape(num_levels, episodes)


def run_kinetix(
    python: Path, arguments: list[str], log, receive=lambda document: None, baseline: str = KINETIX_BASELINE
) -> None:
    """Run Kinetix's side (`benchmarks/<baseline>.py`) with `arguments`: each JSON document it prints goes to
    `receive` as it arrives, and each progress line it writes (`kinetix ...`) to `log`."""
    command = baseline_command(python, baseline, *arguments)
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPOSITORY)
    errors: list[str] = []

    def read_errors() -> None:
        for line in process.stderr:
            errors.append(line)
            if line.startswith("kinetix"):
                log(line.rstrip("\n"))

    reader = threading.Thread(target=read_errors, daemon=True)
    reader.start()
    for line in process.stdout:
        receive(json.loads(line))
    process.wait()
    reader.join()
    if process.returncode != 0:
        raise RuntimeError(f"Kinetix's side failed:\n{''.join(errors)[-3000:]}")


def level_paths(
    python: Path, sizes: list[str], hand: bool, random_levels: int, seed: int, level_dir: Path, log
) -> dict[str, str]:
    """Level name ("hand/s/h1_thrust_over_ball", "random/s/k0-00001") -> level file: the hand-designed levels of
    `sizes` if `hand`, and the first `random_levels` levels of each size that Kinetix's sampler draws with `seed`,
    sampled into `level_dir` by Kinetix's side unless an earlier run left them there."""
    paths = {}
    for size in sizes if hand else ():
        for name in list_levels(size):
            paths[f"hand/{name}"] = str(bundled_level_path(name))
    for size in sizes if random_levels else ():
        files = [level_dir / size / f"k{seed}-{index:05d}.json" for index in range(random_levels)]
        if not all(file.is_file() for file in files):
            log(f"sampling {random_levels} {size} levels with Kinetix's sampler into {level_dir / size}")
            run_kinetix(python, ["--sample", f"{size}:{random_levels}:{seed}", "--sample-dir", str(level_dir)], log)
        paths.update({f"random/{size}/{file.stem}": str(file) for file in files})
    return paths


class KinetixStore:
    """Kinetix's outcomes per level, kept in a JSON file (`--kinetix-results`) under the level file's bytes, the
    episodes and the seed: a level played once is never played again (Kinetix's side does not change between
    measurements of ours), a run that stops keeps every chunk played before, and a longer run plays only new
    levels. A variant of Kinetix (`kinetix_variants`) is kept under its own keys. Without a file, the outcomes
    live for one run."""

    FORMAT = "kforge-fidelity-kinetix-outcomes/2"

    def __init__(self, file: Path | None, episodes: int, seed: int, variant: dict | None = None):
        self.file, self.episodes, self.seed = file, episodes, seed
        self.variant = variant_label(variant or {})
        self.outcomes: dict[str, dict] = {}
        self._digests: dict[str, str] = {}
        if file is not None and file.is_file():
            stored = json.loads(file.read_text())
            if not isinstance(stored, dict) or stored.get("format") != self.FORMAT:
                raise SystemExit(
                    f"{file}: not a file of Kinetix's outcomes in format {self.FORMAT} (an earlier version's? "
                    "delete it or name another --kinetix-results)"
                )
            self.outcomes = stored["outcomes"]

    def key(self, path: str) -> str:
        if path not in self._digests:
            self._digests[path] = hashlib.sha256(Path(path).read_bytes()).hexdigest()
        key = f"{self._digests[path]}/{self.episodes}/{self.seed}"
        return f"{key}/{self.variant}" if self.variant else key

    def missing(self, paths: dict[str, str]) -> dict[str, str]:
        return {name: path for name, path in paths.items() if self.key(path) not in self.outcomes}

    def add(self, played: dict[str, dict]) -> None:
        for path, outcome in played.items():
            self.outcomes[self.key(path)] = {"noop": outcome["noop"], "random": outcome["random"]}
        if self.file is not None:
            partial = self.file.with_name(self.file.name + ".partial")
            partial.write_text(json.dumps({"format": self.FORMAT, "outcomes": self.outcomes}))
            os.replace(partial, self.file)

    def of(self, paths: dict[str, str]) -> dict[str, dict]:
        return {name: self.outcomes[self.key(path)] for name, path in paths.items()}


def kinetix_outcomes(
    python: Path, paths: dict[str, str], listing: Path, args, log, variant: dict | None = None
) -> dict:
    """Kinetix's outcomes per level name (of Kinetix changed by `variant`, if given): those `--kinetix-results`
    holds, and the other levels played now."""
    store = KinetixStore(args.kinetix_results, args.episodes, args.seed, variant)
    missing = store.missing(paths)
    if len(missing) < len(paths):
        log(f"Kinetix's outcomes of {len(paths) - len(missing)} of {len(paths)} levels read from {store.file}")
    if missing:
        listing.write_text("\n".join(missing.values()) + "\n")
        arguments = ["--levels-from", str(listing), "--episodes", str(args.episodes), "--seed", str(args.seed)]
        arguments += [f"--variant={key}={value}" for key, value in sorted((variant or {}).items())]
        run_kinetix(
            python,
            [*arguments, "--chunk-levels", str(args.chunk_levels)],
            log,
            lambda document: store.add(document.get("played", {})),
        )
    return store.of(paths)


def _rate_difference(ours: dict, theirs: dict, outcome: str) -> dict:
    n_ours, n_theirs = sum(ours.values()), sum(theirs.values())
    p_ours, p_theirs = ours[outcome] / n_ours, theirs[outcome] / n_theirs
    error = math.sqrt(p_ours * (1 - p_ours) / n_ours + p_theirs * (1 - p_theirs) / n_theirs)
    difference = p_ours - p_theirs
    return {
        "ours": p_ours,
        "kinetix": p_theirs,
        "standard_error": error,
        "z": difference / error if error > 0 else (0.0 if difference == 0 else math.inf),
        "agree": abs(difference) <= AGREEMENT_STANDARD_ERRORS * error + AGREEMENT_SLACK,
    }


def compare(ours: dict, theirs: dict) -> dict:
    """Per level: both engines' no-op outcome and random-policy rates, and whether they agree."""
    levels = {}
    for name in ours:
        success = _rate_difference(ours[name]["random"], theirs[name]["random"], "success")
        failure = _rate_difference(ours[name]["random"], theirs[name]["random"], "failure")
        noop_agrees = ours[name]["noop"] == theirs[name]["noop"]
        levels[name] = {
            "noop": {"ours": ours[name]["noop"], "kinetix": theirs[name]["noop"], "agree": noop_agrees},
            "random_success": success,
            "random_failure": failure,
            "agree": noop_agrees and success["agree"] and failure["agree"],
        }
    return levels


def summarize(levels: dict) -> dict:
    """Per set and size ("hand/s", "random/m", ...): levels, levels that agree, their share."""
    groups: dict = {}
    for name, level in levels.items():
        group = name.rsplit("/", 1)[0]
        counts = groups.setdefault(group, {"levels": 0, "agree": 0, "disagree": []})
        counts["levels"] += 1
        counts["agree"] += level["agree"]
        if not level["agree"]:
            counts["disagree"].append(name)
    for counts in groups.values():
        counts["share"] = counts["agree"] / counts["levels"]
    return dict(sorted(groups.items()))


def format_table(levels: dict) -> str:
    lines = [
        f"{'level':40s} {'no-op ours/kinetix':22s} {'random success ours/kx (z)':28s} {'failure ours/kx (z)':24s} agree"
    ]
    for name, level in levels.items():
        noop, s, f = level["noop"], level["random_success"], level["random_failure"]
        lines.append(
            f"{name:40s} {noop['ours'] + '/' + noop['kinetix']:22s} "
            f"{s['ours']:.2f}/{s['kinetix']:.2f} ({s['z']:+.1f}){'':12s} {f['ours']:.2f}/{f['kinetix']:.2f} "
            f"({f['z']:+.1f}){'':8s} {'yes' if level['agree'] else 'NO'}"
        )
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", nargs="+", default=["s", "m", "l"], choices=["s", "m", "l"])
    parser.add_argument("--no-hand", action="store_true", help="skip the hand-designed levels")
    parser.add_argument("--random-levels", type=int, default=0, help="Kinetix-sampled random levels per size")
    parser.add_argument("--episodes", type=int, default=280, help="random-policy episodes per level")
    parser.add_argument("--seed", type=int, default=0, help="seed of Kinetix's level sampler and of the actions")
    add_physics_option(parser)
    parser.add_argument(
        "--sim", type=sim_override, action="append", default=[], help="SimParams or law KEY=VALUE of ours"
    )
    add_solver_scheme_options(parser)
    parser.add_argument(
        "--kinetix-variant",
        type=parse_variant,
        action="append",
        default=[],
        help="KEY=VALUE: compare Kinetix changed so, in ours' place, with Kinetix (benchmarks/kinetix_variants.py)",
    )
    parser.add_argument("--kinetix-venv", type=Path, default=DEFAULT_KINETIX_VENV)
    parser.add_argument("--level-dir", type=Path, help="keep the sampled level files here (default: a temp folder)")
    parser.add_argument(
        "--kinetix-results",
        type=Path,
        help="JSON file that keeps Kinetix's outcomes per level, for later runs (other --sim, more levels) and if "
        "this one stops",
    )
    parser.add_argument(
        "--chunk-levels", type=int, default=64, help="levels Kinetix plays per call; each call's outcomes are kept"
    )
    parser.add_argument("--json", action="store_true", help="print the report as one JSON document")
    args = parser.parse_args(argv)
    if args.chunk_levels < 1 or args.episodes < 1:
        parser.error("--chunk-levels and --episodes must be at least 1")
    scheme = solver_scheme(args, parser)
    switched = any(value is not None for value in scheme.values())
    if (args.sim or switched or args.physics != DEFAULT_PHYSICS_SCHEME) and args.kinetix_variant:
        parser.error(
            "--physics, --sim, --substeps, --iterations, --relax-iterations, --block-contacts and "
            "--no-relax-contacts switch our engine and --kinetix-variant replaces it: give one of them"
        )

    def log(line: str) -> None:
        print(line, file=sys.stderr if args.json else sys.stdout, flush=True)

    python = kinetix_python(args.kinetix_venv, log)
    level_dir = (args.level_dir or Path(tempfile.mkdtemp(prefix="kforge-fidelity-"))).absolute()  # for Kinetix's side
    paths = level_paths(python, args.sizes, not args.no_hand, args.random_levels, args.seed, level_dir, log)
    listing = level_dir / "levels.txt"
    listing.parent.mkdir(parents=True, exist_ok=True)

    started = time.perf_counter()
    theirs = kinetix_outcomes(python, paths, listing, args, log)
    kinetix_seconds = time.perf_counter() - started
    started = time.perf_counter()
    variant = dict(args.kinetix_variant)
    if variant:
        ours = kinetix_outcomes(python, paths, listing, args, log, variant)
    else:
        ours = play_ours(paths, args.episodes, args.seed, dict(args.sim), log, scheme, args.physics)
    ours_seconds = time.perf_counter() - started
    compared = f"kinetix-env, {variant_label(variant)}" if variant else "kforge"

    levels = compare(ours, theirs)
    report = {
        **provenance(),
        "machine": describe_machine(),
        "episodes": args.episodes,
        "compared": compared,
        "physics": args.physics,
        "sim_overrides": dict(args.sim),
        **scheme,
        "seconds": {compared: ours_seconds, "kinetix": kinetix_seconds},
        "summary": summarize(levels),
        "levels": levels,
    }
    if args.json:
        print(json.dumps(report, indent=1))
        return
    log(format_table(levels))
    log(f"('ours' is {compared})")
    for group, counts in report["summary"].items():
        log(f"{group}: {counts['agree']}/{counts['levels']} agree ({counts['share']:.0%})")


if __name__ == "__main__":
    main()
