"""The layers use each other's public surfaces only (a benchmark may import an internal it measures from the module
that defines it, as BENCHMARK_INTERNALS lists), imports run downward, each surface holds only names that are used
outside its package or documented as user API and grows past no stated size, and the command line starts light."""

from __future__ import annotations

import ast
import re
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
_EVERY_PACKAGE = _LEARNING | {"pipeline.kinetix", "pipeline.learning", "pipeline.cli"}

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
    "pipeline.cli": _EVERY_PACKAGE - {"pipeline.cli"},
    "jobs": {"configs", "pipeline.generation"},
    "configs": set(),
    "pipeline": {"pipeline.cli"},
    "kforge": {"env", "pipeline.lazy", "pipeline.generation", "pipeline.reading", "pipeline.cli"},
    "benchmarks": _EVERY_PACKAGE,
}
"""Package -> the packages its modules may import (each through its `__init__` only). `kforge` is the user API of
kforge/ (`import kforge`); `benchmarks` imports the packages as any user does."""

TOP_FOLDERS = ("engine", "env", "agents", "pipeline", "jobs", "configs")
"""Folders of the checkout that import as `kforge.<folder>`."""

SURFACES = (
    "engine",
    "env",
    "agents",
    "configs",
    "pipeline.storage",
    "pipeline.reading",
    "pipeline.generation",
    "pipeline.kinetix",
    "pipeline.learning",
    "pipeline.cli",
)
"""Packages whose `__init__` names a public surface in `__all__` (or a lazy surface)."""

USER_DOCS = ("README.md", "docs/*.md")
"""Where a name can be documented as user API: a `from kforge.<package> import ...` line of an example, or the name in
backquotes as `<package>.<name>` (a class also as `<Name>.<member>` or `<Name>(...)`)."""

SURFACE_ALLOWLIST: dict[str, str] = {}
"""`package:name` -> why it is public although nothing outside its package uses it and no doc presents it."""

SURFACE_SIZES = {
    "engine": 36,
    "env": 43,
    "agents": 20,
    "configs": 6,
    "pipeline.storage": 44,
    "pipeline.reading": 3,
    "pipeline.generation": 22,
    "pipeline.kinetix": 3,
    "pipeline.learning": 11,
    "pipeline.cli": 1,
}
"""The most names each surface may export: its size after the cut of issue 53 (215 names, 189 after), when every name
left is used by another package, the command line, the docs or, for want of a higher-level function, a benchmark. A
new name means an old one goes, or a reason to raise the number here."""

_SCHEMES = "chooses the physics scheme by name, the default one (DEFAULT_PHYSICS_SCHEME) unless told"
_RECORDS = "writes level batches and their commit records (ArrayEntry, LevelRecord, LEVEL_ID, write_record) itself"
BENCHMARK_INTERNALS: dict[tuple[str, str], str] = {
    ("benchmarks.accelerator", "engine.batch_last"): "runs each of the solver's loop forms (SOLVER_LOOP_FORMS)",
    ("benchmarks.accelerator", "engine.determinism"): "times XLA's deterministic GPU ops (with_deterministic_ops)",
    ("benchmarks.engine_speed", "engine.schemes"): _SCHEMES,
    ("benchmarks.fidelity", "engine.schemes"): _SCHEMES,
    ("benchmarks.fidelity_trace", "engine.schemes"): _SCHEMES,
    ("benchmarks.sim_overrides", "engine.schemes"): _SCHEMES,
    ("benchmarks.fidelity", "env.rollout"): "compares levels' first-episode outcomes with Kinetix's",
    ("benchmarks.ppo", "agents.ppo"): "times the learner alone (learn, its Batch and optimiser)",
    ("benchmarks.kinetix_transfer_player", "agents.policy"): "samples the BC policy's actions as kforge does (sample)",
    ("benchmarks.object_storage", "pipeline.storage.layout"): _RECORDS,
    ("benchmarks.object_storage", "pipeline.storage.manifest"): _RECORDS,
    ("benchmarks.object_storage", "pipeline.storage.records"): _RECORDS,
    ("benchmarks.storage_codings", "pipeline.storage.shard_store"): "compares Blosc levels with the stored one",
    ("benchmarks.storage_codings", "pipeline.storage.state_codec"): "compares state codings with the stored one",
    ("benchmarks.bc_throughput", "pipeline.learning.data"): "times the BC learner (validation_split)",
    ("benchmarks.bc_throughput", "pipeline.learning.train"): "times the BC learner (Learner)",
    ("benchmarks.kinetix_transfer", "pipeline.learning.evaluation"): "plays level files as kforge's evaluation does",
    ("benchmarks.kinetix_transfer", "pipeline.learning.evaluation_sets"): "names a policy's level size (size_of)",
    ("benchmarks.warm_start", "pipeline.learning.evaluation"): "resolves the dataset's job as evaluation does",
    ("benchmarks.warm_start", "pipeline.learning.evaluation_sets"): "trains on the unseen set's levels (unseen_starts)",
}
"""(benchmark module, internal module of a package) -> why the benchmark imports that internal from the module that
defines it: it measures or mirrors that internal on purpose, so the name stays off the package's surface."""


def package_of(module: str) -> str | None:
    """The package of ALLOWED that holds `module` (the longest match), or None for third-party modules."""
    matches = [name for name in ALLOWED if module == name or module.startswith(name + ".")]
    return max(matches, key=len, default=None)


def _import_targets(node: ast.AST) -> list[str]:
    """The modules an import statement names (`from kforge import engine` names kforge.engine)."""
    if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module == "kforge":
        return [f"kforge.{alias.name}" for alias in node.names]
    if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
        return [node.module]
    if isinstance(node, ast.Import):
        return [alias.name for alias in node.names]
    return []


def import_problems(source: str, module: str) -> list[str]:
    """Imports in `source` (the text of `module`) that reach into another package's private module, or upward."""
    own = package_of(module)
    problems = []
    for node in ast.walk(ast.parse(source)):
        for target in _import_targets(node):
            if target.split(".")[0] in TOP_FOLDERS:
                problems.append(f"{module}:{node.lineno} imports {target}: packages import as kforge.{target}")
                continue
            if target != "kforge" and not target.startswith("kforge."):
                continue
            target = target.removeprefix("kforge.")
            package = package_of(target)
            if package is None or package == own:
                continue
            if package not in ALLOWED[own]:
                problems.append(f"{module}:{node.lineno} imports {target}: {own} may not depend on {package}")
            elif target != package and (module, target) not in BENCHMARK_INTERNALS:
                problems.append(f"{module}:{node.lineno} imports {target}, a private module of {package}")
    return problems


def package_modules():
    """(module, path) of every module of the packages, kforge/ and benchmarks/ (in a checkout they import alike)."""
    for top in (*TOP_FOLDERS, "kforge", "benchmarks"):
        for path in sorted((REPO / top).rglob("*.py")):
            parts = path.relative_to(REPO).with_suffix("").parts
            yield ".".join(parts).removesuffix(".__init__"), path


def surface(init_source: str) -> list[str]:
    """The names an `__init__` exports: its `__all__` list, or the names of its `lazy_surface(...)` map."""
    for node in ast.walk(ast.parse(init_source)):
        if isinstance(node, ast.Assign) and any(
            isinstance(target, ast.Name) and target.id == "__all__" for target in node.targets
        ):
            return [ast.literal_eval(element) for element in node.value.elts]
        if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "lazy_surface":
            return sorted(name for names in ast.literal_eval(node.args[1]).values() for name in names.split())
    return []


def used_names(source: str) -> set[tuple[str, str]]:
    """(package, name) pairs that `source` uses from the packages: names it imports from a package or one of its
    modules, attributes of a package it imports as a module, and names of the lazy surfaces it declares."""
    tree = ast.parse(source)
    used, aliases = set(), {}
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").startswith("kforge"):
            module = node.module.removeprefix("kforge").removeprefix(".")
            for alias in node.names:
                child = f"{module}.{alias.name}".strip(".")
                if child in SURFACES:
                    aliases[alias.asname or alias.name] = child
                elif package_of(module) in SURFACES:
                    used.add((package_of(module), alias.name))
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.removeprefix("kforge.") in SURFACES and alias.asname:
                    aliases[alias.asname] = alias.name.removeprefix("kforge.")
        elif isinstance(node, ast.Call) and getattr(node.func, "id", None) == "lazy_surface":
            for module, names in ast.literal_eval(node.args[1]).items():
                used.update((package_of(module.removeprefix("kforge.")), name) for name in names.split())
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in aliases:
            used.add((aliases[node.value.id], node.attr))
    return used


def documented(package: str, name: str, docs: str) -> bool:
    """Whether `docs` (the text of USER_DOCS) presents `package.name` as user API."""
    for line in re.findall(rf"from kforge\.{re.escape(package)} import ([^\n]*)", docs):
        if name in re.split(r"[\s,()]+", line):
            return True
    patterns = [rf"`[^`\n]*\b(kforge\.)?{re.escape(package)}\.{re.escape(name)}\b[^`\n]*`"]
    if name[0].isupper() and not name.isupper():
        patterns.append(rf"`[^`\n]*\b{re.escape(name)}[.(][^`\n]*`")
    return any(re.search(pattern, docs) for pattern in patterns)


def unused_surface_names(inits: dict[str, str], users: dict[str, str], docs: str) -> list[str]:
    """`package:name` of every exported name (`inits`: package -> its `__init__` source) that no module outside its
    package uses (`users`: module -> source), that no doc presents and that SURFACE_ALLOWLIST does not name."""
    used = {
        (package, name)
        for module, source in users.items()
        for package, name in used_names(source)
        if package != package_of(module)
    }
    return [
        f"{package}:{name}"
        for package, init in inits.items()
        for name in surface(init)
        if (package, name) not in used
        and not documented(package, name, docs)
        and f"{package}:{name}" not in SURFACE_ALLOWLIST
    ]


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
    measured = "from kforge.agents.ppo import learn\n"
    assert import_problems(measured, "benchmarks.ppo") == []
    assert "private module of agents" in import_problems(measured, "benchmarks.experts")[0]


@pytest.mark.parametrize("layer", ["product", "benchmarks"])
def test_every_package_imports_other_packages_through_their_public_surface(layer):
    modules = [(m, path) for m, path in package_modules() if (package_of(m) == "benchmarks") == (layer == "benchmarks")]
    expected = {"benchmarks.timing"} if layer == "benchmarks" else {"engine", "pipeline.storage.writer", "jobs.submit"}
    assert expected | ({"kforge"} if layer == "product" else set()) <= {m for m, _ in modules}
    problems = [problem for module, path in modules for problem in import_problems(path.read_text(), module)]
    assert problems == []


def test_the_surface_checker_finds_names_that_only_their_own_package_uses():
    inits = {
        "env": '__all__ = ["load_level", "EnvParams", "level_to_dict", "goal_reward", "Level"]\n',
        "pipeline.generation": 'x = lazy_surface(__name__, {"kforge.pipeline.generation.run": "run_job summarize"})\n',
    }
    users = {
        "env.sampler": "from kforge.env import goal_reward\n",  # its own package
        "pipeline.cli.levels": "from kforge import env\nenv.level_to_dict(level)\n",
        "benchmarks.speed": "from kforge.pipeline.generation.run import run_job\n",  # a private import still uses it
        "kforge": 'lazy_surface(__name__, {"kforge.env": "EnvParams"})\n',
    }
    docs = "```python\nfrom kforge.env import (Level,)\n```\nand `env.load_level(name)` and `goal_reward`\n"
    assert unused_surface_names(inits, users, docs) == ["env:goal_reward", "pipeline.generation:summarize"]


def test_every_exported_name_is_used_outside_its_package_or_documented():
    inits = {package: (REPO / package.replace(".", "/") / "__init__.py").read_text() for package in SURFACES}
    users = {module: path.read_text() for module, path in package_modules()}
    docs = "\n".join(path.read_text() for pattern in USER_DOCS for path in sorted(REPO.glob(pattern)))
    assert all(surface(init) for init in inits.values())
    assert unused_surface_names(inits, users, docs) == [], (
        "drop these names from their package's __init__ (tests import them from the defining module), or name "
        "why in SURFACE_ALLOWLIST"
    )


def test_no_surface_grows_past_its_curated_size():
    inits = {package: (REPO / package.replace(".", "/") / "__init__.py").read_text() for package in SURFACES}
    sizes = {package: len(surface(init)) for package, init in inits.items()}
    assert set(sizes) == set(SURFACE_SIZES)
    grown = {
        package: (size, SURFACE_SIZES[package]) for package, size in sizes.items() if size > SURFACE_SIZES[package]
    }
    assert not grown, f"surfaces past their size (now, allowed): {grown}; see SURFACE_SIZES"


def test_each_benchmark_internal_is_imported_public_and_off_the_surface():
    """Every BENCHMARK_INTERNALS entry is still imported, names a module without a leading underscore, and brings in
    only names that its package's surface lacks (a name on the surface is imported from the surface)."""
    imported = {}
    for module, path in package_modules():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (module, (node.module or "").removeprefix("kforge.")) in (
                BENCHMARK_INTERNALS
            ):
                imported.setdefault((module, node.module.removeprefix("kforge.")), set()).update(
                    alias.name for alias in node.names
                )
    assert set(imported) == set(BENCHMARK_INTERNALS), "stale BENCHMARK_INTERNALS entries"
    for (module, internal), names in imported.items():
        assert not any(part.startswith("_") for part in internal.split(".")), internal
        exported = surface((REPO / package_of(internal).replace(".", "/") / "__init__.py").read_text())
        assert not names & set(exported), f"{module} imports {sorted(names & set(exported))} from {internal}"


@pytest.mark.parametrize("package", sorted(name for name in ALLOWED if (REPO / name.replace(".", "/")).is_dir()))
def test_every_package_says_its_job(package):
    init = REPO / package.replace(".", "/") / "__init__.py"
    tree = ast.parse(init.read_text())
    assert ast.get_docstring(tree), f"{init.relative_to(REPO)} has no docstring that says its job"


ARCHITECTURE_DOC = REPO / "docs" / "architecture.md"

CHECKOUT_FOLDERS = (*TOP_FOLDERS, "kforge", "benchmarks", "tests", "docs")
"""Folders whose paths docs/architecture.md may name (`pipeline/cli/__init__.py`, `configs/splits/`)."""


def _module_file(parts: list[str], repo: Path) -> Path | None:
    """The source of the module `parts` (without `kforge.`) in `repo`, or None if there is none."""
    base = repo.joinpath(*parts) if parts else repo / "kforge"
    for path in (base / "__init__.py", base.with_suffix(".py")):
        if path.is_file():
            return path
    return None


def _defines(source: str, name: str) -> bool:
    """Whether a module's `source` defines or exports `name`."""
    defined = rf"^(def |class |async def )?{re.escape(name)}\b\s*[(:=]|^(def|class) {re.escape(name)}\b"
    return bool(re.search(defined, source, re.MULTILINE)) or name in surface(source)


def doc_problems(text: str, repo: Path) -> list[str]:
    """Modules, names and paths that `text` names in backquotes and `repo` lacks, and links to missing docs."""
    problems = []
    for code in re.findall(r"`([^`\n]+)`", text):
        for word in code.split():
            word = word.strip(",.;:()")
            parts = word.removeprefix("kforge.").split(".")
            if re.fullmatch(r"(kforge\.)?[a-z_]+(\.\w+)*", word) and (parts[0] in TOP_FOLDERS or word == "kforge"):
                known = max((n for n in range(len(parts) + 1) if _module_file(parts[:n], repo)), default=None)
                rest = parts[known:] if known is not None else parts
                module = _module_file(parts[:known], repo) if known is not None else None
                if module is None or len(rest) > 1 or (rest and not _defines(module.read_text(), rest[0])):
                    problems.append(f"`{word}`: no such module or name")
            elif "/" in word and word.split("/")[0] in CHECKOUT_FOLDERS and not (repo / word).exists():
                problems.append(f"`{word}`: no such path")
    for link in re.findall(r"\]\(([\w./-]+\.md)\)", text):
        if not (repo / "docs" / link).is_file():
            problems.append(f"({link}): no such doc")
    return problems


def module_table_problems(text: str, repo: Path) -> list[str]:
    """Rows `| package | modules | job |` of `text` whose module list differs from the package's modules in `repo`."""
    problems = []
    for package, modules in re.findall(r"^\| `([a-z_.]+)` \| ((?:`\w+`(?:, )?)+) \|", text, re.MULTILINE):
        listed = set(re.findall(r"`(\w+)`", modules))
        folder = repo.joinpath(*package.split("."))
        actual = {path.stem for path in folder.glob("*.py") if path.stem != "__init__"} or {"__init__"}
        if listed != actual:
            problems.append(
                f"{package}: the table lists {sorted(listed - actual)}, leaves out {sorted(actual - listed)}"
            )
    return problems


def test_the_doc_checker_finds_what_the_code_lacks(tmp_path):
    (tmp_path / "env").mkdir()
    (tmp_path / "env" / "__init__.py").write_text('__all__ = ["reset"]\n')
    (tmp_path / "env" / "state.py").write_text("class Level:\n    pass\n\nNO_DISTANCE = 1.0\n")
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "physics.md").write_text("")
    text = (
        "`kforge.env.reset`, `env.state.Level`, `env.state.NO_DISTANCE` and `env/state.py` ([physics](physics.md));\n"
        "`env.sampler`, `env.state.Task`, `kforge.env.step`, `env/levels/` ([kinetix](kinetix.md)) and `pipeline.cli`\n"
        "| `env` | `state`, `actions` | the task |\n"
    )
    assert doc_problems(text, tmp_path) == [
        "`env.sampler`: no such module or name",
        "`env.state.Task`: no such module or name",
        "`kforge.env.step`: no such module or name",
        "`env/levels/`: no such path",
        "`pipeline.cli`: no such module or name",
        "(kinetix.md): no such doc",
    ]
    assert module_table_problems(text, tmp_path) == ["env: the table lists ['actions'], leaves out []"]


def test_the_architecture_doc_names_only_modules_and_paths_that_exist():
    text = ARCHITECTURE_DOC.read_text()
    assert doc_problems(text, REPO) == []
    assert len(re.findall(r"^\| `[a-z_.]+` \| `", text, re.MULTILINE)) == 12  # every package and subpackage
    assert module_table_problems(text, REPO) == []


@pytest.mark.parametrize("package", [name for name in SURFACES if name.startswith("pipeline.")])
def test_each_pipeline_subpackage_says_its_job_in_a_short_docstring(package):
    docstring = ast.get_docstring(ast.parse((REPO / package.replace(".", "/") / "__init__.py").read_text()))
    assert docstring and len(docstring.splitlines()) <= 12


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

    from kforge.engine import SimParams, StaticSimParams

    switches = {
        field.name: type(getattr(SimParams(), field.name)).__name__
        for field in dataclasses.fields(SimParams)
        if type(getattr(SimParams(), field.name)) is not float
    }
    assert not switches, f"SimParams fields that are not floats (law switches belong in StaticSimParams): {switches}"
    static = StaticSimParams()
    laws = [f.name for f in dataclasses.fields(static) if isinstance(getattr(static, f.name), enum.Enum)]
    assert {
        "force_timing",
        "motor_law",
        "contact_law",
        "contact_points",
        "collision_rules",
        "joint_law",
        "contact_order",
    } <= set(laws)
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
