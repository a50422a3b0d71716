"""The layers use each other's public surfaces only, imports run downward, and the command line starts light."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.smoke

REPO = Path(__file__).resolve().parents[1]

_LEARNING = {
    "configs",
    "engine",
    "env",
    "agents",
    "pipeline.lazy",
    "pipeline.storage",
    "pipeline.reading",
    "pipeline.generation",
}

ALLOWED = {
    "engine": set(),
    "env": {"engine"},
    "agents": {"engine", "env"},
    "pipeline.storage": {"engine", "env"},
    "pipeline.reading": {"engine", "env", "pipeline.storage"},
    "pipeline.lazy": set(),
    "pipeline.generation": {"configs", "engine", "env", "agents", "pipeline.lazy", "pipeline.storage"},
    "pipeline.kinetix": {"engine", "env", "pipeline.storage", "pipeline.reading"},
    "pipeline.learning": _LEARNING,
    "pipeline.cli": _LEARNING | {"pipeline.kinetix", "pipeline.learning"},
    "jobs": {"configs", "pipeline.generation"},
    "configs": set(),
    "pipeline": {"pipeline.cli"},
}
"""Package -> the packages its modules may import (each through its `__init__` only)."""


def package_of(module: str) -> str | None:
    """The package of ALLOWED that holds `module` (the longest match), or None for third-party modules."""
    matches = [name for name in ALLOWED if module == name or module.startswith(name + ".")]
    return max(matches, key=len, default=None)


def import_problems(source: str, module: str) -> list[str]:
    """Imports in `source` (the text of `module`) that reach into another package's private module, or upward."""
    own = package_of(module)
    problems = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module == "kforge":
            targets = [f"kforge.{alias.name}" for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            targets = [node.module]
        elif isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        else:
            continue
        for target in targets:
            if package_of(target) is not None:
                problems.append(f"{module}:{node.lineno} imports {target}: packages import as kforge.{target}")
                continue
            target = target.removeprefix("kforge.")
            package = package_of(target)
            if package is None or package == own:
                continue
            if package not in ALLOWED[own]:
                problems.append(f"{module}:{node.lineno} imports {target}: {own} may not depend on {package}")
            elif target != package:
                problems.append(f"{module}:{node.lineno} imports {target}, a private module of {package}")
    return problems


def package_modules():
    for top in ("engine", "env", "agents", "pipeline", "jobs", "configs"):
        for path in sorted((REPO / top).rglob("*.py")):
            module = ".".join(path.relative_to(REPO).with_suffix("").parts)
            yield module.removesuffix(".__init__"), path


def test_the_checker_finds_private_and_upward_imports():
    source = (
        "from kforge.env.level_files import load_level\nimport kforge.pipeline.storage.layout\n"
        "from kforge.agents import PPOConfig\nfrom engine import step\n"
    )
    problems = import_problems(source, "pipeline.reading.loader")
    assert len(problems) == 4
    assert "private module of env" in problems[0]
    assert "private module of pipeline.storage" in problems[1]
    assert "pipeline.reading may not depend on agents" in problems[2]
    assert "import as kforge.engine" in problems[3]
    public = "from kforge.env import load_level\nfrom kforge.pipeline.storage import DONE\nfrom kforge import engine\n"
    assert import_problems(public, "pipeline.reading.x") == []


def test_every_package_imports_other_packages_through_their_public_surface():
    modules = list(package_modules())
    assert {"engine", "env", "agents", "pipeline.cli", "pipeline.storage.writer"} <= {m for m, _ in modules}
    problems = [problem for module, path in modules for problem in import_problems(path.read_text(), module)]
    assert problems == []


@pytest.mark.parametrize("package", sorted(name for name in ALLOWED if (REPO / name.replace(".", "/")).is_dir()))
def test_every_package_names_its_public_surface(package):
    init = REPO / package.replace(".", "/") / "__init__.py"
    tree = ast.parse(init.read_text())
    assert ast.get_docstring(tree), f"{init.relative_to(REPO)} has no docstring naming its public surface"


@pytest.mark.parametrize(
    "arguments",
    [["--help"], ["verify", "--help"], ["run", "--help"], ["bc", "train", "--help"], ["evaluate", "--help"]],
)
def test_the_command_line_answers_help_without_jax_or_ray(arguments):
    probe = (
        "import sys\nfrom kforge.pipeline.cli import main\n"
        f"try:\n    main({arguments!r})\nexcept SystemExit:\n    pass\n"
        "heavy = sorted(name for name in ('jax', 'ray', 'tensorstore', 'zarr') if name in sys.modules)\n"
        "print('HEAVY', heavy)\n"
    )
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, cwd=REPO, check=True)
    assert "usage:" in result.stdout
    assert result.stdout.strip().splitlines()[-1] == "HEAVY []"


def test_sim_params_hold_only_continuous_constants_and_the_laws_are_static():
    """`engine.SimParams` is traced: every field is a float (a law switch there would compile every law into every
    step, and could change under a compiled program). The laws are enum or bool fields of the static
    `engine.StaticSimParams`, each program holding only its own."""
    import dataclasses
    import enum

    from engine import SimParams, StaticSimParams

    switches = {
        field.name: type(getattr(SimParams(), field.name)).__name__
        for field in dataclasses.fields(SimParams)
        if type(getattr(SimParams(), field.name)) is not float
    }
    assert not switches, f"SimParams fields that are not floats (law switches belong in StaticSimParams): {switches}"
    static = StaticSimParams()
    laws = [f.name for f in dataclasses.fields(static) if isinstance(getattr(static, f.name), enum.Enum)]
    assert {"force_timing", "motor_law", "contact_law", "contact_points", "collision_rules", "limit_law"} <= set(laws)
    assert set(laws) <= set(static.physics_options())


def test_every_package_folder_of_the_checkout_is_installed():
    """pyproject.toml lists the packages (the package-dir mapping needs them named); a new subpackage must be added."""
    import tomllib

    declared = set(tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    folders = {
        "kforge." + ".".join(init.parent.relative_to(REPO).parts)
        for top in ("engine", "env", "agents", "configs", "pipeline")
        for init in (REPO / top).rglob("__init__.py")
    }
    assert declared == folders | {"kforge"}
