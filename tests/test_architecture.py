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
