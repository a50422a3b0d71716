"""Who uses each name of each package surface: `python -m tests.surface_users` prints one line per exported name with
its users outside the package: other packages (`package:module`), the command line (`cli:module`), benchmarks,
tests (`(mod)`: imported from the defining module) and the docs (`DOC`: presented as user API in README.md or docs/).
A name marked `*` has no user but benchmarks and tests: a candidate to leave the surface (tests/test_architecture.py
says how)."""

from __future__ import annotations

import ast
from collections import defaultdict

from tests.test_architecture import (
    REPO,
    SURFACES,
    USER_DOCS,
    documented,
    package_modules,
    package_of,
    surface,
    used_names,
)


def _modules():
    """(module, path) of the packages, kforge/, benchmarks/ and tests/."""
    yield from package_modules()
    for path in sorted((REPO / "tests").rglob("*.py")):
        yield ".".join(path.relative_to(REPO).with_suffix("").parts).removesuffix(".__init__"), path


def _through_surface(source: str) -> set[tuple[str, str]]:
    """(package, name) pairs that `source` imports from a package's `__init__` itself (not from one of its modules)."""
    found = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").startswith("kforge"):
            package = node.module.removeprefix("kforge").removeprefix(".")
            if package in SURFACES:
                found.update((package, alias.name) for alias in node.names)
    return found


def _kind(module: str) -> str:
    """The kind of user a module is: tests, bench, cli, or the product package that holds it."""
    if module.startswith("tests"):
        return "tests"
    package = package_of(module) or module
    return {"benchmarks": "bench", "pipeline.cli": "cli"}.get(package, package)


def surface_users() -> dict[str, dict[str, dict[str, set[str]]]]:
    """package -> exported name -> kind of user (`tests(mod)` for a defining-module import) -> the user modules."""
    users: dict[tuple[str, str], dict[str, set[str]]] = defaultdict(lambda: defaultdict(set))
    for module, path in _modules():
        source = path.read_text()
        direct = _through_surface(source)
        for package, name in used_names(source):
            if package == package_of(module) and not module.startswith("tests"):
                continue
            kind = _kind(module) + ("(mod)" if module.startswith("tests") and (package, name) not in direct else "")
            users[package, name][kind].add(module.rsplit(".", 1)[-1])
    inits = {package: (REPO / package.replace(".", "/") / "__init__.py").read_text() for package in SURFACES}
    return {package: {name: users[package, name] for name in surface(init)} for package, init in inits.items()}


def main() -> None:
    docs = "\n".join(path.read_text() for pattern in USER_DOCS for path in sorted(REPO.glob(pattern)))
    total = 0
    for package, names in surface_users().items():
        total += len(names)
        print(f"{package} ({len(names)})")
        for name, kinds in names.items():
            doc = documented(package, name, docs)
            product = doc or any(kind not in ("bench", "tests", "tests(mod)") for kind in kinds)
            used = "; ".join(f"{kind}: {', '.join(sorted(modules))}" for kind, modules in sorted(kinds.items()))
            print(f"  {'' if product else '*'}{name:<30} {'DOC ' if doc else ''}{used}")
    print(f"total {total}")


if __name__ == "__main__":
    main()
