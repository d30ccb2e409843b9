"""The house's layers hold: import-linter's contracts (pyproject.toml) are kept.

A wrong import (the service importing the simulator, the ground importing the command line, two
top-level packages importing each other) fails this test and so CI.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("core", "config", "protocol", "vision", "plant_sim", "controller", "planer")


def test_import_linter_contracts_are_kept():
    pytest.importorskip("importlinter", reason="import-linter comes with the [test] extra")
    proc = subprocess.run(
        [sys.executable, "-c", "import sys; from importlinter.cli import lint_imports_command;"
         " sys.exit(lint_imports_command())"],
        cwd=ROOT, capture_output=True, text=True, check=False,
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-2000:]
    assert "broken" not in proc.stdout.split("Contracts:")[-1].replace("0 broken", ""), proc.stdout


def _top_level_imports(package: str) -> set[str]:
    """Every project package that a module of ``package`` imports, inside functions too."""
    found: set[str] = set()
    for path in (ROOT / package).rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            else:
                continue
            found |= {n.split(".")[0] for n in names if n.split(".")[0] in PACKAGES}
    return found - {package}


def test_no_circle_between_top_level_packages():
    """The package graph (imports inside functions included) has no cycle."""
    graph = {p: _top_level_imports(p) for p in PACKAGES}
    state: dict[str, int] = {}

    def visit(p: str, path: list[str]) -> None:
        state[p] = 1
        for q in sorted(graph[p]):
            assert state.get(q) != 1, "import circle: " + " -> ".join([*path, p, q])
            if q not in state:
                visit(q, [*path, p])
        state[p] = 2

    for p in PACKAGES:
        if p not in state:
            visit(p, [])
    assert "plant_sim" not in graph["controller"] and "controller" not in graph["plant_sim"]


def _modules():
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            yield path, ast.parse(path.read_text(), filename=str(path))


def test_no_class_over_500_lines():
    """A class that grows past a few hundred lines is two classes (under 500)."""
    big = [
        f"{path.relative_to(ROOT)}:{node.name} ({node.end_lineno - node.lineno + 1} lines)"
        for path, tree in _modules()
        for node in ast.walk(tree)
        if isinstance(node, ast.ClassDef) and node.end_lineno - node.lineno + 1 >= 500
    ]
    assert not big, big


def _catches_bare_exception(handler: ast.ExceptHandler) -> bool:
    types = handler.type.elts if isinstance(handler.type, ast.Tuple) else [handler.type]
    return handler.type is None or any(
        isinstance(t, ast.Name) and t.id in ("Exception", "BaseException") for t in types
    )


def test_at_most_three_handlers_swallow_any_exception_each_says_why():
    """Only the supervisor boundaries (one per process) catch everything, with a comment why.

    A handler that catches ``BaseException`` and re-raises (clean-up on the way out) does not
    swallow anything and is not counted.
    """
    found = []
    for path, tree in _modules():
        lines = path.read_text().splitlines()
        for node in ast.walk(tree):
            if not (isinstance(node, ast.ExceptHandler) and _catches_bare_exception(node)):
                continue
            if node.body and isinstance(node.body[-1], ast.Raise) and node.body[-1].exc is None:
                continue  # clean-up, then re-raised
            here = f"{path.relative_to(ROOT)}:{node.lineno}"
            around = " ".join(lines[node.lineno - 2:node.lineno + 1])
            assert "#" in around, f"{here}: a catch-all handler must say why in a comment"
            found.append(here)
    assert len(found) <= 3, found
