"""The project's own promises: quick start, CI script, command line shell."""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest

from planer import cli

ROOT = Path(__file__).resolve().parents[1]


def _first_shell_block() -> list[str]:
    text = (ROOT / "README.md").read_text()
    m = re.search(r"```(?:sh|bash|shell)\n(.*?)```", text, re.S)
    assert m, "README has no shell code block"
    return [ln for ln in m.group(1).splitlines() if ln.strip()]


def test_readme_quick_start_has_exactly_two_commands():
    lines = _first_shell_block()
    assert len(lines) == 2
    assert "planer hil" in lines[0] and lines[0].startswith("pip install")
    assert "pytest" in lines[1] and "[test]" in lines[1]


def test_ci_runs_the_readme_test_command_in_a_fresh_venv():
    ci = (ROOT / ".ci" / "run").read_text()
    assert _first_shell_block()[1] in ci.splitlines()
    assert "python3 -m venv" in ci


def test_every_command_is_registered_with_help():
    parser = cli.build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    assert set(sub.choices) == set(cli.COMMANDS)
    for name in cli.COMMANDS:
        assert "not built" not in sub.choices[name].description, name


def test_value_errors_become_one_line_and_exit_2(capsys, monkeypatch):
    def boom(args):
        raise ValueError("bad thing: value 7\nsecond line")

    parser = cli.build_parser()
    monkeypatch.setattr(cli, "build_parser", lambda *_: parser)
    parser._subparsers._group_actions[0].choices["bench"].set_defaults(_run=boom)
    assert cli.main(["bench"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["planer bench: error: bad thing: value 7"]


@pytest.mark.parametrize("argv", [[], ["nonsense"]])
def test_usage_errors_exit_nonzero(argv):
    with pytest.raises(SystemExit) as exc:
        cli.main(argv)
    assert exc.value.code != 0


# ---------------------------------------------------------------- the docs say what is true now

SKIP_DIRS = {".git", ".ci", "venv", ".venv", "runs", "__pycache__", "node_modules", "build",
             "dist", ".hypothesis", ".pytest_cache", ".ruff_cache"}
"""Folders that are not the project's own text: tools, environments, generated output."""

ISSUE_REF = re.compile(r"\b[Ii]ssues?[ _#-]*\d+|\(#\d+\)")
"""A tracker number (the word, then a number; or a number after ``#`` in parentheses): a reader
of the repository cannot look it up, so only the changelog may name one."""

PATH_REF = re.compile(
    r"(?<![\w./~<>$*-])((?:[\w.*-]+/)+[\w.*-]+"
    r"\.(?:py|md|toml|dbc|json|jsonl|png|csv|js|html|css|svg|txt|sh|sqlite))(?![\w/<>*-])"
)
"""A relative path to a file (``controller/service/service.py``, ``docs/frames.md``)."""

MODULE_FILE_REF = re.compile(r"(?<![\w./<>-])([A-Za-z_]\w*\.py)\b")
"""A module named by its file alone (``records.py``)."""

PACKAGES = ("core", "config", "protocol", "vision", "controller", "plant_sim", "planer")
DOTTED_REF = re.compile(r"(?<![\w./-])((?:" + "|".join(PACKAGES) + r")(?:\.\w+)+)(?![\w/])")
"""A module or its attribute by dotted name (``controller.service.latency.IdleCollector``)."""

DIARY_HEADING = re.compile(
    r"\d{4}-\d{2}-\d{2}|\b(morning|afternoon|evening|night|tonight|today|yesterday|session)\b",
    re.I,
)
"""What a lab notebook's headings carry and a reference's do not: dates, times of day,
sessions. History goes to CHANGELOG.md."""


def _project_files(*suffixes: str) -> list[Path]:
    out = []
    for folder, dirs, files in os.walk(ROOT):
        dirs[:] = [d for d in dirs if d not in SKIP_DIRS and not d.endswith(".egg-info")]
        out += [Path(folder, f) for f in files if f.endswith(suffixes)]
    return sorted(out)


def _docs() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def _issue_refs(text: str) -> list[str]:
    return [m.group(0) for m in ISSUE_REF.finditer(text)]


def _tree_roots() -> set[str]:
    return {p.name for p in ROOT.iterdir() if p.is_dir() and p.name not in SKIP_DIRS} | {".ci"}


def _missing_paths(text: str) -> list[str]:
    """Paths into the tree that ``text`` names and the tree does not hold.

    Only paths that start at one of the repository's own top-level folders are the tree's
    (``runs/...`` is generated, ``DIR/results.csv`` and ``shots/*.png`` are the user's); a glob
    must match at least one file.
    """
    roots = _tree_roots()
    missing = []
    for m in PATH_REF.finditer(text):
        path = m.group(1)
        if path.split("/", 1)[0] not in roots:
            continue
        found = any(ROOT.glob(path)) if "*" in path else (ROOT / path).exists()
        if not found:
            missing.append(path)
    return missing


def _missing_module_files(text: str, names: set[str]) -> list[str]:
    return [m.group(1) for m in MODULE_FILE_REF.finditer(text) if m.group(1) not in names]


def _resolves(dotted: str) -> bool:
    """Whether a dotted name is a module of the tree, or a name inside one of its packages."""
    parts = dotted.split(".")
    if parts[-1] in {"py", "md", "toml", "dbc", "json", "csv", "png", "sqlite"}:
        return True  # a file name (``config.toml``), not a module
    folder = ROOT / parts[0]
    for part in parts[1:]:
        if (folder / part / "__init__.py").exists():
            folder = folder / part
            continue
        if (folder / f"{part}.py").exists():
            return True
        init = folder / "__init__.py"
        return init.exists() and re.search(rf"\b{re.escape(part)}\b", init.read_text()) is not None
    return True


def test_no_issue_numbers_in_source_or_docs():
    offenders = []
    for path in _project_files(".py", ".md", ".toml"):
        if path == ROOT / "CHANGELOG.md":
            continue
        for n, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            if _issue_refs(line):
                offenders.append(f"{path.relative_to(ROOT)}:{n}: {line.strip()[:80]}")
    assert offenders == []


def test_the_issue_pattern_catches_every_spelling_and_nothing_else():
    word = "iss" + "ue"  # spelt apart so this file holds no tracker number itself
    for text in (f"{word} 11", f"{word.title()} 8 item 3", f"({word} 14)", f"{word}10.toml",
                 f"{word}s 10 and 11", f"{word} #12", f"{word}-12 steps", "see (" + "#7)"):
        assert _issue_refs(text), text
    for text in (f"the {word} of the day", f"t{word} 3", f"{word}s remain", "item 3", "#7"):
        assert not _issue_refs(text), text


def test_every_path_the_readme_and_docs_name_exists():
    names = {p.name for p in _project_files(".py")}
    missing = []
    for doc in _docs():
        text = doc.read_text()
        where = doc.relative_to(ROOT)
        missing += [f"{where}: {p}" for p in _missing_paths(text)]
        missing += [f"{where}: {p}" for p in _missing_module_files(text, names)]
        missing += [f"{where}: {d}" for d in {m.group(1) for m in DOTTED_REF.finditer(text)}
                    if not _resolves(d)]
    assert missing == []


def test_the_path_checks_find_what_is_gone_and_allow_what_is_not_the_trees():
    assert _missing_paths("`controller/service/service.py`, `docs/frames.md`") == []
    assert _missing_paths("`controller/safety.py` and docs/helper_notes.md") == [
        "controller/safety.py", "docs/helper_notes.md"]
    assert _missing_paths("`tests/controller/laws/test_control_*.py`") == []
    assert _missing_paths("`tests/test_nothing_like_this_*.py`") == [
        "tests/test_nothing_like_this_*.py"]
    assert _missing_paths("runs/hil-<time>.sqlite, runs/spool/pair-1.json, DIR/results.csv, "
                          "shots/*.png, <name>/x.py, /etc/planer/machine.toml") == []
    names = {p.name for p in _project_files(".py")}
    assert _missing_module_files("`records.py`, `pool.py`", names) == []
    assert _missing_module_files("`frame_source.py`", names) == ["frame_source.py"]
    assert _resolves("controller.service.latency.IdleCollector")
    assert _resolves("controller.frames.camera.latches")
    assert not _resolves("controller.measure_workers")
    assert not _resolves("planer.hil.no_such_module")


def test_docs_have_no_diary_headings():
    dated = []
    for doc in _docs():
        for n, line in enumerate(doc.read_text().splitlines(), 1):
            if line.startswith("#") and DIARY_HEADING.search(line):
                dated.append(f"{doc.relative_to(ROOT)}:{n}: {line}")
    assert dated == []
    assert DIARY_HEADING.search("## Second pass (2026-11-25, afternoon)")
    assert DIARY_HEADING.search("**Late evening**: the replies") and DIARY_HEADING.search(
        "## This session: who owns what")
    assert not DIARY_HEADING.search("## Latency (`planer bench`, `service` part)")


def test_readme_first_shell_block_is_exactly_two_lines():
    text = (ROOT / "README.md").read_text()
    m = re.search(r"```(?:sh|bash|shell)\n(.*?)```", text, re.S)
    assert m, "README has no shell code block"
    assert m.group(1).splitlines() == [
        "pip install -e . && planer hil",
        "pip install -e '.[test]' && python -m pytest -q",
    ]
