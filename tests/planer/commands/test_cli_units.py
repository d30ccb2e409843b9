"""Micrometres are µm in what the user reads: printed lines and docs (identifiers keep ``_um``)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from controller.quality.log import QualityLog
from tests.controller.quality.test_report import QC, make_run

ROOT = Path(__file__).parents[3]
BARE_UM = re.compile(r"(?<![\w.`/])um\b(?![_`])")


@pytest.fixture
def log_file(tmp_path):
    path = tmp_path / "run.sqlite"
    with QualityLog(path) as log:
        log.set_quality_class(QC)
        for r in make_run(3, per_board=5):
            log.append(r)
    return path


def _report(log, tmp_path, **env):
    return subprocess.run([sys.executable, "-m", "planer.cli", "report", str(log),
                           "--out", str(tmp_path / "fig")],
                          capture_output=True, cwd=tmp_path, timeout=120,
                          env={**os.environ, **env})


def test_the_report_prints_micrometres_as_the_unit_sign(log_file, tmp_path):
    out = _report(log_file, tmp_path, PYTHONIOENCODING="utf-8")
    assert out.returncode == 0, out.stderr
    text = out.stdout.decode("utf-8")
    assert re.search(r"depth <= [0-9.]+ µm", text) and not BARE_UM.search(text), text


def test_a_terminal_without_the_micro_sign_gets_an_escape_not_an_error(log_file, tmp_path):
    out = _report(log_file, tmp_path, PYTHONIOENCODING="ascii")
    assert out.returncode == 0, out.stderr
    assert re.search(rb"depth <= [0-9.]+ \\xb5m", out.stdout), out.stdout


def test_the_docs_write_micrometres_as_the_unit_sign():
    bare = {}
    for p in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        for n, line in enumerate(p.read_text(encoding="utf-8").splitlines(), 1):
            if BARE_UM.search(line):
                bare.setdefault(p.name, []).append(n)
    assert bare == {}


def _string_literals(path: Path):
    """``(line, text)`` of the string literals of a module that are not docstrings."""
    import io
    import tokenize

    toks = list(tokenize.generate_tokens(io.StringIO(path.read_text(encoding="utf-8")).readline))
    statement_start = (tokenize.INDENT, tokenize.NEWLINE, tokenize.DEDENT, tokenize.ENCODING,
                       tokenize.NL)
    for i, t in enumerate(toks):
        if t.type != tokenize.STRING:
            continue
        prev = toks[i - 1].type if i else tokenize.NEWLINE
        nxt = toks[i + 1].type if i + 1 < len(toks) else tokenize.NEWLINE
        if prev in statement_start and nxt == tokenize.NEWLINE:
            continue  # a docstring
        yield t.start[0], t.string


def test_no_message_or_label_in_the_code_says_um():
    """Every string the code prints, raises or draws: µm (docstrings and identifiers aside)."""
    bare = []
    for package in ("config", "controller", "core", "planer", "plant_sim", "protocol", "vision"):
        for path in sorted((ROOT / package).rglob("*.py")):
            for line, text in _string_literals(path):
                if BARE_UM.search(text):
                    bare.append(f"{path.relative_to(ROOT)}:{line}: {text}")
    assert bare == []
