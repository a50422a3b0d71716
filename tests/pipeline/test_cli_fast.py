"""The command line answers argument errors before importing anything heavy (JAX, Ray, zarr, wandb), and the names
it parses with equal the engine's and env's own."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from kforge.pipeline.cli import DATASET_METADATA, ENV_SIZES, PHYSICS_SCHEME_NAMES, PLAY_PHYSICS_SCHEME, POLICY_NAMES
from kforge.pipeline.cli.demo import DEMO_RENDER_EVERY

pytestmark = pytest.mark.smoke

REPO = Path(__file__).resolve().parents[2]
HEAVY_MODULES = ("jax", "ray", "tensorstore", "zarr", "wandb")


def argument_errors(tmp: Path) -> list[list[str]]:
    """Commands whose arguments alone are wrong: each must exit 2 before a heavy import."""
    missing, level = str(tmp / "missing"), str(tmp / "level.json")
    looks_like_a_dataset = tmp / "dataset"
    (looks_like_a_dataset / "data").mkdir(parents=True)
    (looks_like_a_dataset / DATASET_METADATA).write_text("{}")  # passes the path check; never opened
    dataset = str(looks_like_a_dataset)
    return [
        ["levels", "sample", "--size", "x", "--seed", "0", "--num", "1"],
        ["levels", "sample", "--size", "s", "--seed", "0", "--num", "0"],
        ["levels", "preview", level, "--out", str(tmp / "start.bmp")],
        ["levels", "preview"],
        ["levels", "export", "1M/s", "zero"],
        ["levels", "list", "--size", "xl"],
        ["levels", "import", level],
        ["render", level, "--steps", "0"],
        ["render", level, "--physics", "jax2d"],
        ["verify", missing],
        ["verify", str(tmp)],
        ["stats", missing],
        ["export", "--format", "kinetix", missing, str(tmp / "out")],
        ["export", "--format", "zarr2", missing, str(tmp / "out")],
        ["bc", "train", missing],
        ["bc", "train", missing, "--stop-after", "0"],
        ["bc", "train", dataset, "train.batch_size=x"],
        ["bc", "train", dataset, "model.architecture=cnn"],
        ["bc", "train", dataset, "model.attention_size=30"],
        ["evaluate", missing],
        ["evaluate", missing, "--episodes", "0"],
        ["evaluate", missing, "--max-levels", "0"],
        ["evaluate", missing, "--on", "seen"],
        ["run", "1M/s", "--max-batches", "x"],
        ["run", "1M/s", "--scale", "huge"],
        ["run", "1M/s", "split.num_levelz=3"],
        ["run", "1M/s", "--scale", "tiny", "ppo.num_minibatches=3"],
        ["run", "1M/s", "ppo.num_steps=7"],
        ["run", "1M/s", "ppo.gamma=1.5"],
        ["run", "1M/s", "experts.budget_mode=streamed", "ppo.select_every_updates=7"],
        ["levels", "export", "1M/s", "0", "ppo.num_envs=0"],
        ["levels", "export", "1M/s", "0", "split.num_levelz=3"],
        ["demo", "--steps", "1"],
        ["demo", "--steps", "x"],
    ]


def test_argument_errors_exit_2_before_any_heavy_import(tmp_path):
    cases = argument_errors(tmp_path)
    probe = (
        "import json, sys\nfrom kforge.pipeline.cli import main\n"
        f"for argv in {cases!r}:\n"
        "    try:\n        main(argv)\n        code = 0\n    except SystemExit as stop:\n        code = stop.code\n"
        f"    heavy = sorted(name for name in {HEAVY_MODULES!r} if name in sys.modules)\n"
        "    print(json.dumps([argv, code, heavy]))\n"
    )
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, cwd=REPO, check=True)
    outcomes = [json.loads(line) for line in result.stdout.splitlines()]
    assert [argv for argv, _, _ in outcomes] == cases
    assert [(argv, code, heavy) for argv, code, heavy in outcomes if code != 2 or heavy] == []


def test_the_names_parsed_are_the_engines_and_envs():
    from kforge.engine import KINETIX_SIZES, PHYSICS_SCHEMES
    from kforge.engine.demo import RENDER_EVERY
    from kforge.env import BUNDLED_SIZES, Policy

    assert ENV_SIZES == tuple(KINETIX_SIZES) == tuple(BUNDLED_SIZES)
    assert set(PHYSICS_SCHEME_NAMES) == set(PHYSICS_SCHEMES) and PLAY_PHYSICS_SCHEME in PHYSICS_SCHEMES
    assert POLICY_NAMES == tuple(policy.value for policy in Policy) and POLICY_NAMES[0] == Policy.NOOP.value
    assert DEMO_RENDER_EVERY == RENDER_EVERY


def test_the_bc_names_checked_without_jax_are_the_networks_and_evaluations():
    from kforge.agents import Architecture
    from kforge.pipeline.learning import evaluate_policy
    from kforge.pipeline.learning.config import ARCHITECTURES, LEVEL_SETS

    assert ARCHITECTURES == tuple(architecture.value for architecture in Architecture)
    with pytest.raises(ValueError, match="unknown level set 'seen'; expected some of train, validation, unseen, hand"):
        evaluate_policy(None, ("seen",))
    assert LEVEL_SETS == ("train", "validation", "unseen", "hand")


def test_kforge_evaluate_plays_as_many_unseen_levels_by_default_as_the_library():
    from kforge.pipeline.cli import evaluate as evaluate_command
    from kforge.pipeline.learning.evaluation_sets import UNSEEN_LEVELS

    args, _ = evaluate_command._parse_args(["a-run"], "kforge evaluate")
    assert args.unseen_levels == evaluate_command.UNSEEN_LEVELS == UNSEEN_LEVELS == 512


def test_render_and_preview_play_kinetix_unless_told_otherwise():
    from kforge.pipeline.cli import levels, render

    assert PLAY_PHYSICS_SCHEME == "kinetix"
    _, subcommands = levels._parser("kforge levels")
    assert subcommands["preview"].get_default("physics") == "kinetix"
    assert render._parser("kforge render").get_default("physics") == "kinetix"
