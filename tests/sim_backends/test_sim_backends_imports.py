"""Every ``rths_hil.sim_backends`` module imports on its own in a fresh interpreter, and the
package's modules import in either order: the import graph has no circle (a circle shows up as
an ImportError for one of the two orders, or as a module that only imports after another)."""

from __future__ import annotations

import ast
import pkgutil
import subprocess
import sys
from pathlib import Path

import pytest
import rths_hil.sim_backends as sim_backends

MODULES = sorted(
    m.name for m in pkgutil.walk_packages(sim_backends.__path__, prefix="rths_hil.sim_backends.")
)


def _run(code: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False
    )


def test_the_package_lists_its_modules() -> None:
    for name in ("registry", "models", "effects", "modelfile", "plant", "first_order"):
        assert f"rths_hil.sim_backends.{name}" in MODULES


@pytest.mark.parametrize("module", MODULES)
def test_each_module_imports_alone(module: str) -> None:
    done = _run(f"import {module}")
    assert done.returncode == 0, done.stderr


@pytest.mark.parametrize("order", [MODULES, MODULES[::-1]], ids=["forward", "backward"])
def test_all_modules_import_in_either_order(order: list[str]) -> None:
    done = _run("\n".join(f"import {m}" for m in order))
    assert done.returncode == 0, done.stderr


def _local_imports(path: Path, package: str) -> set[str]:
    """Modules of ``rths_hil.sim_backends`` that ``path`` imports (top level or not)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    found: set[str] = set()
    base = package.split(".")
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                parts = base[: len(base) - node.level + 1]
                mod = ".".join([*parts, *(node.module.split(".") if node.module else [])])
            else:
                mod = node.module or ""
            names = [f"{mod}.{a.name}" for a in node.names]
            found.update(n for n in [mod, *names] if n in MODULES)
        elif isinstance(node, ast.Import):
            found.update(a.name for a in node.names if a.name in MODULES)
    return found


def test_the_import_graph_has_no_circle() -> None:
    root = Path(sim_backends.__file__).parent
    graph: dict[str, set[str]] = {}
    for module in MODULES:
        rel = module.removeprefix("rths_hil.sim_backends.").split(".")
        path = root.joinpath(*rel).with_suffix(".py")
        if not path.exists():
            path = root.joinpath(*rel, "__init__.py")
        package = module if path.name == "__init__.py" else module.rpartition(".")[0]
        graph[module] = _local_imports(path, package) - {module}
    state: dict[str, int] = {}

    def visit(node: str, trail: list[str]) -> None:
        state[node] = 1
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                cycle = [*trail[trail.index(nxt) :], nxt] if nxt in trail else [node, nxt]
                pytest.fail("import circle: " + " -> ".join(cycle))
            if nxt not in state:
                visit(nxt, [*trail, nxt])
        state[node] = 2

    for module in MODULES:
        if module not in state:
            visit(module, [module])
