"""benchmarks/ is a layer above kforge: a package whose modules import kforge like any user, through its packages'
public surfaces (or from the module that defines an internal the benchmark measures on purpose, as
`tests.test_architecture.BENCHMARK_INTERNALS` lists), import each other as `benchmarks.NAME`, never edit `sys.path`,
and are not named after a package."""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest

from tests.test_architecture import BENCHMARK_INTERNALS

REPO = Path(__file__).resolve().parents[2]
BENCHMARKS = REPO / "benchmarks"
PACKAGE_FOLDERS = ("engine", "env", "agents", "pipeline", "jobs", "configs")
"""The checkout's folders that install as `kforge.<folder>`."""


def kforge_package_names() -> set[str]:
    """The last part of every kforge package's name (`engine`, `storage`, ...): names a benchmark must not take."""
    return {
        init.parent.name
        for top in PACKAGE_FOLDERS
        if (REPO / top).is_dir()
        for init in (REPO / top).rglob("__init__.py")
    }


def is_kforge_package(module: str) -> bool:
    """`kforge` or `kforge.X.Y` whose folder X/Y of the checkout is a package."""
    parts = module.split(".")
    return parts[0] == "kforge" and (len(parts) == 1 or (REPO.joinpath(*parts[1:]) / "__init__.py").is_file())


def layer_problems(source: str, module: str, surface, benchmark_modules: set[str], internals=frozenset()) -> list[str]:
    """What in `source` (the text of benchmarks module `module`) breaks the layer's rules; `surface(package)` gives
    the names a kforge package exports; `internals` holds the (module, kforge module without `kforge.`) pairs of
    internals a benchmark may import from their own module."""
    problems = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Attribute) and node.attr == "path" and getattr(node.value, "id", None) == "sys":
            problems.append(f"{module}:{node.lineno} uses sys.path")
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.startswith("kforge.") and not is_kforge_package(alias.name):
                    problems.append(f"{module}:{node.lineno} imports {alias.name}, a private module of kforge")
                elif alias.name.split(".")[0] in benchmark_modules:
                    problems.append(
                        f"{module}:{node.lineno} imports {alias.name}: import it as benchmarks.{alias.name}"
                    )
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [alias.name for alias in node.names]
            top = node.module.split(".")[0]
            if (module, node.module.removeprefix("kforge.")) in internals:
                pass
            elif top == "kforge" and not is_kforge_package(node.module):
                problems.append(f"{module}:{node.lineno} imports from {node.module}, a private module of kforge")
            elif top == "kforge":
                exported = surface(node.module)
                hidden = [n for n in names if n not in exported and not is_kforge_package(f"{node.module}.{n}")]
                if hidden:
                    problems.append(f"{module}:{node.lineno} imports {hidden}, not on {node.module}'s surface")
            elif top == "benchmarks":
                hidden = [n for n in names if n.startswith("_")]
                if hidden:
                    problems.append(f"{module}:{node.lineno} imports private {hidden} from {node.module}")
            elif top in benchmark_modules:
                problems.append(f"{module}:{node.lineno} imports {node.module}: import it as benchmarks.{node.module}")
    return problems


def surface(package: str) -> set[str]:
    """The names a kforge package exports (its `__all__`)."""
    return set(importlib.import_module(package).__all__)


def benchmark_sources() -> dict[str, str]:
    return {path.stem: path.read_text() for path in sorted(BENCHMARKS.glob("*.py"))}


def test_the_checker_finds_path_edits_private_imports_and_script_imports():
    source = (
        "import sys\nsys.path.insert(0, '..')\nfrom kforge.env.sampler import sample_levels\n"
        "from kforge.env import _hidden\nfrom benchmarks.engine_speed import _states\nfrom timing import best_time\n"
        "import kforge.pipeline.storage.layout\n"
    )
    problems = layer_problems(source, "x", lambda package: {"sample_levels"}, {"timing", "engine_speed"})
    assert len(problems) == 6
    for expected, problem in zip(
        (
            "sys.path",
            "private module",
            "not on kforge.env's surface",
            "private ['_states']",
            "as benchmarks.timing",
            "private module",
        ),
        sorted(problems, key=lambda p: int(p.split(":")[1].split()[0])),
        strict=True,
    ):
        assert expected in problem
    public = (
        "from kforge.env import sample_levels\nfrom kforge import engine\nfrom benchmarks.timing import best_time\n"
    )
    assert layer_problems(public, "x", lambda package: {"sample_levels"}, {"timing"}) == []
    measured = "from kforge.env.sampler import sample_levels\n"
    assert layer_problems(measured, "x", lambda package: set(), set(), {("x", "env.sampler")}) == []


def test_benchmarks_is_a_package_and_no_module_is_named_after_a_kforge_package():
    assert (BENCHMARKS / "__init__.py").is_file()
    names = set(benchmark_sources())
    assert {"engine", "storage", "pipeline"} <= kforge_package_names()
    assert names & kforge_package_names() == set()


@pytest.mark.parametrize("module", sorted(benchmark_sources()))
def test_a_benchmark_imports_kforge_through_its_surfaces_and_leaves_sys_path_alone(module):
    sources = benchmark_sources()
    benchmark_modules = set(sources) - {"__init__"}
    problems = layer_problems(sources[module], f"benchmarks.{module}", surface, benchmark_modules, BENCHMARK_INTERNALS)
    assert problems == []
